"""Checkpoint, resume and provenance of a run folder.

:class:`RunCheckpoint` registers a run's components with their pickle-free adapters
(:mod:`torchrl_mbmf.trainers.checkpointing`), writes rotated checkpoints and resumes from the
newest intact one, refusing any changed setting that affects training. :func:`fingerprint`
is the record of settings a checkpoint must agree on; :func:`write_run_record` writes what a
run ran with (config, commit, machine).
"""

from __future__ import annotations

import json
import logging
import os
import platform
import subprocess
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torchrl.checkpoint import CheckpointRotation, GlobalRNGState, JSONCheckpointAdapter
from torchrl.record.loggers import CSVLogger

from torchrl_mbmf.trainers.checkpointing import (
    DatasetCheckpointAdapter,
    ReplayCheckpointAdapter,
    TensorStateAdapter,
    VerifiedCheckpoint,
    latest_intact_checkpoint,
)
from torchrl_mbmf.trainers.config import (
    MODEL_BASED,
    PPO_METHODS,
    RESUME_SAFE_SETTINGS,
    ConfigError,
    resume_changes,
)
from torchrl_mbmf.trainers.export import save_policy
from torchrl_mbmf.trainers.resume_logs import append_resume_log, cut_csv_logs

__all__ = ["RunCheckpoint", "fingerprint", "git_commit", "machine_record", "write_run_record"]

logger = logging.getLogger(__name__)


def fingerprint(cfg: Any) -> dict[str, Any]:
    """Config entries a checkpoint must agree on to be resumed (kept for old checkpoints).

    Args:
        cfg: the training config.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"method": "ppo", "env": {"id": "E", "num_envs": 1},
        ...     "reward": {"name": "default"}, "seed": 0,
        ...     "ppo": {"hidden_sizes": [8], "frames_per_batch": 64}})
        >>> fingerprint(cfg)["ppo.hidden_sizes"]
        [8]
    """
    algo = "ppo" if cfg.method in PPO_METHODS else "sac"
    out = {
        "method": cfg.method,
        "env.id": cfg.env.id,
        "env.num_envs": int(cfg.env.num_envs),
        "reward": OmegaConf.to_container(cfg.reward, resolve=True),
        "seed": int(cfg.seed),
        f"{algo}.hidden_sizes": list(cfg[algo].hidden_sizes),
        f"{algo}.frames_per_batch": int(cfg[algo].frames_per_batch),
    }
    if cfg.method in MODEL_BASED:
        out["world_model.hidden_sizes"] = list(cfg.world_model.hidden_sizes)
        out["world_model.random_steps"] = int(cfg.world_model.random_steps)
        for key in ("ensemble_size", "probabilistic", "multi_step", "multi_step_weight"):
            if key in cfg.world_model:
                out[f"world_model.{key}"] = cfg.world_model[key]
        planner = OmegaConf.to_container(cfg.planner, resolve=True)
        # the builder's name is no setting of the planner (fingerprints predate it)
        out["planner"] = {k: v for k, v in planner.items() if k != "_target_"}
    if cfg.method in ("mpc", "ppo_mpc"):
        out["planning_updates"] = int(cfg.planning_updates)
    return out


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


def write_run_record(run_dir: Path, cfg: Any) -> None:
    """Writes ``config.yaml``, ``git_commit.txt`` and ``machine.json`` into ``run_dir``.

    Args:
        run_dir: the run folder.
        cfg: the training config (written resolved).

    Examples:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> with tempfile.TemporaryDirectory() as d:
        ...     write_run_record(Path(d), OmegaConf.create({"seed": 0}))
        ...     sorted(p.name for p in Path(d).iterdir())
        ['config.yaml', 'git_commit.txt', 'machine.json']
    """
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    (run_dir / "git_commit.txt").write_text(git_commit() + "\n")
    (run_dir / "machine.json").write_text(json.dumps(machine_record(), indent=2) + "\n")


