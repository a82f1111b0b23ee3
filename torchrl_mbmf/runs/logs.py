"""What a resume does to the run folder's logs: cut them back to the checkpoint, and say so.

Each CSV series is cut back to exactly the rows the checkpoint's
:class:`~torchrl.record.loggers.CSVLogger` state holds (all removed without a checkpoint), so a
killed-and-resumed run's CSV files equal an uninterrupted run's, row for row. Why the rows and
not the steps: ``docs/design/run_folder.md``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from torchrl_mbmf.runs.layout import RESUME_LOG

__all__ = ["append_resume_log", "cut_csv_logs"]

logger = logging.getLogger(__name__)


def _row(step: Any, value: Any) -> str:
    # CSVExperiment.add_scalar's format
    return ",".join([str(step), str(float(value))])


def cut_csv_logs(scalars_dir: Path, rows: Mapping[str, Sequence[tuple[Any, Any]]]) -> dict:
    r"""Cuts every ``<scalars_dir>/<name>.csv`` back to the rows of ``rows[name]``.

    A file keeps its first ``len(rows[name])`` lines when they agree with ``rows[name]`` and is
    rewritten from ``rows[name]`` otherwise; a file whose series is not in ``rows`` is removed.
    Call it before anything is logged by this process (the logger opens its files lazily, in
    append mode).

    Args:
        scalars_dir: the CSV logger's ``scalars`` folder.
        rows: series name -> ``(step, value)`` rows to keep (a ``CSVLogger`` state's
            ``"scalars"``).

    Returns:
        ``{name: number of rows removed}`` for each file that changed.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.logs import cut_csv_logs
        >>> with tempfile.TemporaryDirectory() as d:
        ...     (Path(d) / "loss").mkdir()
        ...     _ = (Path(d) / "loss" / "a.csv").write_text("10,1.0\n20,2.0\n30,3.0\n")
        ...     _ = (Path(d) / "b.csv").write_text("30,1.0\n")
        ...     cut = cut_csv_logs(Path(d), {"loss/a": [(10, 1.0), (20, 2.0)]})
        ...     text = (Path(d) / "loss" / "a.csv").read_text()
        >>> cut, text
        ({'b': 1, 'loss/a': 1}, '10,1.0\n20,2.0\n')
    """
    cut: dict[str, int] = {}
    if not scalars_dir.exists():
        return cut
    for path in sorted(scalars_dir.rglob("*.csv")):
        name = path.relative_to(scalars_dir).with_suffix("").as_posix()
        lines = path.read_text().splitlines()
        keep = rows.get(name, ())
        if not keep:
            path.unlink()
            cut[name] = len(lines)
            continue
        expected = [_row(step, value) for step, value in keep]
        if lines[: len(expected)] == expected:
            if len(lines) == len(expected):
                continue
        else:
            logger.warning("%s disagrees with the checkpoint's log state; rewritten", path)
        path.write_text("".join(line + "\n" for line in expected))
        cut[name] = len(lines) - len(expected)
    return cut


def append_resume_log(run_dir: Path, entry: Mapping[str, Any]) -> None:
    """Appends ``entry`` (with a UTC time stamp) to ``<run_dir>/resume_log.json`` (a JSON list).

    Args:
        run_dir: the run folder.
        entry: what happened (JSON-serialisable).

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.logs import append_resume_log
        >>> with tempfile.TemporaryDirectory() as d:
        ...     append_resume_log(Path(d), {"event": "resume", "step": 400})
        ...     append_resume_log(Path(d), {"event": "resume", "step": 800})
        ...     [e["step"] for e in json.loads((Path(d) / "resume_log.json").read_text())]
        [400, 800]
    """
    path = Path(run_dir) / RESUME_LOG
    entries = json.loads(path.read_text()) if path.exists() else []
    entries.append({"time": datetime.now(UTC).isoformat(timespec="seconds"), **entry})
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(entries, indent=2) + "\n")
    tmp.replace(path)
