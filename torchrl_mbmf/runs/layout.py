"""Every file a run folder holds, by name, with the reader beside each writer.

A run folder written by ``recipes/train.py``::

    <run_dir>/
      config.yaml                 the resolved training config     write_record / read_config
      git_commit.txt              the package's git commit         write_record / read_commit
      machine.json                software and hardware            write_record / read_machine
      summary.json                the finished run's summary       write_summary / read_summary
      policy.pt                   the trained policy               runs.export save/load_policy
      policy.json                 policy.pt's size and SHA-256     runs.export save/load_policy
      train.log                   Hydra's log of the job
      resume_log.json             resumes and restarts             runs.logs / read_resume_log
      run.lock                    the running process' pid         runs.claim.RunFolderLock
      replaced-<time>/            a run moved aside by restart     runs.claim.claim_run_folder
      logs/scalars/<name>.csv     the logger's CSV series          read_scalar
      checkpoints/<step>/         rotated verified checkpoints     runs.resume.RunCheckpoint
      world_models/fit-<n>/       one snapshot per model fit       world_model.snapshots
      world_models/open_loop_errors.json   recipes/evaluate_fits.py

The analysis reads run folders through :class:`RunFolder` and these names only.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import platform
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

__all__ = [
    "CHECKPOINTS",
    "CONFIG",
    "FITS",
    "FIT_ERRORS",
    "GIT_COMMIT",
    "LOCK",
    "LOGS",
    "MACHINE",
    "POLICY",
    "POLICY_RECORD",
    "RESUME_LOG",
    "SCALARS",
    "SUMMARY",
    "TRAIN_LOG",
    "RunFolder",
    "git_commit",
    "machine_record",
    "read_json",
    "write_run_record",
]

CONFIG = "config.yaml"
GIT_COMMIT = "git_commit.txt"
MACHINE = "machine.json"
SUMMARY = "summary.json"
POLICY = "policy.pt"
#: ``policy.pt``'s integrity record (size, SHA-256, real steps), verified on load.
POLICY_RECORD = "policy.json"
TRAIN_LOG = "train.log"
RESUME_LOG = "resume_log.json"
#: The advisory lock of a running run (:class:`~torchrl_mbmf.runs.claim.RunFolderLock`).
LOCK = "run.lock"
#: The logger's experiment folder; its CSV series lie under ``LOGS/SCALARS``.
LOGS = "logs"
SCALARS = "scalars"
CHECKPOINTS = "checkpoints"
#: Folder of the world-model snapshots (``fit-<transitions>``) and their open-loop errors.
FITS = "world_models"
FIT_ERRORS = "open_loop_errors.json"


@dataclass(frozen=True)
class RunFolder:
    """The files of one run folder: their paths, and readers that mirror the writers.

    Args:
        path: the run folder.

    Examples:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     run = RunFolder(Path(d))
        ...     run.write_record({"seed": 0})
        ...     run.write_summary({"real_steps": 10})
        ...     run.read_config(), run.read_summary(), run.read_resume_log()
        ({'seed': 0}, {'real_steps': 10}, [])
    """

    path: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))

    def file(self, name: str) -> Path:
        """The path of a top-level file (one of this module's names, e.g. :data:`SUMMARY`)."""
        return self.path / name

    @property
    def scalars(self) -> Path:
        """The folder of the CSV series (``logs/scalars``)."""
        return self.path / LOGS / SCALARS

    @property
    def checkpoints(self) -> Path:
        """The folder of the rotated checkpoints."""
        return self.path / CHECKPOINTS

    @property
    def fits(self) -> Path:
        """The folder of the world-model snapshots."""
        return self.path / FITS

    def is_training_run(self) -> bool:
        """Whether this is a training run folder (a config and logged series)."""
        return self.file(CONFIG).is_file() and self.scalars.is_dir()

    def write_record(self, cfg: DictConfig | Mapping[str, Any]) -> None:
        """Writes ``config.yaml`` (resolved), ``git_commit.txt`` and ``machine.json``."""
        self.path.mkdir(parents=True, exist_ok=True)
        if not isinstance(cfg, DictConfig):
            cfg = OmegaConf.create(dict(cfg))
        self.file(CONFIG).write_text(OmegaConf.to_yaml(cfg, resolve=True))
        self.file(GIT_COMMIT).write_text(git_commit() + "\n")
        self.file(MACHINE).write_text(json.dumps(machine_record(), indent=2) + "\n")

    def read_config(self) -> dict[str, Any]:
        """``config.yaml`` as plain containers (a ``ValueError`` names a damaged file)."""
        path = self.file(CONFIG)
        try:
            config = yaml.safe_load(path.read_text())
        except (yaml.YAMLError, UnicodeDecodeError) as err:
            raise ValueError(f"{str(path)!r} is not valid YAML ({err})") from err
        if not isinstance(config, dict):
            raise ValueError(f"{str(path)!r} holds a {type(config).__name__}, expected a mapping")
        return config

    def read_commit(self) -> str:
        """The recorded git commit (``"unknown"`` if not recorded)."""
        path = self.file(GIT_COMMIT)
        return path.read_text().strip() if path.exists() else "unknown"

    def read_machine(self) -> dict[str, Any]:
        """``machine.json`` (empty if absent)."""
        path = self.file(MACHINE)
        return read_json(path) if path.exists() else {}

    def write_summary(self, summary: Mapping[str, Any]) -> None:
        """Writes ``summary.json`` (the run finished)."""
        self.file(SUMMARY).write_text(json.dumps(dict(summary), indent=2))

    def read_summary(self) -> dict[str, Any] | None:
        """``summary.json``, or ``None`` for a run that has not finished."""
        path = self.file(SUMMARY)
        return read_json(path) if path.exists() else None

    def read_resume_log(self) -> list[dict[str, Any]]:
        """``resume_log.json``'s entries (empty if the run never resumed)."""
        path = self.file(RESUME_LOG)
        return read_json(path, list) if path.exists() else []

    def scalar_file(self, name: str) -> Path:
        """The CSV file of a logged scalar such as ``"train/episode_return"``."""
        return self.scalars / f"{name}.csv"

    def read_scalar(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """A logged scalar as ``(steps, values)`` arrays (empty if never logged).

        Rows that are not a finite step and value (a damaged or hand-edited file) are left out
        with a warning naming the file and the line.
        """
        path = self.scalar_file(name)
        rows = []
        skipped = []
        if path.exists():
            with path.open() as f:
                for line, row in enumerate(csv.reader(f), start=1):
                    if not row:
                        continue
                    parsed = _scalar_row(row)
                    if parsed is None:
                        skipped.append(line)
                    else:
                        rows.append(parsed)
        if skipped:
            log.warning(
                "%s: left out %d row(s) that are not a finite step and value (lines %s)",
                path,
                len(skipped),
                skipped[:10],
            )
        steps = np.array([r[0] for r in rows], dtype=np.int64)
        values = np.array([r[1] for r in rows], dtype=np.float64)
        return steps, values


def _scalar_row(row: list[str]) -> tuple[int, float] | None:
    """``(step, value)`` of a CSV row, or ``None`` unless both are finite numbers."""
    try:
        step, value = float(row[0]), float(row[1])
    except (ValueError, IndexError):
        return None
    if not (np.isfinite(step) and np.isfinite(value)) or step != int(step):
        return None
    return int(step), value


def read_json(path: Path, kind: type = dict) -> Any:
    """A JSON file of a run or analysis folder; a ``ValueError`` names it when it is damaged.

    Args:
        path: the file.
        kind: the type its top level must have. Defaults to ``dict``.

    Examples:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     (Path(d) / "a.json").write_text("[1]")
        ...     try:
        ...         read_json(Path(d) / "a.json")
        ...     except ValueError as err:
        ...         print(str(err).split(": ")[-1])
        3
        holds a list, expected dict
    """
    try:
        found = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{str(path)!r} is not valid JSON ({err})") from err
    if not isinstance(found, kind):
        raise ValueError(f"{str(path)!r}: holds a {type(found).__name__}, expected {kind.__name__}")
    return found


def machine_record() -> dict[str, Any]:
    """Software and hardware this process runs on (written beside a run's config).

    Examples:
        >>> sorted(machine_record())[:4]
        ['cpu', 'cpu_capability', 'cpu_count', 'machine']
    """
    import torchrl

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        # float results differ between CPUs whose kernels differ (one run on two machines)
        "cpu": _cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_threads": torch.get_num_threads(),
    }


def _cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; the platform's processor string elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_commit() -> str:
    """The package's git commit, ``"unknown"`` outside a checkout.

    Examples:
        >>> isinstance(git_commit(), str)
        True
    """
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def write_run_record(run_dir: Path, cfg: DictConfig | Mapping[str, Any]) -> None:
    """Writes ``config.yaml``, ``git_commit.txt`` and ``machine.json`` into ``run_dir``.

    Args:
        run_dir: the run folder.
        cfg: the training config (written resolved).

    Examples:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_run_record(Path(d), OmegaConf.create({"seed": 0}))
        ...     sorted(p.name for p in Path(d).iterdir())
        ['config.yaml', 'git_commit.txt', 'machine.json']
    """
    RunFolder(Path(run_dir)).write_record(cfg)
