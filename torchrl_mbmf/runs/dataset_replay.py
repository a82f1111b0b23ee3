"""A run's real-transition dataset kept as the actions that made it, rebuilt by replaying them.

:class:`DatasetReplay` records the actions, seeded resets and trajectory ids;
:meth:`DatasetReplay.rebuild` replays them and accepts the result only if it matches the
dataset's checksum bit for bit. :func:`compact_checkpoint` and :func:`expand_checkpoint` swap a
checkpoint's dataset for its replay and back (a checkpoint small enough to commit). Why this
works: ``docs/design/run_folder.md``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite
from torchrl.envs import EnvBase

from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.data import CorruptDatasetError, TransitionDataset
from torchrl_mbmf.data.dataset_files import TERMINATED_KEY
from torchrl_mbmf.data.episodes import TRAJ_KEY, episode_ends
from torchrl_mbmf.runs.storage import DatasetCheckpointAdapter, verify_checkpoint

if TYPE_CHECKING:
    from torchrl_mbmf.runs.buffer_replay import RolloutsLike

__all__ = [
    "DatasetReplay",
    "NotReplayableError",
    "compact_checkpoint",
    "expand_checkpoint",
    "find_resets",
    "replay_rows",
]

_FORMAT = "torchrl_mbmf.dataset_replay/1"
_ACTIONS_FILE = "actions.bin"
_RECORD_FILE = "replay.json"
#: The folder a compacted checkpoint's dataset component holds instead of ``transitions``.
REPLAY_DIR = "replay"
_DATASET_DIR = "transitions"  # DatasetCheckpointAdapter's folder


class NotReplayableError(ValueError):
    """Replaying the actions in the env does not give the dataset's transitions."""


class _ActionSequence:
    """A policy that plays stored actions in order (its spec is complete: no probe call)."""

    def __init__(self, actions: torch.Tensor, env: EnvBase) -> None:
        self.actions = actions
        self.cursor = 0
        self.action_key = env.action_key
        self.spec = Composite({self.action_key: env.full_action_spec_unbatched[env.action_key]})

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set(self.action_key, self.actions[self.cursor])
        self.cursor += 1
        return td


class _Replayer:
    """Steps ``env`` through ``actions`` with the collector the training used."""

    def __init__(self, env: EnvBase, actions: torch.Tensor) -> None:
        if not LeanCollector.supports(env):
            raise ValueError(
                f"replaying needs a single real env built by make_env / make_gym_state_env "
                f"(num_envs=1), got {env!r}"
            )
        self.env = env
        self.policy = _ActionSequence(actions, env)
        self.collector: LeanCollector | None = None

    def reseed(self, seed: int) -> None:
        """Seeds the env and starts a collector (which resets it), as the trainer does."""
        if self.collector is not None:
            self.collector.shutdown()
        self.env.set_seed(int(seed))
        self.collector = LeanCollector(self.env, self.policy, frames_per_batch=1)

    def steps(self, start: int, stop: int) -> TensorDictBase:
        """Rows ``start:stop``, continuing the env where it is (resetting after episode ends)."""
        self.policy.cursor = start
        self.collector.frames_per_batch = stop - start
        return next(iter(self.collector))

    def close(self) -> None:
        if self.collector is not None:
            self.collector.shutdown()


def _episode_starts(data: TensorDictBase, state_key: Any) -> tuple[list[int], set[int]]:
    """Rows where an episode starts, and those of them not preceded by an episode end."""
    state, next_state = data.get(state_key), data.get(("next", state_key))
    done = data.get(("next", "done")).reshape(-1)
    broken = (state[1:] != next_state[:-1]).any(-1)
    starts = torch.nonzero(broken | done[:-1]).reshape(-1) + 1
    forced = torch.nonzero(broken & ~done[:-1]).reshape(-1) + 1
    return [0, *starts.tolist()], {0, *forced.tolist()}


def _stored(
    batch: TensorDictBase, state_key: Any, reward_key: Any, terminated: bool
) -> TensorDictBase:
    """The dataset's fields of a collector batch (without the trajectory ids)."""
    nxt = {
        state_key: batch.get(("next", state_key)),
        reward_key: batch.get(("next", reward_key)),
        "done": episode_ends(batch).unsqueeze(-1),
    }
    if terminated:  # a dataset saved before the flags were stored has none to check
        nxt["terminated"] = batch.get(TERMINATED_KEY).reshape(*batch.batch_size, 1).bool()
    return TensorDict(
        {state_key: batch.get(state_key), "action": batch.get("action"), "next": nxt},
        batch_size=batch.batch_size,
    )


