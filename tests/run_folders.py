"""Fake committed run folders for the tests of the analysis scripts (not part of the package).

The tests' ``conftest.py`` puts this folder on ``sys.path``.
"""

from __future__ import annotations

import json
from pathlib import Path


def fake_run(
    root: Path, name: str, seed: int, evals: dict[int, float], *, done: bool = False
) -> Path:
    """Writes ``root/name`` as a ``sac_mbpo`` run folder with the given evaluation returns.

    The evaluation and last-10 training curves both get ``evals`` (real step -> return); a
    finished run also gets a ``summary.json`` (10 s in all, 8 of them in updates).

    Args:
        root: the run root.
        name: the run's folder name.
        seed: the seed its ``config.yaml`` names.
        evals: the curve's rows.

    Keyword Args:
        done: write a summary (the run finished at its last step). Defaults to ``False``.

    Examples:
        >>> import tempfile
        >>> from run_folders import fake_run
        >>> with tempfile.TemporaryDirectory() as d:
        ...     run = fake_run(Path(d), "x__seed0", 0, {10: 1.0}, done=True)
        ...     print((run / "logs/scalars/eval/return.csv").read_text().strip())
        10,1.0
    """
    folder = root / name
    (folder / "logs/scalars/eval").mkdir(parents=True)
    (folder / "logs/scalars/train").mkdir(parents=True)
    (folder / "config.yaml").write_text(f"method: sac_mbpo\nseed: {seed}\n")
    rows = "".join(f"{step},{value}\n" for step, value in evals.items())
    (folder / "logs/scalars/eval/return.csv").write_text(rows)
    (folder / "logs/scalars/train/return_last10_mean.csv").write_text(rows)
    if done:
        summary = {"real_steps": max(evals), "seconds": 10.0, "time_breakdown": {"update_s": 8.0}}
        (folder / "summary.json").write_text(json.dumps(summary))
    return folder
