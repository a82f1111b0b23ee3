"""A finished run in words: durations as ``h:mm:ss`` and the message a run prints at its end."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

__all__ = ["end_of_run_message", "format_seconds"]


def format_seconds(seconds: float | None) -> str:
    """``h:mm:ss`` (``?`` for an unknown duration).

    Args:
        seconds: a duration, or ``None``.

    Examples:
        >>> from torchrl_mbmf.runs.summary_text import format_seconds
        >>> format_seconds(3725.4), format_seconds(59), format_seconds(None)
        ('1:02:05', '0:00:59', '?')
    """
    if seconds is None or not math.isfinite(seconds):
        return "?"
    s = round(max(0.0, seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def end_of_run_message(summary: dict[str, Any], run_dir: str | Path) -> str:
    """What a finished run prints: its folder, the summary's headline numbers, what to run next.

    Args:
        summary: the run's summary (``summary.json``).
        run_dir: the run folder.

    Examples:
        >>> from torchrl_mbmf.runs.summary_text import end_of_run_message
        >>> summary = {"method": "ppo", "env": "Pendulum-v1", "reward": "default", "seed": 0,
        ...     "real_steps": 4000, "last10_mean_return": -1200.5, "final_eval_return": None,
        ...     "seconds": 61.0}
        >>> print(end_of_run_message(summary, "outputs/short/run"))
        Run finished: outputs/short/run
          ppo on Pendulum-v1, reward default, seed 0: 4,000 real steps in 0:01:01
          last-10 mean return -1200.5, final evaluation return n/a
        Analyse:  python recipes/analyze.py runs=[outputs/short] out_dir=outputs/short/analysis
        Video:    python recipes/record.py run_dir=outputs/short/run
    """
    run_dir = Path(run_dir)

    def number(key: str) -> str:
        value = summary.get(key)
        return "n/a" if value is None else f"{float(value):.1f}"

    head = (
        f"{summary.get('method')} on {summary.get('env')}, reward {summary.get('reward')}, "
        f"seed {summary.get('seed')}: {int(summary.get('real_steps', 0)):,} real steps in "
        f"{format_seconds(summary.get('seconds'))}"
    )
    parent = run_dir.parent.as_posix()
    return "\n".join(
        [
            f"Run finished: {run_dir.as_posix()}",
            f"  {head}",
            f"  last-10 mean return {number('last10_mean_return')}, "
            f"final evaluation return {number('final_eval_return')}",
            f"Analyse:  python recipes/analyze.py runs=[{parent}] out_dir={parent}/analysis",
            f"Video:    python recipes/record.py run_dir={run_dir.as_posix()}",
        ]
    )