def _sha256(array: np.ndarray) -> str:
    return hashlib.sha256(array.tobytes()).hexdigest()


def find_resets(
    data: TensorDictBase,
    actions: torch.Tensor,
    state_key: Any,
    env: EnvBase,
    seed: int,
    stored: Callable[[TensorDictBase], TensorDictBase],
) -> list[tuple[int, int]]:
    """The seeded resets that replay ``actions`` into ``data`` (checked value by value).

    Args:
        data: the stored rows ``[N]`` in the order they were collected (``state_key`` and
            ``("next", "done")`` among their entries).
        actions: their actions ``[N, *action_shape]``.
        state_key: the entry that holds the env's state.
        env: a fresh copy of the env that collected them (``num_envs=1``).
        seed: the run's seed (see :meth:`DatasetReplay.from_dataset`).
        stored: maps a collector batch to the entries ``data`` stores.

    Returns:
        ``(row, seed)`` pairs: the env was seeded with ``seed`` and reset before ``row``.

    Raises:
        NotReplayableError: naming the first row and entry where the replay differs.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=3), 250, seed=3)
        >>> rows = data.tensors()
        >>> pick = lambda batch: batch.select("state", ("next", "state"))
        >>> find_resets(rows, rows["action"], "state", make_env("Pendulum-v1"), 3, pick)
        [(0, 3)]
    """
    n = int(actions.shape[0])
    starts, forced = _episode_starts(data, state_key)
    replayer = _Replayer(env, actions)
    resets: list[tuple[int, int]] = []
    try:
        for a, b in zip(starts, [*starts[1:], n], strict=True):
            batch = None
            if a not in forced:  # after an episode end: does the env's own reset fit?
                batch = replayer.steps(a, b)
                if not torch.equal(batch.get(state_key)[0], data.get(state_key)[a]):
                    batch = None
            if batch is None:
                replayer.reseed(seed + a)
                resets.append((a, seed + a))
                batch = replayer.steps(a, b)
            got = stored(batch)
            for key in got.keys(True, True):
                if not torch.equal(got.get(key), data.get(key)[a:b]):
                    rows = (got.get(key) != data.get(key)[a:b]).reshape(b - a, -1).any(-1)
                    row = a + int(torch.nonzero(rows)[0])
                    raise NotReplayableError(
                        f"replaying the actions gives another {key!r} at row {row} (episode "
                        f"rows {a}-{b}, seeded {resets[-1]}): the env or its seeding is "
                        "not the one that collected the rows"
                    )
    finally:
        replayer.close()
    return resets


def replay_rows(
    env: EnvBase,
    actions: torch.Tensor,
    resets: Sequence[tuple[int, int]],
    stored: Callable[[TensorDictBase], TensorDictBase],
    *,
    chunk: int = 20_000,
) -> list[TensorDictBase]:
    """Replays ``actions`` in ``env`` from the seeded ``resets``; the stored entries, in parts.

    Args:
        env: a fresh copy of the env that collected the rows (``num_envs=1``).
        actions: the actions ``[N, *action_shape]``.
        resets: ``(row, seed)`` pairs (see :func:`find_resets`).
        stored: maps a collector batch to the entries kept.

    Keyword Args:
        chunk: most steps replayed in one collector batch. Defaults to ``20_000``.

    Returns:
        The kept entries of consecutive steps (empty without actions).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=3), 250, seed=3)
        >>> rows = data.tensors()
        >>> parts = replay_rows(make_env("Pendulum-v1"), rows["action"], [(0, 3)],
        ...                     lambda batch: batch.select("state"), chunk=100)
        >>> len(parts), torch.equal(torch.cat(parts)["state"], rows["state"])
        (3, True)
    """
    n = int(actions.shape[0])
    parts: list[TensorDictBase] = []
    if not n:
        return parts
    replayer = _Replayer(env, actions)
    bounds = [row for row, _ in resets] + [n]
    try:
        for (a, seed), b in zip(resets, bounds[1:], strict=True):
            replayer.reseed(seed)
            for start in range(a, b, chunk):
                parts.append(stored(replayer.steps(start, min(b, start + chunk))))
    finally:
        replayer.close()
    return parts


