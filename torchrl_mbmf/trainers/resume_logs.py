"""What a resume records in the run folder (``resume_log.json``)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

#: Where the run's history of resumes is appended.
RESUME_LOG = "resume_log.json"


def append_resume_log(run_dir: Path, entry: Mapping[str, Any]) -> None:
    """Appends ``entry`` (with a UTC time stamp) to ``<run_dir>/resume_log.json`` (a JSON list).

    Args:
        run_dir: the run folder.
        entry: what happened (JSON-serialisable).

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.trainers.resume_logs import append_resume_log
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
