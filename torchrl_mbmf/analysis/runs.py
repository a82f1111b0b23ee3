"""Reading training run folders and turning them into across-seed curves and tables.

A run folder written by ``recipes/train.py`` holds ``config.yaml``, ``logs/scalars/<group>/
<name>.csv`` (rows ``step,value``, the step being the global real-step count) and, once finished,
``summary.json``. The functions here load such folders (finished or interrupted), aggregate a
scalar over seeds on a common step grid with the interquartile mean and a bootstrap confidence
interval, and compute the thesis' "PPO-maximum" sample-efficiency table (table 10).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchrl_mbmf.analysis.stats import Interval, bootstrap_ci, first_step_reaching
from torchrl_mbmf.methods import MODEL_BASED
from torchrl_mbmf.runs.export import variant_tag
from torchrl_mbmf.runs.layout import CONFIG, RunFolder

#: The methods that fit a world model on random data first (``sac_mbpo`` included).
MODEL_BASED_METHODS = MODEL_BASED
RETURN_CURVE = "train/return_last10_mean"


@dataclass
class Run:
    r"""One training run folder.

    Attributes:
        path: the run folder.
        config: its resolved config (``config.yaml``) as a dict.
        summary: ``summary.json`` as a dict, or ``None`` for a run that has not finished.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> (d / "logs/scalars/train").mkdir(parents=True)
        >>> _ = (d / "logs/scalars/train/episode_return.csv").write_text("1000,5.0\n2000,7.0\n")
        >>> run = Run(d, {"method": "ppo", "seed": 0}, None)
        >>> run.scalar("train/episode_return")[1].tolist(), run.last_step, run.complete
        ([5.0, 7.0], 2000, False)
    """

    path: Path
    config: dict[str, Any]
    summary: dict[str, Any] | None = None
    _cache: dict[str, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, repr=False, init=False
    )

    @property
    def name(self) -> str:
        """The run folder's name."""
        return self.path.name

    @property
    def method(self) -> str:
        """The training method: one of :data:`torchrl_mbmf.methods.METHODS`."""
        return str(self.config["method"])

    @property
    def reward(self) -> str:
        """The reward variant's name."""
        return str(self.config.get("reward", {}).get("name", "default"))

    @property
    def horizon(self) -> int:
        """The planning horizon (meaningful for model-based methods only)."""
        return int(self.config.get("planner", {}).get("horizon", 0))

    @property
    def variant(self) -> str:
        """Beyond-the-thesis options of the run (``""`` for the thesis' planner and model)."""
        tag = variant_tag(self.config.get("planner", {}), self.config.get("world_model", {}))
        return tag.removeprefix("__")

    @property
    def seed(self) -> int:
        """The run's seed."""
        return int(self.config["seed"])

    @property
    def total_steps(self) -> int:
        """The configured budget of real steps."""
        return int(self.config.get("total_steps", 0))

    @property
    def complete(self) -> bool:
        """Whether the run finished (it wrote ``summary.json``)."""
        return self.summary is not None

    @property
    def random_steps(self) -> int:
        """Random-policy real steps collected to fit the first world model (0 if model-free)."""
        if self.summary is not None and "random_steps" in self.summary:
            return int(self.summary["random_steps"])
        if self.method in MODEL_BASED_METHODS:
            return int(self.config["world_model"]["random_steps"])
        return 0

    @property
    def switch_step(self) -> int | None:
        """Real step at which planning stops and pure PPO fine-tuning starts (MPC methods)."""
        if self.method not in ("mpc", "ppo_mpc"):
            return None
        frames = int(self.config["ppo"]["frames_per_batch"])
        return self.random_steps + int(self.config["planning_updates"]) * frames

    @property
    def commit(self) -> str:
        """The git commit the run's code came from (``"unknown"`` if not recorded)."""
        return RunFolder(self.path).read_commit()

    @property
    def machine(self) -> dict[str, Any]:
        """``machine.json``: Python, torch and torchrl versions, CPU count (empty if absent)."""
        return RunFolder(self.path).read_machine()

    @property
    def wall_seconds(self) -> float | None:
        """Wall time of the training loop over the work the run kept (``None`` if not logged).

        :meth:`wall_seconds_to` the run's last logged step.
        """
        return self.wall_seconds_to(None)

    def wall_seconds_to(self, step: int | None) -> float | None:
        r"""Wall time of the training loop up to real step ``step`` (``None``: the whole run).

        A run resumed after an interruption ran in several processes (``resume_log.json``
        gives the real step each resumed from). Each process logs ``time/steps_per_s``, its
        real steps per second since it started; its last row up to ``step`` and to the step the
        next one resumed from gives its time. Work done after an interruption's last checkpoint,
        which was thrown away and redone, is not counted. Falls back to the summary's
        ``seconds`` (:meth:`summary_at`) where the rate was not logged.

        Args:
            step: the real step to time up to (a logged row's step, such as a budget the run
                finished at); ``None`` for all of it.

        Examples:
            >>> import tempfile, pathlib
            >>> from torchrl_mbmf.analysis.runs import Run
            >>> d = pathlib.Path(tempfile.mkdtemp())
            >>> (d / "logs/scalars/time").mkdir(parents=True)
            >>> _ = (d / "logs/scalars/time/steps_per_s.csv").write_text("1000,10\n2000,10\n")
            >>> run = Run(d, {"method": "sac", "seed": 0})
            >>> run.wall_seconds_to(1000), run.wall_seconds
            (100.0, 200.0)
        """
        steps, rates = self.scalar("time/steps_per_s")
        if not steps.size:
            summary = self.summary if step is None else self.summary_at(step)
            return None if summary is None else summary.get("seconds")
        total = 0.0
        for begin, end in self._bounds():
            last = min(c for c in (end, step, int(steps[-1])) if c is not None)
            rows = np.nonzero((steps > begin) & (steps <= last))[0]
            if rows.size:
                total += (steps[rows[-1]] - begin) / rates[rows[-1]]
        return float(total)

    @property
    def resumed_from(self) -> int:
        """The real step the run's last process resumed from (0 for a run never resumed).

        ``summary.json``'s ``seconds`` and ``time_breakdown`` cover that last process only.

        Examples:
            >>> import tempfile, pathlib
            >>> from torchrl_mbmf.analysis.runs import Run
            >>> d = pathlib.Path(tempfile.mkdtemp())
            >>> Run(d, {"method": "sac", "seed": 0}).resumed_from
            0
            >>> _ = (d / "resume_log.json").write_text('[{"event": "resume", "real_steps": 20500}]')
            >>> Run(d, {"method": "sac", "seed": 0}).resumed_from
            20500
        """
        return self._resume_steps()[-1]

    def segments(self) -> list[tuple[int, int]]:
        """``(start, end)`` real steps of each process whose logged rows the run kept, in order.

        Each process logged the rows past its start up to its end: the step the next process
        resumed from (a resume cuts the rows past its checkpoint), or the run's last step.

        Examples:
            >>> import tempfile, pathlib
            >>> from torchrl_mbmf.analysis.runs import Run
            >>> d = pathlib.Path(tempfile.mkdtemp())
            >>> _ = (d / "resume_log.json").write_text('[{"event": "resume", "real_steps": 500}]')
            >>> Run(d, {"method": "sac", "seed": 0}, {"real_steps": 1000}).segments()
            [(0, 500), (500, 1000)]
        """
        return [(b, self.last_step if e is None else e) for b, e in self._bounds()]

    def _bounds(self) -> list[tuple[int, int | None]]:
        """:meth:`segments` with ``None`` for the last one's end (all its rows)."""
        starts = self._resume_steps()
        ends = [min(starts[i + 1 :], default=None) for i in range(len(starts))]
        return [(b, e) for b, e in zip(starts, ends, strict=True) if e is None or e > b]

    def _resume_steps(self) -> list[int]:
        """0, then the real step of each resume in ``resume_log.json``, in order."""
        return [0] + [int(e["real_steps"]) for e in self._resume_events()]

    def summary_at(self, step: int) -> dict[str, Any] | None:
        """The summary the run wrote when it finished at real step ``step`` (``None``: it did not).

        A finished run continued to a raised budget (``total_steps``) keeps its earlier summary
        in ``resume_log.json`` (``previous_summary`` of the resume that continued it).

        Args:
            step: the real step, such as an earlier budget of the run.

        Examples:
            >>> import tempfile, pathlib
            >>> from torchrl_mbmf.analysis.runs import Run
            >>> d = pathlib.Path(tempfile.mkdtemp())
            >>> _ = (d / "resume_log.json").write_text(
            ...     '[{"event": "resume", "real_steps": 1000, '
            ...     '"previous_summary": {"real_steps": 1000, "seconds": 4.0}}]')
            >>> run = Run(d, {"method": "sac", "seed": 0})
            >>> run.summary_at(1000)["seconds"], run.summary_at(2000)
            (4.0, None)
        """
        return next((s for s in self._summaries() if int(s["real_steps"]) == step), None)

    def finished_at(self) -> list[int]:
        """The real steps at which the run wrote a summary, earlier budgets included."""
        return sorted({int(s["real_steps"]) for s in self._summaries()})

    def _summaries(self) -> list[dict[str, Any]]:
        """Every summary the run wrote: those kept in its resume log, then ``summary.json``."""
        events = RunFolder(self.path).read_resume_log()
        summaries = [e.get("previous_summary") for e in events] + [self.summary]
        return [s for s in summaries if s is not None]

    def segment_start(self, step: int) -> int:
        """The real step the process that logged real step ``step`` resumed from (0: it started).

        That process is the last to start before ``step`` (a resume cuts the rows past its
        checkpoint). A summary's ``seconds`` and ``time_breakdown`` (:meth:`summary_at`) cover
        it.

        Args:
            step: a real step the run logged.
        """
        return self._resume_steps()[self._segment(step)]

    def machine_at(self, step: int) -> dict[str, Any]:
        """``machine.json`` of the process that logged real step ``step`` (empty if not kept).

        The folder's ``machine.json`` is the last process's; each resume keeps the one it
        replaces in its ``resume_log.json`` entry (``previous_machine``; older entries lack it).

        Args:
            step: a real step the run logged.
        """
        after = self._resume_events()[self._segment(step) :]
        return dict(after[0].get("previous_machine", {})) if after else self.machine

    def commit_at(self, step: int) -> str:
        """The git commit of the process that logged real step ``step`` (``"unknown"``).

        Kept like :meth:`machine_at`'s record (``previous_commit``).

        Args:
            step: a real step the run logged.
        """
        after = self._resume_events()[self._segment(step) :]
        return str(after[0].get("previous_commit", "unknown")) if after else self.commit

    def _resume_events(self) -> list[dict[str, Any]]:
        """The ``resume`` entries of ``resume_log.json``, in order."""
        return [e for e in RunFolder(self.path).read_resume_log() if e.get("event") == "resume"]

    def _segment(self, step: int) -> int:
        """Index into :meth:`_resume_steps` of the process that logged real step ``step``."""
        return max(i for i, s in enumerate(self._resume_steps()) if s < step or i == 0)

    @property
    def refit_seconds(self) -> float:
        """Seconds spent fitting the world model, over every fit the run logged (0 model-free)."""
        return float(self.scalar("time/model_fit_s")[1].sum())

    @property
    def last_step(self) -> int:
        """The last real step the run logged (its progress if interrupted)."""
        if self.summary is not None:
            return int(self.summary["real_steps"])
        ends = [self.scalar(n)[0] for n in ("train/episode_return", RETURN_CURVE)]
        return max((int(s[-1]) for s in ends if s.size), default=0)

    def scalar(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Loads a logged scalar as ``(steps, values)`` arrays (empty if never logged).

        Args:
            name: the scalar's name, for example ``"train/return_last10_mean"``.
        """
        if name not in self._cache:
            self._cache[name] = RunFolder(self.path).read_scalar(name)
        return self._cache[name]


def load_runs(roots: str | Path | Iterable[str | Path], *, dedupe: bool = True) -> list[Run]:
    r"""Finds every run folder (one with ``config.yaml`` and ``logs/scalars``) under ``roots``.

    Args:
        roots: one folder or several, searched recursively.

    Keyword Args:
        dedupe: when the same run (folder name) is found under several roots, keep only the
            one that got furthest (finished runs first, then the most real steps). Defaults to
            ``True``.

    Returns:
        The runs, sorted by folder name.

    Raises:
        FileNotFoundError: a root does not exist.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import load_runs
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> (d / "a/logs/scalars").mkdir(parents=True)
        >>> _ = (d / "a/config.yaml").write_text("method: ppo\nseed: 1\n")
        >>> [(r.name, r.method, r.seed) for r in load_runs(d)]
        [('a', 'ppo', 1)]
    """
    if isinstance(roots, str | Path):
        roots = [roots]
    runs = []
    for root in roots:
        root = Path(root)
        if not root.exists():
            raise FileNotFoundError(f"run root {root} does not exist")
        for cfg_path in sorted(root.rglob(CONFIG)):
            folder = RunFolder(cfg_path.parent)
            if not folder.is_training_run():
                continue  # Hydra's own .hydra/config.yaml, or a world-model job
            runs.append(Run(folder.path, folder.read_config(), folder.read_summary()))
    if dedupe:
        best: dict[str, Run] = {}
        for run in runs:
            kept = best.get(run.name)
            if kept is None or (run.complete, run.last_step) > (kept.complete, kept.last_step):
                best[run.name] = run
        runs = list(best.values())
    return sorted(runs, key=lambda r: r.name)


def group_runs(
    runs: Iterable[Run], keys: Sequence[str] = ("method", "reward", "horizon", "variant")
) -> dict[tuple[Any, ...], list[Run]]:
    """Groups runs that differ only by seed.

    Args:
        runs: the runs.
        keys: :class:`Run` attributes that define a group. Defaults to method, reward, horizon
            and variant.

    Returns:
        ``{key tuple: runs sorted by seed}``.

    Examples:
        >>> from pathlib import Path
        >>> from torchrl_mbmf.analysis.runs import Run, group_runs
        >>> runs = [Run(Path(f"r{s}"), {"method": "ppo", "seed": s}) for s in (1, 0)]
        >>> {k: [r.seed for r in v] for k, v in group_runs(runs, ["method"]).items()}
        {('ppo',): [0, 1]}
    """
    groups: dict[tuple[Any, ...], list[Run]] = {}
    for run in runs:
        groups.setdefault(tuple(getattr(run, k) for k in keys), []).append(run)
    return {k: sorted(v, key=lambda r: r.seed) for k, v in sorted(groups.items())}


@dataclass
class Curve:
    """A scalar aggregated over seeds on a grid of real steps.

    Attributes:
        steps: the grid (real steps).
        iqm: interquartile mean over seeds at each grid step (NaN where no seed has data).
        low: lower bound of the 95% bootstrap interval of the IQM.
        high: upper bound of the interval.
        band_min: minimum over seeds of the last-10-episode minimum (the thesis' shaded band;
            equal to the seeds' minimum of the scalar itself for other scalars).
        band_max: maximum over seeds of the last-10-episode maximum.
        per_seed: ``[seeds, grid]`` values of each seed.
        seeds: the seeds.

    Examples:
        >>> import numpy as np
        >>> from torchrl_mbmf.analysis.runs import Curve
        >>> c = Curve(*(np.zeros(2) for _ in range(6)), np.zeros((1, 2)), [0])
        >>> c.steps.shape
        (2,)
    """

    steps: np.ndarray
    iqm: np.ndarray
    low: np.ndarray
    high: np.ndarray
    band_min: np.ndarray
    band_max: np.ndarray
    per_seed: np.ndarray
    seeds: list[int]

    def to_dict(self) -> dict[str, list]:
        """The curve as JSON-serialisable lists (NaN as ``None``)."""

        def clean(a: np.ndarray) -> list:
            return [None if not np.isfinite(x) else float(x) for x in np.ravel(a)]

        return {
            "steps": [int(s) for s in self.steps],
            "iqm": clean(self.iqm),
            "low": clean(self.low),
            "high": clean(self.high),
            "band_min": clean(self.band_min),
            "band_max": clean(self.band_max),
            "seeds": list(self.seeds),
        }


def _on_grid(steps: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Last value carried forward onto ``grid``; NaN before the first and after the last log."""
    idx = np.searchsorted(steps, grid, side="right") - 1
    out = np.full(grid.shape, np.nan)
    if steps.size:
        ok = (idx >= 0) & (grid <= steps[-1])
        out[ok] = values[idx[ok]]
    return out


#: Episodes in the window of the logged ``train/return_last10_*`` scalars.
LAST_EPISODES = 10


def _policy_points(run: Run, name: str, policy_only: bool) -> tuple[np.ndarray, np.ndarray]:
    """``run.scalar(name)``, or with ``policy_only`` only what the run's own policy earned.

    For a run with a random-data phase, ``policy_only`` keeps the values logged from the end of
    its 10th episode after that phase on (before it, the last-10-episode window still holds
    random-policy episodes), or, where the run logged no episodes, those logged after the
    phase. A run without such a phase keeps everything.
    """
    steps, values = run.scalar(name)
    if not policy_only or run.random_steps <= 0:
        return steps, values
    episode_steps = run.scalar("train/episode_return")[0]
    own = episode_steps[episode_steps > run.random_steps]
    if not episode_steps.size:
        keep = steps > run.random_steps
    elif own.size >= LAST_EPISODES:
        keep = steps >= own[LAST_EPISODES - 1]
    else:
        keep = np.zeros(steps.shape, dtype=bool)
    return steps[keep], values[keep]


def aggregate_curve(
    runs: Sequence[Run],
    name: str = RETURN_CURVE,
    *,
    grid: np.ndarray | None = None,
    points: int = 100,
    exclude_random: bool = False,
    policy_only: bool = False,
    until: int | None = None,
    min_seeds: int = 1,
    n_resamples: int = 1000,
) -> Curve:
    r"""Aggregates one scalar of several seeds on a common grid of real steps.

    Each seed's curve is read with its last value carried forward (up to the seed's last logged
    step: an interrupted seed stops contributing there). At each grid step the seeds are reduced
    with the IQM and a 95% percentile-bootstrap interval.

    Args:
        runs: runs of one configuration (different seeds).
        name: the scalar. Defaults to the mean of the last 10 episode returns.

    Keyword Args:
        grid: real steps to read at; by default ``points`` steps up to the longest run.
        points: grid size when ``grid`` is not given. Defaults to ``100``.
        exclude_random: subtract each run's random-data steps from its step axis (the thesis'
            "without random steps" count). Defaults to ``False``: every real step counts.
        policy_only: read only what each run's own policy earned: a run with a random-data
            phase contributes the values it logged from the end of its 10th episode after that
            phase on (until then the last-10-episode window holds random-policy episodes).
            Defaults to ``False``: every logged value.
        until: only values logged at real steps up to this count (before any shift by
            ``exclude_random``). Defaults to ``None``: all.
        min_seeds: the aggregate is NaN at grid steps where fewer seeds have a value (so a
            curve does not silently turn into the mean of fewer seeds). Defaults to ``1``.
        n_resamples: bootstrap resamples per grid step. Defaults to ``1000``.

    Returns:
        A :class:`Curve`.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run, aggregate_curve
        >>> runs = []
        >>> for seed in range(3):
        ...     d = pathlib.Path(tempfile.mkdtemp())
        ...     (d / "logs/scalars/train").mkdir(parents=True)
        ...     rows = "".join(f"{s},{s / 100 + seed}\n" for s in (100, 200, 300))
        ...     _ = (d / "logs/scalars/train/return_last10_mean.csv").write_text(rows)
        ...     runs.append(Run(d, {"method": "ppo", "seed": seed}))
        >>> aggregate_curve(runs, grid=[100, 300]).iqm.tolist()
        [2.0, 4.0]
    """
    if not runs:
        raise ValueError("aggregate_curve needs at least one run")
    if not isinstance(min_seeds, int) or isinstance(min_seeds, bool) or min_seeds < 1:
        raise ValueError(f"min_seeds must be an integer >= 1, got {min_seeds!r}")

    def points(run: Run, key: str) -> tuple[np.ndarray, np.ndarray]:
        steps, values = _policy_points(run, key, policy_only)
        if until is not None and steps.size and steps[-1] > until:
            # the run went on: its last value up to ``until`` holds until then
            keep = steps <= until
            steps = np.append(steps[keep], until)
            values = np.append(values[keep], values[keep][-1:] if keep.any() else np.nan)
        return steps, values

    shifted = []
    for run in runs:
        steps, values = points(run, name)
        offset = run.random_steps if exclude_random else 0
        shifted.append((steps - offset, values, offset))
    if grid is None:
        end = max((s[-1] for s, _, _ in shifted if s.size), default=0)
        grid = np.linspace(0, end, points + 1)[1:].round().astype(np.int64)
    grid = np.asarray(grid, dtype=np.int64)
    per_seed = np.stack([_on_grid(s, v, grid) for s, v, _ in shifted])
    band_lo, band_hi = per_seed.copy(), per_seed.copy()
    if name == RETURN_CURVE:
        for i, run in enumerate(runs):
            off = shifted[i][2]
            for key, out in (
                ("train/return_last10_min", band_lo),
                ("train/return_last10_max", band_hi),
            ):
                s, v = points(run, key)
                if s.size:
                    out[i] = _on_grid(s - off, v, grid)
    center, low, high = (np.full(grid.shape, np.nan) for _ in range(3))
    for j in range(grid.size):
        col = per_seed[:, j]
        col = col[np.isfinite(col)]
        if col.size >= min_seeds:
            ci = bootstrap_ci(col, n_resamples=n_resamples, seed=j)
            center[j], low[j], high[j] = ci.estimate, ci.low, ci.high
    with np.errstate(all="ignore"):
        all_nan = ~np.isfinite(band_lo).any(0)
        band_min = np.where(
            all_nan, np.nan, np.nanmin(np.where(np.isfinite(band_lo), band_lo, np.inf), 0)
        )
        band_max = np.where(
            all_nan, np.nan, np.nanmax(np.where(np.isfinite(band_hi), band_hi, -np.inf), 0)
        )
    return Curve(grid, center, low, high, band_min, band_max, per_seed, [r.seed for r in runs])


def final_values(
    runs: Sequence[Run], name: str = RETURN_CURVE, *, at_step: int | None = None
) -> list[float]:
    r"""Each seed's value of a scalar at ``at_step`` (last value logged at or before it).

    Args:
        runs: runs of one configuration.
        name: the scalar. Defaults to the mean of the last 10 episode returns.

    Keyword Args:
        at_step: the real step; by default each run's last logged value.

    Returns:
        One value per run that logged the scalar by then; a run without data, or one that
        stopped before ``at_step`` (its value there is unknown), is left out.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run, final_values
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> (d / "logs/scalars/train").mkdir(parents=True)
        >>> _ = (d / "logs/scalars/train/return_last10_mean.csv").write_text("10,1.0\n20,3.0\n")
        >>> final_values([Run(d, {"method": "ppo", "seed": 0})], at_step=15)
        [1.0]
    """
    out = []
    for run in runs:
        steps, values = run.scalar(name)
        if at_step is not None:
            if run.last_step < at_step:
                continue
            keep = steps <= at_step
            steps, values = steps[keep], values[keep]
        if values.size:
            out.append(float(values[-1]))
    return out


def compare_intervals(a: Interval, b: Interval) -> str:
    """Compares two bootstrap intervals: ``"higher"``, ``"lower"`` or ``"overlapping"``.

    An interval over a single seed is a point, not an interval, so any comparison involving one
    is ``"one seed"``: never read as a difference.

    Args:
        a: the interval of the first configuration.
        b: the interval of the second.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import Interval
        >>> from torchrl_mbmf.analysis.runs import compare_intervals
        >>> compare_intervals(Interval(5, 4, 6, 0.95, 3), Interval(1, 0, 2, 0.95, 3))
        'higher'
        >>> compare_intervals(Interval(5, 5, 5, 0.95, 1), Interval(1, 0, 2, 0.95, 3))
        'one seed'
    """
    if min(a.n, b.n) < 2:
        return "one seed"
    if a.low > b.high:
        return "higher"
    if a.high < b.low:
        return "lower"
    return "overlapping"


def _resampled_iqm(rows: np.ndarray) -> np.ndarray:
    """IQM over axis ``-2`` of resampled seeds, NaN in a column where any drawn seed is NaN.

    As the point estimate (:func:`aggregate_curve` with every seed required), a resample's
    curve exists only where all of its seeds have a value.
    """
    return np.where(np.isnan(rows).any(-2), np.nan, _nan_iqm_columns(rows))


def _nan_iqm_columns(rows: np.ndarray) -> np.ndarray:
    """IQM over axis ``-2`` ignoring NaN (``[..., seeds, grid] -> [..., grid]``; NaN if none)."""
    ordered = np.sort(rows, axis=-2)  # NaN last
    count = np.isfinite(ordered).sum(-2)
    cut = np.floor(0.25 * count).astype(np.int64)  # scipy's trim_mean cut for each column
    sums = np.concatenate(
        [np.zeros_like(ordered[..., :1, :]), np.nan_to_num(ordered, nan=0.0).cumsum(-2)], -2
    )
    upper = np.take_along_axis(sums, (count - cut)[..., None, :], -2)[..., 0, :]
    lower = np.take_along_axis(sums, cut[..., None, :], -2)[..., 0, :]
    kept = count - 2 * cut
    with np.errstate(all="ignore"):
        return np.where(kept > 0, (upper - lower) / kept, np.nan)


def _first_index_reaching(curves: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Per row of ``curves`` ``[B, grid]``, the first index reaching ``threshold`` ``[B]`` (-1)."""
    hit = np.nan_to_num(curves, nan=-np.inf) >= threshold[:, None]
    return np.where(hit.any(-1), hit.argmax(-1), -1)


def ratio_interval(
    reference: np.ndarray,
    candidate: np.ndarray,
    grid: np.ndarray,
    *,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> dict[str, float]:
    r"""Percentile-bootstrap interval of the ratio of the steps to the reference's maximum.

    Each resample draws the seeds of both configurations with replacement (independently),
    takes their IQM curves, the reference curve's maximum as the threshold and the ratio of the
    first grid steps at which the candidate's and the reference's curves reach it. A resample in
    which the candidate never reaches the threshold counts as an infinite ratio, so an upper
    bound of ``inf`` means that more than ``(1 - confidence) / 2`` of the resamples never got
    there.

    Args:
        reference: ``[seeds, grid]`` per-seed curves of the reference (``Curve.per_seed``).
        candidate: ``[seeds, grid]`` per-seed curves of the configuration compared with it.
        grid: the real steps of the curves' columns.

    Keyword Args:
        confidence: confidence level. Defaults to ``0.95``.
        n_resamples: bootstrap resamples. Defaults to ``2000``.
        seed: seed of the resampling. Defaults to ``0``.

    Returns:
        ``{"low", "high", "reached"}``: the interval's bounds and the fraction of resamples in
        which the candidate reached the threshold.

    Examples:
        >>> import numpy as np
        >>> from torchrl_mbmf.analysis.runs import ratio_interval
        >>> grid = np.array([100, 200, 300, 400])
        >>> ref = np.array([[0.0, 1.0, 2.0, 4.0], [0.0, 1.0, 3.0, 4.0]])
        >>> fast = ref[:, [1, 3, 3, 3]]  # reaches 4 at step 200
        >>> ratio_interval(ref, fast, grid)
        {'low': 0.5, 'high': 0.5, 'reached': 1.0}
    """
    reference, candidate = np.asarray(reference, float), np.asarray(candidate, float)
    grid = np.asarray(grid)
    for name, rows in (("reference", reference), ("candidate", candidate)):
        if rows.ndim != 2 or rows.shape[1] != grid.size or rows.shape[0] < 1:
            raise ValueError(
                f"{name} curves have shape {rows.shape}; expected [seeds >= 1, {grid.size}]"
            )
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    ref_iqm = _resampled_iqm(
        reference[rng.integers(0, len(reference), (n_resamples, len(reference)))]
    )
    cand_iqm = _resampled_iqm(
        candidate[rng.integers(0, len(candidate), (n_resamples, len(candidate)))]
    )
    with np.errstate(all="ignore"):
        threshold = np.nanmax(np.where(np.isfinite(ref_iqm), ref_iqm, -np.inf), -1)
    ref_at = _first_index_reaching(ref_iqm, threshold)
    cand_at = _first_index_reaching(cand_iqm, threshold)
    ok = ref_at >= 0
    ratios = np.where(cand_at >= 0, grid[cand_at] / grid[np.maximum(ref_at, 0)], np.inf)[ok]
    if not ratios.size:
        raise ValueError("the reference curves hold no finite value")
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(ratios, [tail, 100 - tail], method="lower")
    return {"low": float(low), "high": float(high), "reached": float(np.isfinite(ratios).mean())}


def _random_policy_return(groups: Mapping[str, Sequence[Run]]) -> float | None:
    """IQM over the runs with a random-data phase of their mean random-policy episode return."""
    means = []
    for runs in groups.values():
        for run in runs:
            steps, returns = run.scalar("train/episode_return")
            random = returns[steps <= run.random_steps] if run.random_steps > 0 else returns[:0]
            if random.size:
                means.append(float(random.mean()))
    if not means:
        return None
    return float(_nan_iqm_columns(np.asarray(means)[:, None])[0])


def _table_curves(
    groups: Mapping[str, Sequence[Run]], budget: int | None, exclude_random: bool, points: int
) -> tuple[int, np.ndarray, dict[str, Curve]]:
    """The budget, grid and per-configuration curves of the steps-to-a-level tables."""
    end = budget
    if end is None:
        end = max(r.last_step for runs in groups.values() for r in runs)
    grid = np.linspace(0, end, points + 1)[1:].round().astype(np.int64)
    curves = {
        label: aggregate_curve(
            runs,
            grid=grid,
            exclude_random=exclude_random,
            policy_only=True,
            until=end,
            min_seeds=len(runs),
            n_resamples=200,
        )
        for label, runs in groups.items()
    }
    return int(end), grid, curves


def _level_row(label: str, curve: Curve, grid: np.ndarray, threshold: float) -> dict[str, Any]:
    """First steps of a curve (its IQM and each seed) at ``threshold``, with its best value."""
    per_seed = [
        first_step_reaching(grid, np.nan_to_num(row, nan=-np.inf), threshold)
        for row in curve.per_seed
    ]
    return {
        "label": label,
        "step": first_step_reaching(grid, np.nan_to_num(curve.iqm, nan=-np.inf), threshold),
        "best": float(np.nanmax(curve.iqm)) if np.isfinite(curve.iqm).any() else None,
        "seeds_reached": sum(s is not None for s in per_seed),
        "per_seed_steps": per_seed,
        "seeds": curve.seeds,
    }


def ppo_maximum_table(
    groups: Mapping[str, Sequence[Run]],
    reference: str,
    *,
    budget: int | None = None,
    exclude_random: bool = False,
    points: int = 1000,
) -> dict[str, Any]:
    r"""The thesis' "PPO-maximum" table (table 10), on across-seed IQM curves.

    The threshold is the best value the reference's aggregated last-10-episode curve reaches
    within ``budget`` real steps; for every configuration the table gives the first real step at
    which its own aggregated curve reaches that threshold, and the ratio to the reference's step
    (below 1: fewer real steps than the reference). Per-seed first steps are given too, each
    seed's own curve against the same threshold.

    The curves are those of :func:`aggregate_curve` with ``policy_only=True`` (a run's
    last-10-episode mean counts once its window holds only episodes of its own policy:
    random-data episodes never "reach" a threshold, though the steps of that phase count
    unless ``exclude_random``), each run read
    up to ``budget`` real steps, and an aggregate only where every seed of the configuration
    has a value. First steps are grid steps (``grid_spacing`` apart), so each is late by less
    than one spacing.

    Two caveats travel with the table. The threshold is the maximum of the reference's own noisy
    curve, which the reference reaches by construction and any other curve must match: the ratio
    is biased upwards, and ``reference_self`` gives the :func:`ratio_interval` of the reference
    against itself (both sides resampled from its seeds), what identical methods show. And a
    threshold at or below ``random_policy_return`` (the IQM of the random-data episodes' mean
    return) says nothing: random actions do as well.

    Args:
        groups: ``{label: runs}``, one entry per configuration; must hold ``reference``.
        reference: the label whose maximum is the threshold (``"ppo"`` or ``"sac"``).

    Keyword Args:
        budget: only steps up to this count are considered (the planning budget). Defaults to
            the longest run.
        exclude_random: count steps without the random-data steps. Defaults to ``False``.
        points: grid resolution. Defaults to ``1000``.

    Returns:
        ``{"reference", "threshold", "budget", "exclude_random", "grid_spacing",
        "random_policy_return", "reference_self", "rows": [{label, step, ratio, ratio_ci,
        best, seeds_reached, per_seed_steps, seeds}]}``; ``step`` and ``ratio`` are ``None``
        where never reached; ``ratio_ci`` is :func:`ratio_interval` over the seeds (``None``
        for the reference itself); ``random_policy_return`` is ``None`` when no run has a
        random-data phase.

    Raises:
        KeyError: ``reference`` is not in ``groups``.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run, ppo_maximum_table
        >>> def run(label, rows):
        ...     d = pathlib.Path(tempfile.mkdtemp())
        ...     (d / "logs/scalars/train").mkdir(parents=True)
        ...     text = "".join(f"{s},{v}\n" for s, v in rows)
        ...     _ = (d / "logs/scalars/train/return_last10_mean.csv").write_text(text)
        ...     return Run(d, {"method": label, "seed": 0})
        >>> groups = {"ppo": [run("ppo", [(100, 0.0), (200, 5.0)])],
        ...           "sac": [run("sac", [(100, 6.0), (200, 7.0)])]}
        >>> t = ppo_maximum_table(groups, "ppo", points=2)
        >>> [(r["label"], r["step"], r["ratio"]) for r in t["rows"]]
        [('ppo', 200, 1.0), ('sac', 100, 0.5)]
    """
    if reference not in groups:
        raise KeyError(f"reference {reference!r} not among the groups {sorted(groups)}")
    end, grid, curves = _table_curves(groups, budget, exclude_random, points)
    ref = curves[reference].iqm
    if not np.isfinite(ref).any():
        raise ValueError(f"the reference {reference!r} logged no returns within {end} steps")
    threshold = float(np.nanmax(ref))
    ref_step = first_step_reaching(grid, np.nan_to_num(ref, nan=-np.inf), threshold)
    rows = []
    for label, curve in curves.items():
        row = _level_row(label, curve, grid, threshold)
        step = row["step"]
        row["ratio"] = None if step is None or not ref_step else step / ref_step
        row["ratio_ci"] = (
            None
            if label == reference
            else ratio_interval(curves[reference].per_seed, curve.per_seed, grid)
        )
        rows.append(row)
    reference_seeds = curves[reference].per_seed
    return {
        "reference": reference,
        "threshold": threshold,
        "budget": int(end),
        "exclude_random": exclude_random,
        "grid_spacing": float(end / points),
        "random_policy_return": _random_policy_return(groups),
        "reference_self": ratio_interval(reference_seeds, reference_seeds, grid, seed=1),
        "rows": rows,
    }


def steps_interval(
    per_seed: np.ndarray,
    grid: np.ndarray,
    threshold: float,
    *,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> dict[str, float]:
    r"""Percentile-bootstrap interval of the first step an IQM curve reaches a fixed level.

    Each resample draws the seeds with replacement, takes their IQM curve and the first grid
    step at which it reaches ``threshold``; a resample that never reaches it counts as an
    infinite step, so an upper bound of ``inf`` means that more than ``(1 - confidence) / 2``
    of the resamples never got there within the grid.

    Args:
        per_seed: ``[seeds, grid]`` per-seed curves (``Curve.per_seed``).
        grid: the real steps of the curves' columns.
        threshold: the level to reach (fixed beforehand, not read off these curves).

    Keyword Args:
        confidence: confidence level. Defaults to ``0.95``.
        n_resamples: bootstrap resamples. Defaults to ``2000``.
        seed: seed of the resampling. Defaults to ``0``.

    Returns:
        ``{"low", "high", "reached"}``: the bounds (real steps; ``inf`` for never) and the
        fraction of resamples that reached the level.

    Examples:
        >>> import numpy as np
        >>> from torchrl_mbmf.analysis.runs import steps_interval
        >>> grid = np.array([100, 200, 300])
        >>> steps_interval(np.array([[0.0, 5.0, 9.0], [1.0, 6.0, 9.0]]), grid, 5.0)
        {'low': 200.0, 'high': 200.0, 'reached': 1.0}
    """
    rows, grid = np.asarray(per_seed, float), np.asarray(grid)
    if rows.ndim != 2 or rows.shape[1] != grid.size or rows.shape[0] < 1:
        raise ValueError(f"curves have shape {rows.shape}; expected [seeds >= 1, {grid.size}]")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    iqm = _resampled_iqm(rows[rng.integers(0, len(rows), (n_resamples, len(rows)))])
    at = _first_index_reaching(iqm, np.full(n_resamples, float(threshold)))
    steps = np.where(at >= 0, grid[np.maximum(at, 0)].astype(float), np.inf)
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(steps, [tail, 100 - tail], method="lower")
    return {"low": float(low), "high": float(high), "reached": float(np.isfinite(steps).mean())}


def fixed_threshold_table(
    groups: Mapping[str, Sequence[Run]],
    threshold: float,
    *,
    source: str,
    budget: int | None = None,
    exclude_random: bool = False,
    points: int = 1000,
) -> dict[str, Any]:
    r"""The real steps each configuration needs to reach a level fixed beforehand.

    The variant of :func:`ppo_maximum_table` without its bias: the level is not the maximum of
    one of the compared curves (which that curve reaches by construction) but a number given
    in advance, for example the thesis' own PPO return at a budget, or the reference's IQM at
    the budget. Curves, grid and counting are those of :func:`ppo_maximum_table`; each row has
    its own :func:`steps_interval` over its seeds, so two configurations compare by their
    intervals, with no ratio to a curve that may never reach the level.

    Args:
        groups: ``{label: runs}``, one entry per configuration.
        threshold: the level.

    Keyword Args:
        source: where the level comes from (shown with the table).
        budget: only steps up to this count are considered. Defaults to the longest run.
        exclude_random: count steps without the random-data steps. Defaults to ``False``.
        points: grid resolution. Defaults to ``1000``.

    Returns:
        ``{"threshold", "source", "budget", "exclude_random", "grid_spacing", "rows": [{label,
        step, step_ci, best, seeds_reached, per_seed_steps, seeds}]}``; ``step`` is ``None``
        where the IQM curve never reaches the level.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run, fixed_threshold_table
        >>> def run(label, rows):
        ...     d = pathlib.Path(tempfile.mkdtemp())
        ...     (d / "logs/scalars/train").mkdir(parents=True)
        ...     text = "".join(f"{s},{v}\n" for s, v in rows)
        ...     _ = (d / "logs/scalars/train/return_last10_mean.csv").write_text(text)
        ...     return Run(d, {"method": label, "seed": 0})
        >>> groups = {"ppo": [run("ppo", [(100, 0.0), (200, 5.0)])],
        ...           "sac": [run("sac", [(100, 6.0), (200, 7.0)])]}
        >>> t = fixed_threshold_table(groups, 5.5, source="given", points=2)
        >>> [(r["label"], r["step"], r["step_ci"]["high"]) for r in t["rows"]]
        [('ppo', None, inf), ('sac', 100, 100.0)]
    """
    if not groups:
        raise ValueError("fixed_threshold_table needs at least one configuration")
    if not np.isfinite(threshold):
        raise ValueError(f"threshold must be a finite return, got {threshold}")
    end, grid, curves = _table_curves(groups, budget, exclude_random, points)
    rows = []
    for label, curve in curves.items():
        row = _level_row(label, curve, grid, threshold)
        row["step_ci"] = steps_interval(curve.per_seed, grid, threshold)
        rows.append(row)
    return {
        "threshold": float(threshold),
        "source": source,
        "budget": int(end),
        "exclude_random": exclude_random,
        "grid_spacing": float(end / points),
        "rows": rows,
    }


def interval_of(
    runs: Sequence[Run], name: str = RETURN_CURVE, *, at_step: int | None = None
) -> Interval | None:
    r"""IQM and 95% bootstrap interval over seeds of :func:`final_values`.

    Args:
        runs: runs of one configuration.
        name: the scalar. Defaults to the mean of the last 10 episode returns.

    Keyword Args:
        at_step: read each seed at this real step; by default at its end.

    Returns:
        The :class:`~torchrl_mbmf.analysis.stats.Interval`, or ``None`` without data.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run, interval_of
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> (d / "logs/scalars/train").mkdir(parents=True)
        >>> _ = (d / "logs/scalars/train/return_last10_mean.csv").write_text("10,2.0\n")
        >>> str(interval_of([Run(d, {"method": "ppo", "seed": 0})]))
        '2 [2, 2]'
    """
    values = final_values(runs, name, at_step=at_step)
    return bootstrap_ci(values) if values else None


__all__ = [
    "Curve",
    "Run",
    "aggregate_curve",
    "compare_intervals",
    "final_values",
    "fixed_threshold_table",
    "group_runs",
    "interval_of",
    "load_runs",
    "ppo_maximum_table",
    "ratio_interval",
    "steps_interval",
]