class DatasetReplay:
    """The record that rebuilds a run's :class:`~torchrl_mbmf.data.TransitionDataset` in its env.

    :meth:`from_dataset` finds the seeded rows by replaying the actions (checking every stored
    value on the way); :meth:`rebuild` replays them again, on this or another machine, and
    returns the dataset only if it matches the record's checksum bit for bit.

    Args:
        actions: the ``[N, *action_shape]`` float32 actions, row by row.
        resets: ``(row, seed)`` pairs in row order, the first at row 0: before ``row`` the
            env was seeded with ``seed`` and reset.
        trajectories: ``(row, trajectory id)`` pairs in row order, the first at row 0: the id
            of the rows from ``row`` to the next pair.
        record: the dataset's :meth:`~torchrl_mbmf.data.TransitionDataset.record`.

    Raises:
        ValueError: naming the argument that does not fit the others.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.runs.dataset_replay import DatasetReplay
        >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=3), 250, seed=3)
        >>> replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=3)
        >>> replay.resets, replay.trajectories
        ([(0, 3)], [(0, 0), (200, 1)])
        >>> rebuilt = replay.rebuild(make_env("Pendulum-v1"))
        >>> rebuilt.record()["sha256"] == data.record()["sha256"]
        True
    """

    def __init__(
        self,
        actions: torch.Tensor,
        resets: Sequence[tuple[int, int]],
        trajectories: Sequence[tuple[int, int]],
        record: Mapping[str, Any],
    ) -> None:
        n = int(record.get("num_transitions", -1))
        if actions.dtype != torch.float32 or actions.ndim < 1 or actions.shape[0] != n:
            raise ValueError(
                f"actions must be float32 with one row per transition ({n}), got "
                f"{actions.dtype} {tuple(actions.shape)}"
            )
        for name, pairs in (("resets", resets), ("trajectories", trajectories)):
            rows = [int(row) for row, _ in pairs]
            if n and (not rows or rows[0] != 0 or rows != sorted(set(rows)) or rows[-1] >= n):
                raise ValueError(
                    f"{name} must start at row 0 and rise strictly below {n}, got rows {rows[:8]}"
                )
        self.actions = actions
        self.resets = [(int(r), int(s)) for r, s in resets]
        self.trajectories = [(int(r), int(i)) for r, i in trajectories]
        self.record = json.loads(json.dumps(dict(record)))

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @classmethod
    def from_dataset(cls, dataset: TransitionDataset, env: EnvBase, *, seed: int) -> DatasetReplay:
        """The replay record of ``dataset``, checked by replaying it in ``env``.

        Args:
            dataset: transitions collected by the trainer's single env, in order.
            env: a fresh copy of that env (same id, reward and settings; ``num_envs=1``).

        Keyword Args:
            seed: the run's seed: an episode that starts without a preceding episode end (a
                new collector) was seeded with ``seed + row``; one after an episode end either
                continues the env's stream or, at a collector start, was seeded the same way.

        Returns:
            The record.

        Raises:
            NotReplayableError: naming the first row and field where the replay differs.
        """
        n = len(dataset)
        record = dataset.record()
        if n == 0:
            return cls(torch.zeros(0, dtype=torch.float32), [], [], record)
        data = dataset.tensors()
        state_key, reward_key = dataset.state_key, dataset.reward_key
        actions = data.get(dataset.action_key).clone()
        if dataset.action_key != "action":
            raise ValueError(f"replaying needs the action key 'action', got {dataset.action_key}")
        pick = lambda batch: _stored(  # noqa: E731
            batch, state_key, reward_key, dataset.stores_terminated
        )
        resets = find_resets(data, actions, state_key, env, seed, pick)
        ids = data.get(TRAJ_KEY)
        changes = torch.nonzero(ids[1:] != ids[:-1]).reshape(-1) + 1
        rows = [0, *changes.tolist()]
        trajectories = [(row, int(ids[row])) for row in rows]
        return cls(actions, resets, trajectories, record)

    def rebuild(
        self,
        env: EnvBase,
        *,
        capacity: int | None = None,
        scratch_dir: str | os.PathLike | None = None,
        chunk: int = 20_000,
    ) -> TransitionDataset:
        """Replays the actions in ``env`` and returns the dataset, checked against its record.

        Args:
            env: a fresh copy of the env that collected the dataset (``num_envs=1``).

        Keyword Args:
            capacity: the dataset's capacity. Defaults to the recorded one.
            scratch_dir: folder of its memory-mapped files. Defaults to a temporary folder.
            chunk: most steps replayed in one collector batch. Defaults to ``20_000``.

        Returns:
            The dataset, bit-identical to the recorded one.

        Raises:
            CorruptDatasetError: if the replayed transitions do not match the record's checksum
                (another env version or machine whose physics differ in the last bit).
        """
        n = len(self)
        keys = [tuple(k) if isinstance(k, list) else k for k in self.record["keys"]]
        state_key, reward_key = keys[0], keys[3][1]
        terminated = TERMINATED_KEY in keys
        pick = lambda batch: _stored(batch, state_key, reward_key, terminated)  # noqa: E731
        parts = replay_rows(env, self.actions, self.resets, pick, chunk=chunk)
        stored = None
        if parts:
            stored = torch.cat(parts)
            ids = torch.empty(n, dtype=torch.long)
            rows = [row for row, _ in self.trajectories] + [n]
            for (a, traj), b in zip(self.trajectories, rows[1:], strict=True):
                ids[a:b] = traj
            stored.set(TRAJ_KEY, ids)
        try:
            return TransitionDataset.from_record(
                self.record,
                stored,
                capacity=capacity,
                scratch_dir=scratch_dir,
                source="the replayed transitions",
            )
        except CorruptDatasetError as err:
            raise CorruptDatasetError(
                f"{err} (the env replays the actions differently here than where they were taken)"
            ) from err

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Writes ``replay.json`` and the raw actions (``actions.bin``) into the folder ``path``.

        Args:
            path: target folder.

        Keyword Args:
            overwrite: replace an existing folder. Defaults to ``False``.

        Returns:
            The path.

        Raises:
            FileExistsError: if ``path`` exists and ``overwrite`` is ``False``.

        Examples:
            >>> import tempfile
            >>> from pathlib import Path
            >>> from torchrl_mbmf.data import collect_random_transitions
            >>> from torchrl_mbmf.envs import make_env
            >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=0), 300, seed=0)
            >>> replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=0)
            >>> with tempfile.TemporaryDirectory() as d:
            ...     path = replay.save(Path(d) / "replay")
            ...     loaded = DatasetReplay.load(path)
            ...     size = (path / "actions.bin").stat().st_size
            >>> size, loaded.resets == replay.resets  # 4 bytes an action
            (1200, True)
        """
        return _write_replay(self, path, overwrite)

    @classmethod
    def load(cls, path: str | os.PathLike) -> DatasetReplay:
        """Reads a folder written by :meth:`save` (JSON and raw float32 only: nothing unpickled).

        Args:
            path: the folder.

        Returns:
            The record.

        Raises:
            FileNotFoundError: if ``path`` has no ``replay.json``.
            CorruptDatasetError: on another format, or actions of another size or checksum.

        Examples:
            >>> import tempfile
            >>> from pathlib import Path
            >>> from torchrl_mbmf.data import collect_random_transitions
            >>> from torchrl_mbmf.envs import make_env
            >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=0), 300, seed=0)
            >>> replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=0)
            >>> with tempfile.TemporaryDirectory() as d:
            ...     rebuilt = DatasetReplay.load(replay.save(Path(d) / "r")).rebuild(
            ...         make_env("Pendulum-v1"))
            >>> rebuilt.record() == data.record()
            True
        """
        return cls(*_read_replay(path))


def _write_replay(replay: DatasetReplay, path: str | os.PathLike, overwrite: bool) -> Path:
    """:meth:`DatasetReplay.save`'s writing."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        raw = replay.actions.numpy().astype("<f4", copy=False)
        (tmp / _ACTIONS_FILE).write_bytes(raw.tobytes())
        meta = {
            "format": _FORMAT,
            "num_transitions": len(replay),
            "action_shape": list(replay.actions.shape[1:]),
            "actions_sha256": _sha256(raw),
            "resets": [list(pair) for pair in replay.resets],
            "trajectories": [list(pair) for pair in replay.trajectories],
            "record": replay.record,
        }
        (tmp / _RECORD_FILE).write_text(json.dumps(meta, indent=1, sort_keys=True))
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def _read_replay(
    path: str | os.PathLike,
) -> tuple[torch.Tensor, list[tuple[int, int]], list[tuple[int, int]], dict[str, Any]]:
    """:meth:`DatasetReplay.load`'s reading: the constructor's arguments."""
    path = Path(path)
    meta_file = path / _RECORD_FILE
    if not meta_file.is_file():
        raise FileNotFoundError(f"no dataset replay at {path} (missing {_RECORD_FILE})")
    try:
        meta = json.loads(meta_file.read_text())
    except json.JSONDecodeError as err:
        raise CorruptDatasetError(f"{meta_file} is not valid JSON: {err}") from err
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise CorruptDatasetError(f"{meta_file} has format {found!r}, expected {_FORMAT!r}")
    shape = [int(meta["num_transitions"]), *(int(d) for d in meta["action_shape"])]
    raw = (path / _ACTIONS_FILE).read_bytes() if (path / _ACTIONS_FILE).is_file() else b""
    if len(raw) != 4 * int(np.prod(shape)):
        raise CorruptDatasetError(
            f"{path / _ACTIONS_FILE} has {len(raw)} bytes, expected {4 * int(np.prod(shape))} "
            f"(float32 actions of shape {shape})"
        )
    array = np.frombuffer(raw, dtype="<f4")
    if _sha256(array) != meta["actions_sha256"]:
        raise CorruptDatasetError(f"{path / _ACTIONS_FILE} does not match its SHA-256")
    actions = torch.from_numpy(array.astype(np.float32).reshape(shape))
    return (
        actions,
        [tuple(pair) for pair in meta["resets"]],
        [tuple(pair) for pair in meta["trajectories"]],
        meta["record"],
    )


