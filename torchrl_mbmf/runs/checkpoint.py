"""A run's checkpoint: what it holds, when it is written, and the resume from it.

A checkpoint is a folder ``<run_dir>/checkpoints/<step>/`` written by :class:`RunCheckpoint`
(rotated, verified, no pickle). It holds, under these component names:

- ``progress``: the loop's progress record (JSON), with the run's config and fingerprint;
- the tensor state of each part the trainer registers: the agent's networks, optimiser and
  loss state (``PPOAgent`` / ``SACAgent.checkpoint_components``) and, for model-based
  methods, the world model and its optimiser (``WorldModelPart.checkpoint_components``);
- ``rng``: the global random states (Python, NumPy, torch);
- ``logger``: the logger's state (the CSV rows written so far), when it has one;
- ``dataset``: the real-transition dataset (model-based methods), left out where the
  schedule no longer needs it (after planning ends);
- ``replay``: SAC's replay buffer entries;
- ``model_replay``: ``sac_mbpo``'s imagined transitions, and ``model_rounds``: what re-runs
  the rollout rounds they come from
  (:class:`~torchrl_mbmf.world_model.branched_rollouts.RolloutRounds`).

Beside each checkpoint the trained policy is exported (``policy.pt``). How the folders are
written and checked is :mod:`torchrl_mbmf.runs.storage`; what a resume may change is
:mod:`torchrl_mbmf.runs.resume`; a compact, committable form of a checkpoint is
:func:`~torchrl_mbmf.runs.dataset_replay.compact_checkpoint` (the dataset and both replays
kept as what rebuilds them exactly).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import torch
from tensordict import NestedKey
from torchrl.checkpoint import CheckpointRotation, GlobalRNGState, JSONCheckpointAdapter
from torchrl.data import TensorDictReplayBuffer
from torchrl.record.loggers import CSVLogger, Logger

from torchrl_mbmf.checks import ConfigError
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.runs.export import save_policy
from torchrl_mbmf.runs.layout import CHECKPOINTS, SUMMARY, RunFolder
from torchrl_mbmf.runs.logs import append_resume_log, cut_csv_logs
from torchrl_mbmf.runs.resume import (
    RESUME_SAFE_SETTINGS,
    check_resume_budget,
    describe_refused,
    resume_changes,
)
from torchrl_mbmf.runs.storage import (
    DatasetCheckpointAdapter,
    ReplayCheckpointAdapter,
    SealedWriter,
    TensorStateAdapter,
    latest_intact_checkpoint,
)

__all__ = ["ModelReplaySource", "ProgressAdapter", "ProgressRecord", "RunCheckpoint"]

#: Components a checkpoint written before they existed lacks (a resume goes on without them).
OPTIONAL_COMPONENTS = ("model_rounds",)

logger = logging.getLogger(__name__)


class ProgressRecord(Protocol):
    """The loop state a checkpoint holds, read by entry (a ``dict`` or a typed state object).

    A typed object (``torchrl_mbmf.trainers.schedule.Progress``) also has ``to_dict`` and
    ``load_dict``, which :class:`ProgressAdapter` uses.

    Args:
        *args: none (a protocol is not instantiated).
        **kwargs: none.

    Examples:
        >>> record: ProgressRecord = {"real_steps": 3}
        >>> record["real_steps"]
        3
    """

    def __getitem__(self, key: str) -> Any: ...

    def __setitem__(self, key: str, value: Any) -> None: ...

    def get(self, key: str, default: Any = None) -> Any:
        """The entry ``key``, ``default`` if it is missing."""
        ...


class ModelReplaySource(Protocol):
    """What ``sac_mbpo``'s model replay is checkpointed from (a ``BranchedRollouts``).

    Args:
        *args: none (a protocol is not instantiated).
        **kwargs: none.

    Examples:
        >>> from torchrl_mbmf.world_model.branched_rollouts import BranchedRollouts
        >>> sorted(ModelReplaySource.__annotations__)
        ['keys', 'replay', 'rounds']
    """

    replay: TensorDictReplayBuffer
    keys: Sequence[NestedKey]
    rounds: Any


class ProgressAdapter(JSONCheckpointAdapter):
    """TorchRL's JSON adapter for the progress record, a ``dict`` or a typed state object.

    An object with ``to_dict`` / ``load_dict`` is stored as the same ``value.json`` a
    ``dict`` is, so checkpoints of either load into either.

    Examples:
        >>> import tempfile
        >>> adapter = ProgressAdapter()
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _ = adapter.save({"real_steps": 3}, Path(d), args=(), kwargs={})
        ...     restored = {}
        ...     _ = adapter.load(restored, Path(d), map_location=None, tensor_load_kwargs={},
        ...                      args=(), kwargs={})
        >>> restored
        {'real_steps': 3}
    """

    def save(self, component: Any, path: Path, *, args: tuple, kwargs: Mapping[str, Any]) -> Any:
        """Writes ``component`` (its ``to_dict()`` if it has one) as JSON."""
        value = component.to_dict() if hasattr(component, "to_dict") else component
        super().save(value, path, args=args, kwargs=kwargs)
        return component

    def load(self, component: Any, path: Path, **kwargs: Any) -> Any:
        """Restores ``component`` in place (through its ``load_dict`` if it has one)."""
        if not hasattr(component, "load_dict"):
            return super().load(component, path, **kwargs)
        value: dict[str, Any] = {}
        super().load(value, path, **kwargs)
        component.load_dict(value)
        return component


class RunCheckpoint:
    """The rotated, verified checkpoints of a run folder and the resume from them.

    Every component is restored without pickle, and only after the whole checkpoint passed its
    integrity record. A resume compares the saved config with this run's first and refuses
    any change outside :data:`~torchrl_mbmf.runs.resume.RESUME_SAFE_SETTINGS` (naming
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
        model_replay: the rollouts of ``sac_mbpo`` (their ``replay`` of imagined transitions,
            its ``keys`` and the ``rounds`` that rebuild it), if any.
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
        progress: ProgressRecord,
        tensors: Mapping[str, Any],
        logger: Logger | None,
        *,
        keep_last: int = 2,
        dataset: TransitionDataset | None = None,
        dataset_needed: Callable[[Any], bool] | None = None,
        replay: tuple[TensorDictReplayBuffer, Sequence[NestedKey]] | None = None,
        model_replay: ModelReplaySource | None = None,
        backend: str = "csv",
    ) -> None:
        self.run_dir = Path(run_dir)
        self.dataset_needed = dataset_needed
        self.progress = progress
        self.logger = logger
        self.backend = backend
        checkpoint = SealedWriter()
        checkpoint.register("progress", progress, adapter=ProgressAdapter())
        components = {**tensors, "rng": GlobalRNGState()}
        if logger is not None and hasattr(logger, "state_dict"):
            components["logger"] = logger
        state = TensorStateAdapter()
        for name, component in components.items():
            checkpoint.register(name, component, adapter=state)
        if dataset is not None:
            checkpoint.register("dataset", dataset, adapter=DatasetCheckpointAdapter())
        self.names = ["progress", *components]
        if dataset is not None:
            self.names.append("dataset")
        model = None if model_replay is None else (model_replay.replay, model_replay.keys)
        for name, entry in (("replay", replay), ("model_replay", model)):
            if entry is not None:
                buffer, keys = entry
                checkpoint.register(name, buffer, adapter=ReplayCheckpointAdapter(keys=keys))
                self.names.append(name)
        if model_replay is not None:
            checkpoint.register("model_rounds", model_replay.rounds, adapter=state)
            self.names.append("model_rounds")
        self.checkpoint = checkpoint
        self.rotation = CheckpointRotation(self.run_dir / CHECKPOINTS, keep_last=keep_last)
        #: The resume-safe settings the last :meth:`resume` found changed (``{key: (old, new)}``).
        self.allowed_changes: dict[str, tuple[Any, Any]] = {}

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
        check_resume_budget(self.progress["real_steps"], config, latest)
        self.allowed_changes = allowed
        stored = set(self.checkpoint.manifest(latest)["components"])
        components = [n for n in self.components() if n in stored or n not in OPTIONAL_COMPONENTS]
        if missing := [name for name in components if name not in stored]:
            raise ValueError(
                f"{latest} holds no {', '.join(missing)}, which a run at its progress "
                f"(phase {self.progress.get('phase')!r}) needs"
            )
        self.checkpoint.load(latest, components=components)
        self.progress["config"] = config
        self.progress["fingerprint"] = expected
        cut = self._cut_logs(self.logger.experiment.scalars if self._csv_logs() else {})
        previous = self._raised_summary(config)
        # git_commit.txt and machine.json are rewritten by this process next: the commit and
        # machine of the process before it (the last to run in this folder) go into this entry
        folder = RunFolder(Path(self.run_dir))
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
                "previous_commit": folder.read_commit(),
                "previous_machine": folder.read_machine(),
                **({} if previous is None else {"previous_summary": previous}),
            },
        )
        if previous is not None:
            # a finished run continued to a raised total_steps is unfinished again until it
            # writes its new summary; the old one is kept in the entry just logged
            (Path(self.run_dir) / SUMMARY).unlink()
        logger.info("resumed from %s at %d real steps", latest, self.progress["real_steps"])
        return True

    def _raised_summary(self, config: Mapping[str, Any]) -> dict[str, Any] | None:
        """The folder's ``summary.json`` if it ends short of ``config``'s ``total_steps``."""
        path = Path(self.run_dir) / SUMMARY
        if not path.exists():
            return None
        summary = json.loads(path.read_text())
        total = config.get("total_steps")
        done = summary.get("real_steps")
        if isinstance(total, int) and isinstance(done, int) and done < total:
            return summary
        return None

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
            lines = describe_refused(refused)
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
