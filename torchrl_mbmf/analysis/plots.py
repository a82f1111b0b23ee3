"""Figures of the report: learning curves over seeds, scalars per group, gait comparisons."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from torchrl_mbmf.analysis.gait import GaitMetrics
from torchrl_mbmf.analysis.runs import Curve


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curves(
    curves: Mapping[str, Curve],
    path: str | Path,
    *,
    title: str = "",
    ylabel: str = "return, mean of last 10 episodes",
    xlabel: str = "real environment steps (random-data steps included)",
    vlines: Mapping[str, float] | None = None,
    hline: float | None = None,
    hline_label: str = "reference maximum",
    band: bool = True,
    anchors: Mapping[str, Sequence[tuple[float, float, float]]] | None = None,
) -> None:
    """Plots across-seed curves: IQM line, 95% bootstrap interval and the min-max band.

    The thesis' figures show the mean of the last 10 episodes with the min-max of those 10
    episodes shaded; here the line is the IQM over seeds of that mean, the darker shade its 95%
    bootstrap interval and the light shade the min-max band over seeds and episodes. Where
    some of a curve's seeds have stopped (interrupted runs), its line is dashed.

    Args:
        curves: ``{label: curve}``.
        path: PNG file to write.

    Keyword Args:
        title: figure title.
        ylabel: y-axis label (with units).
        xlabel: x-axis label.
        vlines: ``{label: step}`` dashed vertical lines (for example the switch to fine-tuning).
        hline: a dotted horizontal line (for example the PPO maximum).
        hline_label: legend of ``hline``.
        band: draw the min-max band. Defaults to ``True``.
        anchors: ``{label: [(step, low, high), ...]}`` published numbers drawn in grey beside
            the curves: a marker where ``low == high``, a vertical bar for a range.

    Examples:
        >>> import tempfile, os
        >>> import numpy as np
        >>> from torchrl_mbmf.analysis.runs import Curve
        >>> from torchrl_mbmf.analysis.plots import plot_curves
        >>> x = np.array([1, 2, 3]); y = np.array([0.0, 1.0, 2.0])
        >>> c = Curve(x, y, y - 1, y + 1, y - 2, y + 2, y[None], [0])
        >>> with tempfile.TemporaryDirectory() as d:
        ...     plot_curves({"ppo": c}, os.path.join(d, "c.png"), hline=1.5)
        >>> two = Curve(x, y, y, y, y, y, np.array([y, [0.0, 1.0, np.nan]]), [0, 1])
        >>> with tempfile.TemporaryDirectory() as d:  # seed 1 stops: dashed after step 2
        ...     plot_curves({"ppo": two}, os.path.join(d, "c.png"))
        >>> with tempfile.TemporaryDirectory() as d:  # a published point and a published range
        ...     plot_curves({"ppo": c}, os.path.join(d, "c.png"),
        ...                 anchors={"MBPO": [(3, 2.5, 2.5)], "SAC": [(3, 1.0, 1.5)]})
    """
    plt = _pyplot()
    # published anchors add legend rows: the legend then goes beside the axes, not over them
    fig, ax = plt.subplots(figsize=(10.5, 4.8) if anchors else (7.5, 4.5))
    for i, (label, c) in enumerate(curves.items()):
        color = f"C{i}"
        n = len(c.seeds)
        counts = np.isfinite(np.asarray(c.per_seed, dtype=float)).sum(0)
        fewer = (counts < n) & np.isfinite(c.iqm)
        ax.plot(
            c.steps,
            np.where(fewer, np.nan, c.iqm),
            color=color,
            label=f"{label} (IQM, {n} seed{'s' * (n != 1)})",
        )
        if fewer.any():
            # dashed where some seeds have stopped (joined to the solid part it follows)
            joined = fewer | np.append(fewer[1:], False)
            ax.plot(
                c.steps,
                np.where(joined, c.iqm, np.nan),
                color=color,
                linestyle="--",
                label=f"{label}, fewer seeds (as few as {int(counts[fewer].min())})",
            )
        ax.fill_between(c.steps, c.low, c.high, color=color, alpha=0.3, linewidth=0)
        if band:
            ax.fill_between(c.steps, c.band_min, c.band_max, color=color, alpha=0.08, linewidth=0)
    for j, (label, step) in enumerate((vlines or {}).items()):
        ax.axvline(step, color="k", linestyle="--", linewidth=1, alpha=0.6 - 0.15 * j, label=label)
    for j, (label, rows) in enumerate((anchors or {}).items()):
        steps, low, high = (np.asarray(v, dtype=float) for v in zip(*rows, strict=True))
        marker = "osD^v<>ph*"[j % 10]
        ax.plot(
            steps,
            (low + high) / 2,
            linestyle="none",
            marker=marker,
            color="0.35",
            markerfacecolor="none",
            label=f"{label} (published)",
        )
        ranged = high > low
        if ranged.any():
            ax.vlines(steps[ranged], low[ranged], high[ranged], color="0.35", linewidth=1.5)
    if hline is not None:
        ax.axhline(hline, color="k", linestyle=":", linewidth=1, label=hline_label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    if anchors:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:
        ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_gait_comparison(metrics: Mapping[str, GaitMetrics], path: str | Path) -> None:
    """Compares the gaits of several policies (thesis figures 14, 15 and 16 side by side).

    Args:
        metrics: ``{label: gait metrics}``, for example one per reward.
        path: PNG file to write.

    Examples:
        >>> import tempfile, os
        >>> from torchrl_mbmf.analysis.gait import GaitMetrics
        >>> from torchrl_mbmf.analysis.plots import plot_gait_comparison
        >>> m = GaitMetrics(["a", "b"], [1.0, -1.0], [1.0, 1.0], [0.1, 0.2], [0.0, 0.1], 0.1, 0.05)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     plot_gait_comparison({"default": m, "shin_pen": m}, os.path.join(d, "g.png"))
    """
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    labels = list(metrics)
    joints = next(iter(metrics.values())).joints
    width = 0.8 / max(1, len(labels))
    x = np.arange(len(joints))
    for i, label in enumerate(labels):
        m = metrics[label]
        axes[0].bar(x + i * width, m.average_power, width, label=label)
        t = np.arange(1, len(m.torso_height) + 1)
        axes[1].plot(t, m.torso_height, label=f"{label} (std {m.height_std:.3f} m)")
        axes[2].plot(t, m.x_position, label=f"{label} ({m.distance:.2f} m)")
    axes[0].set_xticks(x + width * (len(labels) - 1) / 2, joints, rotation=30)
    axes[0].set_ylabel("average power, torque x angular velocity (W)")
    axes[0].set_title("power per joint (eq. 20, figure 14)")
    axes[1].set_xlabel("time step (0.05 s)")
    axes[1].set_ylabel("torso height (m)")
    axes[1].set_title("vertical displacement (figure 15)")
    axes[2].set_xlabel("time step (0.05 s)")
    axes[2].set_ylabel("torso x position (m)")
    axes[2].set_title("forward motion (figure 16)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def save_image(image: np.ndarray, path: str | Path) -> None:
    """Writes an ``[H, W, 3]`` ``uint8`` image as PNG.

    Args:
        image: the pixels.
        path: PNG file to write.

    Examples:
        >>> import tempfile, os
        >>> import numpy as np
        >>> from torchrl_mbmf.analysis.plots import save_image
        >>> with tempfile.TemporaryDirectory() as d:
        ...     save_image(np.zeros((4, 6, 3), dtype=np.uint8), os.path.join(d, "f.png"))
    """
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"image must be [H, W, 3], got shape {image.shape}")
    _pyplot().imsave(path, image)


__all__ = ["plot_curves", "plot_gait_comparison", "save_image"]