def _dataset_components(checkpoint: Path) -> list[Path]:
    """The folders of a checkpoint's dataset components (from its manifest)."""
    manifest = json.loads((checkpoint / "manifest.json").read_text())
    adapter = DatasetCheckpointAdapter.adapter_id
    return [
        checkpoint / entry["path"]
        for entry in manifest["components"].values()
        if entry.get("adapter") == adapter
    ]


def compact_checkpoint(
    checkpoint: str | os.PathLike,
    dest: str | os.PathLike,
    env: EnvBase,
    *,
    seed: int,
    rollouts: RolloutsLike | None = None,
) -> Path:
    """Copies a checkpoint to ``dest`` with each dataset replaced by its :class:`DatasetReplay`.

    The replay buffers go too: SAC's by the actions that made its rows, ``sac_mbpo``'s model
    replay by the record of its rollout rounds (:mod:`torchrl_mbmf.runs.buffer_replay`). The
    copy keeps the checkpoint's integrity record, which still lists the removed files: it
    verifies again only once :func:`expand_checkpoint` has rebuilt them bit for bit.

    Args:
        checkpoint: a verified checkpoint folder of a run.
        dest: the new folder (must not exist).
        env: a fresh copy of the run's real env (``num_envs=1``).

    Keyword Args:
        seed: the run's seed (see :meth:`DatasetReplay.from_dataset`).
        rollouts: rollouts built like the run's (a ``BranchedRollouts``), needed when the
            checkpoint holds a model replay (their parameters are overwritten). Defaults to
            ``None``.

    Returns:
        ``dest``.

    Raises:
        FileExistsError: if ``dest`` exists.
        NotReplayableError: if a dataset or replay buffer cannot be rebuilt exactly (a
            wrapped SAC replay, rollout rounds not all recorded; nothing is written then).
        ValueError: if the checkpoint holds a model replay and ``rollouts`` is ``None``.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.runs.storage import (
        ...     DatasetCheckpointAdapter, SealedWriter, verify_checkpoint)
        >>> from torchrl_mbmf.runs.dataset_replay import compact_checkpoint, expand_checkpoint
        >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=0), 300, seed=0)
        >>> checkpoint = SealedWriter()
        >>> _ = checkpoint.register("dataset", data, adapter=DatasetCheckpointAdapter())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     saved = checkpoint.save(Path(d) / "ckpt")
        ...     env = make_env("Pendulum-v1")
        ...     small = compact_checkpoint(saved, Path(d) / "small", env, seed=0)
        ...     rebuilt = expand_checkpoint(small, make_env("Pendulum-v1"))
        ...     verify_checkpoint(small)  # every file as saved
        >>> rebuilt
        True
    """
    from torchrl_mbmf.runs.buffer_replay import compact_replay, replay_components

    checkpoint, dest = Path(checkpoint), Path(dest)
    if dest.exists():
        raise FileExistsError(f"{dest} exists; remove it first")
    verify_checkpoint(checkpoint)
    replays = []
    for folder in _dataset_components(checkpoint):
        dataset = TransitionDataset.load(folder / _DATASET_DIR)
        replays.append((folder, DatasetReplay.from_dataset(dataset, env, seed=seed)))
    staging = dest.with_name(f".{dest.name}.compacting")
    shutil.rmtree(staging, ignore_errors=True)
    skip = {folder / _DATASET_DIR for folder, _ in replays}
    shutil.copytree(
        checkpoint, staging, ignore=lambda d, names: [n for n in names if Path(d) / n in skip]
    )
    try:
        for folder, replay in replays:
            replay.save(staging / folder.relative_to(checkpoint) / REPLAY_DIR)
        for name in replay_components(checkpoint):
            compact_replay(checkpoint, name, staging, env, seed=seed, rollouts=rollouts)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    os.replace(staging, dest)
    return dest


