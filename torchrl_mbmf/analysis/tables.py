"""Table cells of the result scripts: an IQM with its interval, and a run's compute per step."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from torchrl_mbmf.analysis.runs import Run
from torchrl_mbmf.analysis.stats import bootstrap_ci, iqm

#: the parts of a run's ``summary.json`` ``time_breakdown``, in the order tables print them
TIME_PARTS = ("update_s", "refit_s", "rollout_s", "act_s", "env_s", "other_s")


def iqm_cell(values: Sequence[float]) -> tuple[str, dict[str, object]]:
    """A table cell ``"IQM [low, high] (seeds)"`` and its JSON record.

    Args:
        values: one number per seed (an empty sequence gives ``"n/a"``).

    Returns:
        ``(text, record)``: the record holds ``values``, and with values also ``iqm`` and
        ``ci95`` (the 95% percentile-bootstrap interval of :func:`bootstrap_ci`).

    Examples:
        >>> from torchrl_mbmf.analysis.tables import iqm_cell
        >>> iqm_cell([1000.0, 1000.0])[0]
        '1,000 [1,000, 1,000] (2)'
        >>> iqm_cell([])
        ('n/a', {'values': []})
    """
    if not len(values):
        return "n/a", {"values": []}
    values = [float(v) for v in values]
    ci = bootstrap_ci(values)
    record = {"values": values, "iqm": float(iqm(values)), "ci95": [ci.low, ci.high]}
    return f"{float(iqm(values)):,.0f} [{ci.low:,.0f}, {ci.high:,.0f}] ({len(values)})", record


def compute_split(runs: Sequence[Run], at_step: int | None = None) -> dict[str, object]:
    """Wall milliseconds per real step of finished runs, and where their last process went.

    A resumed run's summary times the process that wrote it only (the one that logged its last
    step, :meth:`~torchrl_mbmf.analysis.runs.Run.segment_start`): the split is per real step
    of that segment, averaged over the runs; the whole-run rate comes from
    :meth:`~torchrl_mbmf.analysis.runs.Run.wall_seconds_to`.

    Args:
        runs: runs of one configuration; those without a summary at the budget are left out.
        at_step: the budget: runs that finished at this real step, including runs since
            continued to a raised budget (their earlier summary,
            :meth:`~torchrl_mbmf.analysis.runs.Run.summary_at`); ``None``: the runs that are
            finished now, at whatever step.

    Returns:
        ``{"runs": 0}`` without such a run, else ``runs``, ``real_steps`` (of the first),
        ``ms_per_real_step`` (per run), ``segment_ms_per_real_step`` (``{part: ms}`` over
        :data:`TIME_PARTS`), ``segment_starts`` and ``segment_cpus`` (per run: the real step the
        process that finished it resumed from, torch's CPU capability on its machine, ``"?"``
        where no ``machine.json`` of that process was kept) and ``commits`` (those processes').

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run
        >>> from torchrl_mbmf.analysis.tables import compute_split
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> summary = {"real_steps": 1000, "seconds": 4.0, "time_breakdown": {"update_s": 3.0}}
        >>> split = compute_split([Run(d, {"method": "sac", "seed": 0}, summary)])
        >>> split["ms_per_real_step"], split["segment_ms_per_real_step"]["update_s"]
        ([4.0], 3.0)
        >>> compute_split([Run(d, {"method": "sac", "seed": 0}, summary)], at_step=2000)
        {'runs': 0}
    """
    done = [
        (run, summary)
        for run in runs
        if (summary := run.summary if at_step is None else run.summary_at(at_step)) is not None
    ]
    if not done:
        return {"runs": 0}
    split: dict[str, list[float]] = {p: [] for p in TIME_PARTS}
    ends = [int(summary["real_steps"]) for _, summary in done]
    for (run, summary), end in zip(done, ends, strict=True):
        steps = end - run.segment_start(end)
        for p in TIME_PARTS:
            split[p].append(1e3 * summary.get("time_breakdown", {}).get(p, 0.0) / steps)
    return {
        "runs": len(done),
        "real_steps": ends[0],
        "ms_per_real_step": [
            1e3 * (run.wall_seconds_to(end) or 0.0) / end
            for (run, _), end in zip(done, ends, strict=True)
        ],
        "segment_ms_per_real_step": {p: float(np.mean(v)) for p, v in split.items()},
        "segment_starts": [
            run.segment_start(end) for (run, _), end in zip(done, ends, strict=True)
        ],
        "segment_cpus": [
            str(run.machine_at(end).get("cpu_capability", "?"))
            for (run, _), end in zip(done, ends, strict=True)
        ],
        "commits": sorted({run.commit_at(end) for (run, _), end in zip(done, ends, strict=True)}),
    }


def compute_row(label: str, compute: dict[str, object]) -> str | None:
    """The Markdown row of :func:`compute_split`'s record (``None`` without a finished run).

    Args:
        label: the method's name, first cell of the row.
        compute: :func:`compute_split`'s record.

    Examples:
        >>> from torchrl_mbmf.analysis.tables import compute_row
        >>> split = {p: 0.0 for p in TIME_PARTS}
        >>> record = {"runs": 1, "real_steps": 1000, "ms_per_real_step": [4.0],
        ...           "segment_starts": [0], "segment_cpus": ["AVX2"],
        ...           "segment_ms_per_real_step": split}
        >>> compute_row("sac", record)
        '| sac (1,000 steps) | 4 | 0 (AVX2) | 0.0 | 0.0 | 0.0 | 0.0 | 0.0 | 0.0 |'
        >>> compute_row("sac", {"runs": 0}) is None
        True
    """
    if not compute["runs"]:
        return None
    ms = ", ".join(f"{v:.0f}" for v in compute["ms_per_real_step"])
    cpus = compute.get("segment_cpus") or ["?"] * len(compute["segment_starts"])
    starts = ", ".join(
        f"{s:,} ({cpu})" for s, cpu in zip(compute["segment_starts"], cpus, strict=True)
    )
    split = " | ".join(f"{compute['segment_ms_per_real_step'][p]:.1f}" for p in TIME_PARTS)
    return f"| {label} ({compute['real_steps']:,} steps) | {ms} | {starts} | {split} |"


def process_rows(run: Run) -> list[dict[str, object]]:
    r"""Where each process of a run spent its time, per real step, and on which CPU.

    One record per process whose rows the run kept
    (:meth:`~torchrl_mbmf.analysis.runs.Run.segments`), from the logged series: the wall rate
    (``time/steps_per_s``); the seconds from each batch's arrival to the end of its learning
    (``time/update_s``: SAC updates, world-model refits, model rollouts, evaluations and
    checkpoints), of which refits (``time/model_fit_s``) and rollouts (``time/rollout_s``);
    and the refits' cost per training transition and epoch
    (``model/transitions``, ``model/epochs``): a refit trains on every real transition so far,
    so its cost per real step grows with the run while its cost per transition and epoch
    measures the machine.

    Args:
        run: a run folder.

    Returns:
        Per process: ``start`` and ``end`` (real steps), ``cpu`` and ``cpu_name`` (torch's CPU
        capability and the processor's name, ``"?"`` where its ``machine.json`` was not kept),
        ``ms_per_real_step`` (wall; ``None`` if not logged); per real step ``learn_ms`` and of
        it ``refit_ms``, ``rollout_ms`` and ``rest_ms`` (updates, evaluations, checkpoints);
        ``refit_us_per_transition_epoch`` and ``refit_transitions`` (medians over its refits;
        ``None`` without a refit).

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import Run
        >>> from torchrl_mbmf.analysis.tables import process_rows
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> for name, rows in {"time/steps_per_s": "1000,20\n", "time/update_s": "1000,30\n",
        ...                    "time/model_fit_s": "1000,8\n", "model/epochs": "1000,4\n",
        ...                    "model/transitions": "1000,1000\n"}.items():
        ...     (d / "logs/scalars" / name).parent.mkdir(parents=True, exist_ok=True)
        ...     _ = (d / "logs/scalars" / f"{name}.csv").write_text(rows)
        >>> (row,) = process_rows(Run(d, {"method": "sac_mbpo", "seed": 0}, {"real_steps": 1000}))
        >>> row["ms_per_real_step"], row["rest_ms"], row["refit_us_per_transition_epoch"]
        (50.0, 22.0, 2000.0)
    """
    rate_steps, rates = run.scalar("time/steps_per_s")
    fit_steps, fits = run.scalar("time/model_fit_s")
    epoch_steps, epochs = run.scalar("model/epochs")
    data_steps, transitions = run.scalar("model/transitions")
    out: list[dict[str, object]] = []
    for start, end in run.segments():
        machine = run.machine_at(end)
        record: dict[str, object] = {
            "start": start,
            "end": end,
            "cpu": str(machine.get("cpu_capability", "?")),
            "cpu_name": str(machine.get("cpu", "?")),
        }
        rows = np.nonzero((rate_steps > start) & (rate_steps <= end))[0]
        record["ms_per_real_step"] = 1e3 / float(rates[rows[-1]]) if rows.size else None
        for part, name in (
            ("learn", "update_s"),
            ("refit", "model_fit_s"),
            ("rollout", "rollout_s"),
        ):
            steps, seconds = run.scalar(f"time/{name}")
            inside = (steps > start) & (steps <= end)
            record[f"{part}_ms"] = 1e3 * float(seconds[inside].sum()) / (end - start)
        record["rest_ms"] = record["learn_ms"] - record["refit_ms"] - record["rollout_ms"]
        refits = (fit_steps > start) & (fit_steps <= end)
        same = np.array_equal(fit_steps, epoch_steps) and np.array_equal(fit_steps, data_steps)
        if refits.any() and same:
            cost = fits[refits] / (epochs[refits] * transitions[refits])
            record["refit_us_per_transition_epoch"] = 1e6 * float(np.median(cost))
            record["refit_transitions"] = float(np.median(transitions[refits]))
        else:
            record["refit_us_per_transition_epoch"] = record["refit_transitions"] = None
        out.append(record)
    return out
