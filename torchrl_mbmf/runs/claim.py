"""A run folder belongs to its run: what a new run may find there, and the lock while it runs.

:func:`claim_run_folder` takes the folder's lock (:class:`RunFolderLock`) before a run writes
anything and decides from what the folder holds: a fresh run, a resume, a restart over a run
killed before its first checkpoint, nothing to do (a finished run), or a refusal. ``restart``
moves an old run aside; nothing is ever deleted. The cases: ``docs/design/run_folder.md``.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from torchrl_mbmf.runs.layout import (
    CHECKPOINTS,
    CONFIG,
    FITS,
    GIT_COMMIT,
    LOCK,
    LOGS,
    MACHINE,
    POLICY,
    POLICY_RECORD,
    RESUME_LOG,
    SUMMARY,
    TRAIN_LOG,
)
from torchrl_mbmf.runs.resume import describe_refused, flatten_settings, resume_changes

__all__ = ["FinishedRunError", "RunFolderError", "RunFolderLock", "claim_run_folder"]

log = logging.getLogger(__name__)

#: Entries a training run writes (and may find again when it resumes).
RUN_ENTRIES = frozenset(
    {
        CONFIG,
        GIT_COMMIT,
        MACHINE,
        SUMMARY,
        POLICY,
        POLICY_RECORD,
        RESUME_LOG,
        LOGS,
        CHECKPOINTS,
        FITS,
        f"{POLICY}.tmp",  # the exports' staging files, left by a kill during a save
        f"{POLICY_RECORD}.tmp",
    }
)
#: Entries a run folder may hold that are not the run's: Hydra's job log and config copy, the
#: lock, and runs moved aside by ``restart``.
OTHER_ENTRIES = frozenset({TRAIN_LOG, ".hydra", LOCK})
REPLACED_PREFIX = "replaced-"


class RunFolderError(ValueError):
    """A run folder holds something this run must not write over, or is in use."""


class FinishedRunError(RunFolderError):
    """The run folder holds this config's run, finished: there is nothing to train.

    Args:
        message: what was found.
        summary: the finished run's ``summary.json``.
    """

    def __init__(self, message: str, summary: dict[str, Any]) -> None:
        super().__init__(message)
        self.summary = summary


@dataclass
class RunFolderLock:
    """The advisory lock of a run folder, held while the run writes to it.

    Args:
        path: the run folder.

    Examples:
        >>> import tempfile
        >>> from torchrl_mbmf.runs.claim import RunFolderLock
        >>> with tempfile.TemporaryDirectory() as d:
        ...     lock = RunFolderLock(Path(d)).acquire()
        ...     held = lock.held
        ...     lock.release()
        >>> held, lock.held
        (True, False)
    """

    path: Path
    _file: IO[str] | None = field(default=None, init=False, repr=False)

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._file is not None

    def acquire(self) -> RunFolderLock:
        """Takes the lock, or raises :class:`RunFolderError` naming the process holding it."""
        lock_path = self.path / LOCK
        file = lock_path.open("a+")
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            file.close()
            if err.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            holder = _read_pid(lock_path)
            if holder == os.getpid():  # this process already runs here (a second Trainer)
                return self
            raise RunFolderError(
                f"run_dir={str(self.path)!r} is in use by process {holder} (lock {LOCK}); "
                "wait for it to stop, or choose another run_dir"
            ) from None
        file.seek(0)
        file.truncate()
        file.write(f"{os.getpid()}\n")
        file.flush()
        self._file = file
        return self

    def __del__(self) -> None:
        # A lock dropped without release (a Trainer built but never trained) is released.
        self.release()

    def release(self) -> None:
        """Releases the lock (the lock file stays, naming no live holder)."""
        if self._file is not None:
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None


def _read_pid(path: Path) -> int | str:
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return "unknown"


def claim_run_folder(
    run_dir: str | os.PathLike,
    config: Mapping[str, Any],
    *,
    restart: bool = False,
) -> RunFolderLock:
    """Checks what ``run_dir`` holds, moves an old run aside if asked, and locks the folder.

    Args:
        run_dir: the run folder (created if missing).
        config: this run's resolved config as nested plain containers (compared with the
            config of a run found in the folder, up to the resume-safe settings).

    Keyword Args:
        restart: move a run found in the folder into ``replaced-<UTC time>/`` and start
            afresh. Defaults to ``False``.

    Returns:
        The held :class:`RunFolderLock`; release it when the run stops.

    Raises:
        RunFolderError: ``run_dir`` is a file or not writable, holds files that are not a
            run's or a run of another config (without ``restart``), or is locked by another
            live process. Nothing was written.
        FinishedRunError: ``run_dir`` holds this config's finished run (without ``restart``).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.claim import claim_run_folder
        >>> with tempfile.TemporaryDirectory() as d:
        ...     (Path(d) / "notes.txt").write_text("mine")
        ...     try:
        ...         claim_run_folder(d, {"seed": 0})
        ...     except ValueError as err:
        ...         print(str(err).split("; ")[0].split(" holds ")[1])
        4
        files that are not a training run's: ['notes.txt']
    """
    path = Path(run_dir)
    if path.exists() and not path.is_dir():
        raise RunFolderError(f"run_dir={str(run_dir)!r} is a file, expected a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RunFolderError(f"run_dir={str(run_dir)!r} cannot be created: {err}") from err
    if not os.access(path, os.W_OK | os.X_OK):
        raise RunFolderError(f"run_dir={str(run_dir)!r} is not writable")
    _refuse_foreign(path)  # before the lock file is written into someone else's folder
    lock = RunFolderLock(path).acquire()
    try:
        _check_contents(path, config, restart=restart)
    except BaseException:
        lock.release()
        raise
    return lock


def _refuse_foreign(path: Path) -> set[str]:
    """The folder's entries; refuses entries that are not a run's."""
    names = {p.name for p in path.iterdir()}
    foreign = sorted(
        n for n in names - RUN_ENTRIES - OTHER_ENTRIES if not n.startswith(REPLACED_PREFIX)
    )
    if foreign:
        raise RunFolderError(
            f"run_dir={str(path)!r} holds files that are not a training run's: {foreign[:10]}"
            f"{' ...' if len(foreign) > 10 else ''}; choose a new or empty folder (nothing "
            "was written)"
        )
    return names


def _check_contents(path: Path, config: Mapping[str, Any], *, restart: bool) -> None:
    found = sorted(_refuse_foreign(path) & RUN_ENTRIES)
    if not found:
        return
    if restart:
        aside = path / f"{REPLACED_PREFIX}{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}"
        aside.mkdir()
        for name in found:
            os.replace(path / name, aside / name)
        log.warning("restart=true: the old run's files were moved to %s", aside)
        return
    has_checkpoint = (path / CHECKPOINTS).is_dir() and any((path / CHECKPOINTS).iterdir())
    summary = path / SUMMARY
    done = _summary_steps(summary) if summary.exists() else None
    total = config.get("total_steps")
    finished_and_raised = isinstance(total, int) and done is not None and total > done
    if summary.exists() and has_checkpoint and finished_and_raised:
        return  # a finished run continued to a larger budget: its checkpoint's check applies
    if (path / CONFIG).exists():
        _check_same_config(path, config)
    if summary.exists() and finished_and_raised:
        raise RunFolderError(
            f"run_dir={str(path)!r} holds a finished run ({SUMMARY}: {done} real steps) without "
            f"checkpoints, so total_steps={total} cannot continue it; pass restart=true to move "
            "its files aside and train afresh"
        )
    if summary.exists():
        more = " or raise total_steps past them to continue it" if has_checkpoint else ""
        raise FinishedRunError(
            f"run_dir={str(path)!r} holds this config's finished run ({SUMMARY}: {done} real "
            f"steps): nothing to train; pass restart=true to move its files aside and train "
            f"again{more}",
            _summary(summary),
        )
    # Otherwise an unfinished run of this config: resumed from its checkpoint, or (killed
    # before its first checkpoint) started again over its rows.


def _check_same_config(path: Path, config: Mapping[str, Any]) -> None:
    """Refuses a folder whose run was written with other settings than the resume-safe ones."""
    try:
        saved = yaml.safe_load((path / CONFIG).read_text())
    except yaml.YAMLError as err:
        raise RunFolderError(
            f"{str(path / CONFIG)!r} is not valid YAML ({err}); pass restart=true to move the "
            "folder's run aside"
        ) from err
    if not isinstance(saved, Mapping):
        raise RunFolderError(
            f"{str(path / CONFIG)!r} holds no config; pass restart=true to move it aside"
        )
    refused, _ = resume_changes(flatten_settings(saved), flatten_settings(config))
    if refused:
        lines = describe_refused(refused)
        raise RunFolderError(
            f"run_dir={str(path)!r} holds a run of another config:\n{lines}\npass restart=true "
            "to move it aside and train afresh, or choose another run_dir"
        )


def _summary(summary: Path) -> dict[str, Any]:
    try:
        found = json.loads(summary.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, OSError):
        return {}
    return found if isinstance(found, dict) else {}


def _summary_steps(summary: Path) -> int | None:
    steps = _summary(summary).get("real_steps")
    return steps if isinstance(steps, int) and not isinstance(steps, bool) else None