class RunCheckpoint:
    """The rotated, verified checkpoints of a run folder and the resume from them.

    Every component is restored without pickle, and only after the whole checkpoint passed its
    integrity record. A resume compares the saved config with this run's first and refuses
    any change outside :data:`~torchrl_mbmf.trainers.config.RESUME_SAFE_SETTINGS` (naming
    each, with both values); it records the allowed ones in ``resume_log.json`` and cuts the
    CSV logs back to the checkpoint (removes them when there is none).

    Args:
        run_dir: the run folder (checkpoints under ``checkpoints/``).
        progress: the loop's progress record (saved as JSON; holds ``config`` and
            ``fingerprint``).
        tensors: components saved as tensor state (modules, optimisers), in order.
        logger: the run's logger (its state is saved when it has one).

    Keyword Args:
        keep_last: checkpoints kept. Defaults to 2.
        dataset: the transition dataset, if any.
        dataset_needed: whether a checkpoint at a given progress record holds the dataset
            (``None``: always). A checkpoint written where it is not needed leaves it out,
            and resuming from one leaves the dataset as it is.
        replay: ``(buffer, keys)``: the replay buffer and the entries it stores, if any.
        backend: the logger backend's name (for the warning of uncut logs).

    Examples:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     progress = {"real_steps": 3, "config": {}, "fingerprint": {}}
        ...     run = RunCheckpoint(Path(d), progress, {"net": torch.nn.Linear(1, 1)}, None)
        ...     run.save(torch.nn.Linear(1, 1))
        ...     run.resume()
        True
    """

    def __init__(
        self,
        run_dir: Path,
        progress: dict[str, Any],
        tensors: Mapping[str, Any],
        logger: Any,
        *,
        keep_last: int = 2,
        dataset: Any = None,
        dataset_needed: Callable[[Mapping[str, Any]], bool] | None = None,
        replay: tuple[Any, Any] | None = None,
        backend: str = "csv",
    ) -> None:
        self.run_dir = Path(run_dir)
        self.dataset_needed = dataset_needed
        self.progress = progress
        self.logger = logger
        self.backend = backend
        checkpoint = VerifiedCheckpoint()
        checkpoint.register("progress", progress, adapter=JSONCheckpointAdapter())
        components = {**tensors, "rng": GlobalRNGState()}
        if logger is not None and hasattr(logger, "state_dict"):
            components["logger"] = logger
        state = TensorStateAdapter()
        for name, component in components.items():
            checkpoint.register(name, component, adapter=state)
        if dataset is not None:
            checkpoint.register("dataset", dataset, adapter=DatasetCheckpointAdapter())
        if replay is not None:
            buffer, keys = replay
            checkpoint.register("replay", buffer, adapter=ReplayCheckpointAdapter(keys=keys))
        self.checkpoint = checkpoint
        self.names = ["progress", *components]
        if dataset is not None:
            self.names.append("dataset")
        if replay is not None:
            self.names.append("replay")
        self.rotation = CheckpointRotation(self.run_dir / "checkpoints", keep_last=keep_last)

    def save(self, actor: torch.nn.Module) -> None:
        """Atomically writes a checkpoint at the current step (once per step) and the policy."""
        latest = self.rotation.latest()
        step = self.progress["real_steps"]
        if latest is not None and latest.name.endswith(f"{step:012d}"):
            return
        self.rotation.save(self.checkpoint, step=step, components=self.components())
        save_policy(actor, self.run_dir, step)

    def components(self) -> list[str]:
        """The components a checkpoint at the current progress holds (in registration order)."""
        needed = self.dataset_needed is None or self.dataset_needed(self.progress)
        return [name for name in self.names if name != "dataset" or needed]

    def resume(self) -> bool:
        """Restores the newest intact checkpoint if there is one; returns whether it did.

        Raises:
            ConfigError: if the checkpoint was written with settings that change training.
        """
        latest = latest_intact_checkpoint(self.rotation)
        if latest is None:
            # A run killed before its first checkpoint starts again: its rows go.
            removed = self._cut_logs({})
            if removed:
                append_resume_log(self.run_dir, {"event": "restart", "removed_rows": removed})
            return False
        expected = dict(self.progress["fingerprint"])
        config = self.progress["config"]
        # Compare the config first (the progress entry alone), then restore everything.
        self.checkpoint.load(latest, components=["progress"])
        allowed = self._check_compatible(latest, expected, config)
        components = self.components()
        stored = set(self.checkpoint.manifest(latest)["components"])
        if missing := [name for name in components if name not in stored]:
            raise ValueError(
                f"{latest} holds no {', '.join(missing)}, which a run at its progress "
                f"(phase {self.progress.get('phase')!r}) needs"
            )
        self.checkpoint.load(latest, components=components)
        self.progress["config"] = config
        self.progress["fingerprint"] = expected
        cut = self._cut_logs(self.logger.experiment.scalars if self._csv_logs() else {})
        append_resume_log(
            self.run_dir,
            {
                "event": "resume",
                "checkpoint": latest.name,
                "real_steps": self.progress["real_steps"],
                "allowed_changes": {
                    key: {"checkpoint": old, "now": new} for key, (old, new) in allowed.items()
                },
                "removed_rows": cut,
            },
        )
        logger.info("resumed from %s at %d real steps", latest, self.progress["real_steps"])
        return True

    def _check_compatible(
        self, latest: Path, expected: dict[str, Any], config: dict[str, Any]
    ) -> dict[str, tuple[Any, Any]]:
        saved = self.progress.get("config")
        allowed: dict[str, tuple[Any, Any]] = {}
        if saved is None:  # written before whole configs were saved: the fingerprint only
            logger.warning("%s predates saved configs: only its fingerprint is compared", latest)
            old = self.progress["fingerprint"]
            refused = {k: (old.get(k), v) for k, v in expected.items() if old.get(k) != v}
        else:
            refused, allowed = resume_changes(saved, config)
        if refused:
            lines = "\n".join(
                f"  was written with {key}={old!r}, this run has {key}={new!r}"
                for key, (old, new) in refused.items()
            )
            raise ConfigError(
                f"checkpoint {latest} was written with other settings that change training:\n"
                f"{lines}\nuse another run_dir or the original config (settings a resume may "
                f"change: {list(RESUME_SAFE_SETTINGS)})"
            )
        return allowed

    def _csv_logs(self) -> bool:
        return isinstance(self.logger, CSVLogger)

    def _cut_logs(self, rows: dict[str, Any]) -> dict[str, int]:
        """Cuts the CSV series back to ``rows`` (see :func:`cut_csv_logs`)."""
        if not self._csv_logs():
            if self.logger is not None and self.rotation.latest() is not None:
                logger.warning("logs of backend %s are not cut on resume", self.backend)
            return {}
        return cut_csv_logs(Path(self.logger.experiment.log_dir) / "scalars", rows)