def expand_checkpoint(
    checkpoint: str | os.PathLike, env: EnvBase, *, rollouts: RolloutsLike | None = None
) -> bool:
    """Rebuilds in place the datasets and replays of a :func:`compact_checkpoint` copy.

    Each dataset replay is replayed in ``env`` and written back as the dataset, then each
    replay buffer is rebuilt (SAC's by replaying its actions, the model replay by re-running
    its rollout rounds), the records are removed, and the checkpoint must then pass its
    integrity record: every file as saved.

    Args:
        checkpoint: the compacted checkpoint folder.
        env: a fresh copy of the run's real env (``num_envs=1``).

    Keyword Args:
        rollouts: rollouts built like the run's, needed for a compacted model replay (their
            parameters are overwritten). Defaults to ``None``.

    Returns:
        Whether anything was rebuilt (``False``: the checkpoint holds no replay).

    Raises:
        CorruptDatasetError: if a replay does not rebuild its dataset bit for bit (nothing is
            changed then).
        CheckpointIntegrityError: if a file kept in the compact copy or a rebuilt one differs
            from the one saved (naming it).
        NotReplayableError: if a buffer's record does not fit its rows.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.runs.storage import (
        ...     DatasetCheckpointAdapter, SealedWriter, verify_checkpoint)
        >>> from torchrl_mbmf.runs.dataset_replay import compact_checkpoint, expand_checkpoint
        >>> data = collect_random_transitions(make_env("Pendulum-v1", seed=0), 300, seed=0)
        >>> checkpoint = SealedWriter()
        >>> _ = checkpoint.register("dataset", data, adapter=DatasetCheckpointAdapter())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     saved = checkpoint.save(Path(d) / "ckpt")
        ...     env = make_env("Pendulum-v1")
        ...     small = compact_checkpoint(saved, Path(d) / "small", env, seed=0)
        ...     rebuilt = expand_checkpoint(small, make_env("Pendulum-v1"))
        ...     verify_checkpoint(small)  # every file as saved
        >>> rebuilt
        True
    """
    from torchrl_mbmf.runs.buffer_replay import REBUILD_DIR, expand_replay, replay_components

    checkpoint = Path(checkpoint)
    # every file kept as saved (a changed round record or network is refused before any work)
    verify_checkpoint(checkpoint, compacted=(REPLAY_DIR, REBUILD_DIR))
    folders = [f for f in _dataset_components(checkpoint) if (f / REPLAY_DIR).is_dir()]
    rebuilt = []
    for folder in folders:
        dataset = DatasetReplay.load(folder / REPLAY_DIR).rebuild(env)
        rebuilt.append((folder, dataset))
    for folder, dataset in rebuilt:
        dataset.save(folder / _DATASET_DIR, overwrite=True)
        shutil.rmtree(folder / REPLAY_DIR)
    # SAC's replay before the model replay: rounds draw start states from the dataset
    expanded = [
        expand_replay(checkpoint, name, env, rollouts=rollouts)
        for name in sorted(replay_components(checkpoint), reverse=True)
    ]
    if rebuilt or any(expanded):
        verify_checkpoint(checkpoint)
    return bool(rebuilt) or any(expanded)
