"""The real-transition dataset the world model is fitted on, saved with its provenance."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

import torchrl_mbmf
from torchrl_mbmf.checks import check_number
from torchrl_mbmf.data.memmap import UnsafeFolderError, load_tensor_folder
from torchrl_mbmf.envs.factory import env_metadata
from torchrl_mbmf.envs.keys import STATE_KEY

# Version 2: the checksum also covers the metadata and each tensor's dtype and shape.
_FORMAT = "torchrl_mbmf.transitions/2"
_META_FILE = "metadata.json"
_BUFFER_DIR = "buffer"
TRAJ_KEY = "traj_id"


class DatasetMismatchError(ValueError):
    """A saved dataset was collected under another env, reward or key layout."""


class CorruptDatasetError(RuntimeError):
    """A saved dataset is truncated or its content does not match its checksum."""


def episode_ends(batch: TensorDictBase) -> torch.Tensor:
    """Where episodes end in a batch of transitions: ``done | terminated | truncated``.

    Args:
        batch: transitions with ``("next", "done")`` and/or ``terminated`` / ``truncated``.

    Returns:
        A bool tensor of the batch's shape.

    Raises:
        KeyError: none of the three flags is present.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.data.transitions import episode_ends
        >>> td = TensorDict(next=TensorDict(terminated=torch.tensor([[False], [True]]),
        ...                                 truncated=torch.tensor([[True], [False]])),
        ...                 batch_size=[2])
        >>> episode_ends(td).tolist()
        [True, True]
    """
    nxt = batch.get("next")
    done = nxt.get("done").clone() if "done" in nxt else None
    for key in ("terminated", "truncated"):
        if key in nxt:
            flag = nxt.get(key)
            done = flag.clone() if done is None else done | flag
    if done is None:
        raise KeyError("transitions need ('next', 'done') (or terminated/truncated)")
    return done.reshape(batch.batch_size)


def consecutive_windows(
    traj_ids: torch.Tensor,
    done: torch.Tensor,
    state: torch.Tensor,
    next_state: torch.Tensor,
    length: int,
) -> torch.Tensor:
    """Row indices of every run of ``length`` consecutive transitions inside one episode.

    Rows are put in time order within each episode by a stable sort on ``traj_ids`` (the
    storage order of one episode is its time order). Row ``j`` is followed by row ``j'`` in a
    window only if all three hold:

    * both carry the same trajectory id;
    * row ``j`` is not done (done, terminated or truncated: after it the env was reset);
    * row ``j``'s next state equals row ``j'``'s state exactly. A
      :class:`TransitionDataset` continues an episode id across ``extend`` calls unless the
      last step was done, so an env that was reset between two batches without a done flag
      (e.g. a new collector, which resets its env) would otherwise be joined to the episode
      before it; this check cuts such joins.

    The last transition of a window may be done: its next state is still the real one.

    Args:
        traj_ids: episode id of each row ``[N]``.
        done: done flag of each row ``[N]`` or ``[N, 1]``.
        state: state of each row ``[N, ...]``.
        next_state: next state of each row ``[N, ...]``.
        length: transitions per window (``>= 1``).

    Returns:
        A ``[W, length]`` long tensor of row indices, each row in time order; with
        ``length == 1`` every row is a window.

    Raises:
        ValueError: if ``length < 1``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.data.transitions import consecutive_windows
        >>> state = torch.arange(6.0)[:, None]
        >>> done = torch.tensor([False, False, True, False, False, False])
        >>> consecutive_windows(torch.tensor([0, 0, 0, 1, 1, 1]), done, state, state + 1, 2)
        tensor([[0, 1],
                [1, 2],
                [3, 4],
                [4, 5]])
    """
    if length < 1:
        raise ValueError(f"window length must be >= 1, got {length}")
    traj_ids = traj_ids.reshape(-1)
    n = traj_ids.numel()
    order = torch.sort(traj_ids, stable=True).indices
    if length == 1:
        return order[:, None]
    if n < length:
        return torch.empty(0, length, dtype=torch.long)
    cur, nxt = order[:-1], order[1:]
    link = (
        (traj_ids[cur] == traj_ids[nxt])
        & ~done.reshape(-1)[cur].bool()
        & (next_state[cur] == state[nxt]).reshape(n - 1, -1).all(-1)
    )
    # broken[j]: how many of the links between positions 0..j are broken
    broken = torch.cat([torch.zeros(1, dtype=torch.long), (~link).long().cumsum(0)])
    starts = torch.arange(n - length + 1)
    starts = starts[broken[starts + length - 1] == broken[starts]]
    return order[starts[:, None] + torch.arange(length)]


class TransitionDataset:
    """All real transitions ``(s, a, r, s')`` of a run, in a replay buffer stored on disk.

    The world model is fitted on every real transition collected so far (thesis section 5.1:
    random-policy data first, then every step the agent takes). Transitions are kept in a
    :class:`~torchrl.data.TensorDictReplayBuffer` over a
    :class:`~torchrl.data.LazyMemmapStorage`: memory-mapped files grow with the data instead
    of pre-allocating RAM for the full capacity, and torchrl's ``dumps``/``loads`` save and
    restore them. Only the keys the world model needs are stored (``state``, ``action``,
    ``("next", "state")``, ``("next", "reward")``, ``("next", "done")``) plus a trajectory id,
    so consecutive steps of each episode can be recovered for multi-step evaluation.

    ``save`` writes the stored transitions (a memory-mapped TensorDict) and a
    ``metadata.json`` (env id, reward name and parameters, step
    count, seed, package version, and a SHA-256 of the stored tensors) into a temporary folder
    renamed into place, so a crash during a save never leaves a half-written dataset under the
    target name. ``load`` checks the checksum against the data and metadata, then the metadata
    against what the caller expects, and raises instead of returning partial data. Loading
    never unpickles: the stored tensors are read from their raw files (see
    :func:`~torchrl_mbmf.data.memmap.load_tensor_folder`) and any other stored entry is
    refused. ``extend`` refuses transitions with a NaN or Inf in any stored field.

    Args:
        metadata: provenance, at least ``env_id`` and ``reward`` (see
            :func:`~torchrl_mbmf.envs.env_metadata`); an optional ``state_shape`` (the
            state's trailing shape) is checked by the first ``extend``.

    Keyword Args:
        capacity: maximal number of transitions. Defaults to ``2_000_000``.
        scratch_dir: folder of the memory-mapped files. Defaults to a temporary folder.
        state_key: state key. Defaults to ``"state"``.
        action_key: action key. Defaults to ``"action"``.
        reward_key: reward key (under ``"next"``). Defaults to ``"reward"``.

    Examples:
        >>> from torchrl_mbmf.data import TransitionDataset
        >>> from torchrl_mbmf.envs import env_metadata, make_gym_state_env
        >>> env = make_gym_state_env("Pendulum-v1", seed=0)
        >>> data = TransitionDataset(env_metadata(env))
        >>> data.extend(env.rollout(50))
        >>> len(data), data.tensors()["state"].shape
        (50, torch.Size([50, 3]))
    """

    def __init__(
        self,
        metadata: Mapping[str, Any],
        *,
        capacity: int = 2_000_000,
        scratch_dir: str | os.PathLike | None = None,
        state_key: NestedKey = STATE_KEY,
        action_key: NestedKey = "action",
        reward_key: NestedKey = "reward",
    ) -> None:
        for key in ("env_id", "reward"):
            if key not in metadata:
                raise ValueError(f"metadata needs an {key!r} entry, got {sorted(metadata)}")
        self.metadata = dict(metadata)
        self.capacity = check_number(capacity, "capacity", minimum=1, integer=True)
        self.state_key = state_key
        self.action_key = action_key
        self.reward_key = reward_key
        self._scratch = scratch_dir
        self.buffer = TensorDictReplayBuffer(
            storage=LazyMemmapStorage(self.capacity, scratch_dir=scratch_dir),
            sampler=RandomSampler(),
        )
        self._next_traj = 0
        self._open_traj: torch.Tensor | None = None  # id of each env's running episode
        # Trailing shape and dtype of each stored field, fixed by the first ``extend``.
        self._layout: dict[NestedKey, tuple[tuple[int, ...], torch.dtype]] | None = None

    def __len__(self) -> int:
        return len(self.buffer)

    @property
    def keys(self) -> list[NestedKey]:
        """The stored keys."""
        return [
            self.state_key,
            self.action_key,
            ("next", self.state_key),
            ("next", self.reward_key),
            ("next", "done"),
            TRAJ_KEY,
        ]

    def extend(self, batch: TensorDictBase) -> None:
        """Appends real transitions from ``env.rollout`` or a collector batch.

        Args:
            batch: ``[T]`` (one env) or ``[N, T]`` (``N`` batched envs) transitions. Episodes
                continue across calls: the last step of each env in one batch and the first of
                the next belong to the same episode unless it was done.

        Raises:
            ValueError: on a batch of another shape, an empty batch, missing keys, a stored
                field of another size or dtype than the dataset holds (floating fields must be
                ``float32``: wrap a float64 env in ``DoubleToFloat``), a NaN or Inf in a stored
                field (state, action, next state, reward; nothing is stored), or when full.
        """
        if batch.batch_dims not in (1, 2):
            raise ValueError(f"extend expects a [T] or [N, T] batch, got {tuple(batch.batch_size)}")
        if batch.batch_size.numel() == 0:
            raise ValueError(
                f"extend got an empty batch of shape {tuple(batch.batch_size)}; nothing to store"
            )
        if batch.batch_dims == 1:
            batch = batch.unsqueeze(0)
        n_envs, steps = batch.batch_size
        if len(self) + n_envs * steps > self.capacity:
            raise ValueError(
                f"dataset capacity {self.capacity} exceeded: holds {len(self)}, "
                f"adding {n_envs * steps}; build it with a larger capacity"
            )
        missing = [k for k in self.keys[:-2] if k not in batch.keys(True)]
        if missing:
            raise ValueError(f"transitions lack keys {missing}; present: {batch.keys(True)}")
        self._check_layout(batch)
        # One vectorised check per field, before anything is stored.
        for name in self.keys[:4]:
            if not torch.isfinite(batch.get(name)).all():
                raise ValueError(f"transitions contain NaN or Inf in {name!r}; nothing was stored")
        done = episode_ends(batch)
        if self._open_traj is None or self._open_traj.numel() != n_envs:
            self._open_traj = torch.arange(self._next_traj, self._next_traj + n_envs)
            self._next_traj += n_envs
        # A new episode starts after every done step; each done opens one new id (the last
        # step's done opens the id the env continues with in the next batch).
        starts = torch.zeros_like(done, dtype=torch.long)
        starts[:, 1:] = done[:, :-1].long()
        local = starts.cumsum(1)  # 0 for the episode left open by the previous batch
        opened = done.long().sum(1)
        base = self._next_traj + torch.cumsum(opened, 0) - opened
        ids = torch.where(local == 0, self._open_traj[:, None], base[:, None] + local - 1)
        self._open_traj = torch.where(opened > 0, base + opened - 1, self._open_traj)
        self._next_traj += int(opened.sum())
        flat = TensorDict(
            {
                self.state_key: batch.get(self.state_key),
                self.action_key: batch.get(self.action_key),
                "next": {
                    self.state_key: batch.get(("next", self.state_key)),
                    self.reward_key: batch.get(("next", self.reward_key)),
                    "done": done.unsqueeze(-1),
                },
                TRAJ_KEY: ids,
            },
            batch_size=[n_envs, steps],
        ).reshape(-1)
        self.buffer.extend(flat.to(torch.device("cpu")))

    def _check_layout(self, batch: TensorDictBase) -> None:
        """Refuses fields whose size or dtype differ from the stored ones (or are not float32)."""
        layout = {}
        for name in self.keys[:4]:
            value = batch.get(name)
            layout[name] = (tuple(value.shape[2:]), value.dtype)
            if value.dtype.is_floating_point and value.dtype != torch.float32:
                raise ValueError(
                    f"transitions' {name!r} is {value.dtype}, expected torch.float32 (the world "
                    "model's dtype): wrap a float64 env in torchrl's DoubleToFloat transform"
                )
        if self._layout is None and len(self) > 0:
            stored = self.tensors()
            self._layout = {
                k: (tuple(stored.get(k).shape[1:]), stored.get(k).dtype) for k in layout
            }
        if self._layout is None:
            self._check_first_states(layout)
            self._layout = layout
            return
        for name, (shape, dtype) in layout.items():
            want_shape, want_dtype = self._layout[name]
            if (shape, dtype) != (want_shape, want_dtype):
                raise ValueError(
                    f"transitions' {name!r} has trailing shape {list(shape)} and dtype {dtype}, "
                    f"but the dataset holds {list(want_shape)} and {want_dtype}; nothing was "
                    "stored (a dataset holds one env's transitions)"
                )

    def _check_first_states(
        self, layout: dict[NestedKey, tuple[tuple[int, ...], torch.dtype]]
    ) -> None:
        """The first batch's state and next state agree, and match ``metadata["state_shape"]``."""
        shape, next_shape = layout[self.state_key][0], layout[("next", self.state_key)][0]
        want = self.metadata.get("state_shape")
        if want is not None and list(shape) != list(want):
            raise ValueError(
                f"transitions' {self.state_key!r} has trailing shape {list(shape)}, but the "
                f"dataset's metadata says state_shape={list(want)} (env_id="
                f"{self.metadata['env_id']!r}); nothing was stored"
            )
        if next_shape != shape:
            raise ValueError(
                f"transitions' state has trailing shape {list(shape)} but their next state "
                f"{list(next_shape)}; nothing was stored"
            )

    def tensors(self) -> TensorDictBase:
        """All stored transitions as one ``[N]`` TensorDict (a view of the storage)."""
        if len(self) == 0:
            raise ValueError("the dataset is empty")
        return self.buffer.storage[: len(self)]

    def trajectories(self) -> list[torch.Tensor]:
        """Row indices of each episode, in time order (for open-loop multi-step evaluation).

        Returns:
            One index tensor per episode (episodes cut by a collector batch are joined).

        Examples:
            >>> from torchrl_mbmf.data import collect_random_transitions
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 250, seed=0)
            >>> [len(idx) for idx in data.trajectories()]  # Pendulum episodes last 200 steps
            [200, 50]
        """
        ids = self.tensors().get(TRAJ_KEY)
        order = torch.sort(ids, stable=True).indices
        counts = torch.unique_consecutive(ids[order], return_counts=True)[1]
        return list(torch.split(order, counts.tolist()))

    def windows(self, length: int) -> torch.Tensor:
        """Row indices of every ``length`` consecutive transitions inside one episode.

        For multi-step model losses. Relies on the stored trajectory ids and
        ``("next", "done")`` flags and checks that each step's next state is the following
        step's state (see :func:`consecutive_windows`), so no window crosses a done, a
        truncation or a reset between two ``extend`` calls.

        Args:
            length: transitions per window (``>= 1``).

        Returns:
            A ``[W, length]`` long tensor of row indices of :meth:`tensors`, in time order.

        Examples:
            >>> from torchrl_mbmf.data import collect_random_transitions
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 250, seed=0)
            >>> data.windows(5).shape  # episodes of 200 and 50 steps: 196 + 46 windows
            torch.Size([242, 5])
        """
        td = self.tensors()
        return consecutive_windows(
            td.get(TRAJ_KEY),
            td.get(("next", "done")),
            td.get(self.state_key),
            td.get(("next", self.state_key)),
            length,
        )

    def _checksum(self, meta: Mapping[str, Any]) -> str:
        """SHA-256 of the metadata (all but ``sha256``), each tensor's dtype, shape and bytes."""
        digest = hashlib.sha256()
        record = {k: v for k, v in meta.items() if k != "sha256"}
        digest.update(json.dumps(record, sort_keys=True, separators=(",", ":")).encode())
        if len(self):
            data = self.tensors()
            for key in self.keys:
                tensor = data.get(key).contiguous()
                digest.update(f"{key!r}:{tensor.dtype}:{list(tensor.shape)};".encode())
                digest.update(tensor.reshape(-1).view(torch.uint8).numpy())
        return digest.hexdigest()

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Writes the dataset to the folder ``path`` atomically.

        Args:
            path: target folder.

        Keyword Args:
            overwrite: replace an existing dataset at ``path``. Defaults to ``False``.

        Returns:
            The path.

        Raises:
            FileExistsError: if ``path`` exists and ``overwrite`` is ``False``.

        Examples:
            >>> import tempfile
            >>> from pathlib import Path
            >>> from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
            >>> from torchrl_mbmf.envs import env_metadata, make_gym_state_env
            >>> env = make_gym_state_env("Pendulum-v1")
            >>> data = collect_random_transitions(env, 30, seed=0)
            >>> with tempfile.TemporaryDirectory() as d:
            ...     path = data.save(Path(d) / "random")
            ...     loaded = TransitionDataset.load(path, expect=env_metadata(env))
            >>> len(loaded), loaded.metadata["env_id"]
            (30, 'Pendulum-v1')
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        try:
            if len(self):
                self.tensors().select(*self.keys).memmap(tmp / _BUFFER_DIR)
            meta = self.record()
            (tmp / _META_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True))
            if path.exists():
                old = path.with_name(path.name + ".old")
                shutil.rmtree(old, ignore_errors=True)
                os.replace(path, old)
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    def record(self) -> dict[str, Any]:
        """The metadata :meth:`save` writes (``metadata.json``), with the checksum of the data.

        The provenance, the format, the counts, the trajectory-id state, the stored keys, the
        package version and a SHA-256 over all of them and every stored tensor:
        :meth:`from_record` rebuilds the dataset from this record and the tensors and checks
        them against it.

        Returns:
            A JSON-compatible dict (its ``"sha256"`` entry is the checksum).

        Examples:
            >>> from torchrl_mbmf.data import collect_random_transitions
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 30, seed=0)
            >>> record = data.record()
            >>> record["num_transitions"], len(record["sha256"])
            (30, 64)
        """
        meta = {
            **self.metadata,
            "format": _FORMAT,
            "num_transitions": len(self),
            "capacity": self.capacity,
            "next_traj": self._next_traj,
            "open_traj": None if self._open_traj is None else self._open_traj.tolist(),
            "keys": [list(k) if isinstance(k, tuple) else k for k in self.keys],
            "package_version": torchrl_mbmf.__version__,
        }
        # the checksum is taken over the metadata as it will be read back (JSON types)
        meta = json.loads(json.dumps(meta))
        meta["sha256"] = self._checksum(meta)
        return meta

    def dumps(self, path: str | os.PathLike) -> None:
        """Saves into ``path`` for ``torchrl.checkpoint`` (same files as :meth:`save`)."""
        self.save(path, overwrite=True)

    def loads(self, path: str | os.PathLike) -> None:
        """Restores in place from :meth:`dumps` output, checking env, reward and checksum."""
        other = type(self).load(
            path,
            expect={"env_id": self.metadata["env_id"], "reward": self.metadata["reward"]},
            capacity=self.capacity,
            scratch_dir=self._scratch,
        )
        self.buffer = other.buffer
        self._next_traj = other._next_traj
        self._open_traj = other._open_traj
        self.metadata = other.metadata

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        *,
        expect: Mapping[str, Any] | None = None,
        capacity: int | None = None,
        scratch_dir: str | os.PathLike | None = None,
    ) -> TransitionDataset:
        """Loads a dataset written by :meth:`save`, checking provenance and integrity.

        Args:
            path: the folder.

        Keyword Args:
            expect: metadata entries that must match (typically ``env_metadata(env)``: env id
                and reward parameters). Defaults to no check.
            capacity: capacity of the loaded dataset. Defaults to the saved one or the number of
                transitions, whichever is larger.
            scratch_dir: folder of the memory-mapped files. Defaults to a temporary folder.

        Returns:
            The dataset.

        Raises:
            FileNotFoundError: if there is no dataset at ``path``.
            DatasetMismatchError: if an ``expect`` entry differs (the message names it).
            CorruptDatasetError: if files are missing (the message names them), truncated,
                hold anything but the expected plain tensors, or fail the checksum (which
                covers the metadata too).
        """
        path = Path(path)
        meta_file = path / _META_FILE
        if not meta_file.exists():
            raise FileNotFoundError(f"no dataset at {path} (missing {_META_FILE})")
        try:
            meta = json.loads(meta_file.read_text())
        except json.JSONDecodeError as err:
            raise CorruptDatasetError(f"{meta_file} is not valid JSON: {err}") from err
        keys = _check_record(meta, str(meta_file), str(path))
        stored = None
        if int(meta["num_transitions"]):
            try:
                # JSON and raw tensor files only: nothing stored is ever unpickled
                stored = load_tensor_folder(path / _BUFFER_DIR, keys=keys)
            except UnsafeFolderError as err:
                raise CorruptDatasetError(f"cannot read the buffer of {path}: {err}") from err
            absent = [k for k in keys if k not in stored.keys(True, True)]
            if absent:
                raise CorruptDatasetError(
                    f"cannot read the buffer of {path}: "
                    f"{path / _BUFFER_DIR / 'meta.json'} lacks the entries {absent}"
                )
        return cls.from_record(
            meta,
            stored,
            expect=expect,
            capacity=capacity,
            scratch_dir=scratch_dir,
            source=str(path),
        )

    @classmethod
    def from_record(
        cls,
        record: Mapping[str, Any],
        stored: TensorDictBase | None,
        *,
        expect: Mapping[str, Any] | None = None,
        capacity: int | None = None,
        scratch_dir: str | os.PathLike | None = None,
        source: str = "the record",
    ) -> TransitionDataset:
        """A dataset from its :meth:`record` and its stored tensors, checked against the record.

        :meth:`load` reads both from a saved folder; a dataset rebuilt another way (for
        example by replaying its actions in the real env,
        :class:`~torchrl_mbmf.runs.dataset_replay.DatasetReplay`) is checked the same way:
        the tensors and the record must match the record's checksum.

        Args:
            record: the metadata of :meth:`record` (``metadata.json``).
            stored: the ``[N]`` transitions (:attr:`keys`; ``None`` when ``N`` is 0).

        Keyword Args:
            expect: metadata entries that must match. Defaults to no check.
            capacity: capacity of the dataset. Defaults to the recorded one or ``N``, whichever
                is larger.
            scratch_dir: folder of the memory-mapped files. Defaults to a temporary folder.
            source: what the error messages call the data. Defaults to ``"the record"``.

        Returns:
            The dataset.

        Raises:
            CorruptDatasetError: if the record is invalid, the tensors are not ``N``
                transitions, or either fails the checksum.
            DatasetMismatchError: if an ``expect`` entry differs.

        Examples:
            >>> from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 30, seed=0)
            >>> copy = TransitionDataset.from_record(data.record(), data.tensors().clone())
            >>> len(copy), copy.record()["sha256"] == data.record()["sha256"]
            (30, True)
        """
        meta = dict(record)
        keys = _check_record(meta, source, source)
        n = int(meta["num_transitions"])
        provenance = {k: v for k, v in meta.items() if k not in _RECORD_ONLY}
        data = cls(
            provenance,
            capacity=max(capacity or int(meta.get("capacity", 0)), n, 1),
            scratch_dir=scratch_dir,
            state_key=keys[0],
            action_key=keys[1],
            reward_key=keys[3][1],
        )
        data.metadata["package_version"] = meta.get("package_version")
        if n:
            if stored is None or stored.batch_size != (n,):
                found = None if stored is None else tuple(stored.batch_size)
                raise CorruptDatasetError(
                    f"{source} holds {found} transitions, its metadata says {n}"
                )
            absent = [k for k in data.keys if k not in stored.keys(True, True)]
            if absent:
                raise CorruptDatasetError(f"{source} lacks the entries {absent}")
            data.buffer.extend(stored.select(*data.keys))
        if data._checksum(meta) != meta["sha256"]:
            raise CorruptDatasetError(
                f"{source}: stored transitions or metadata do not match their checksum"
            )
        for key, value in (expect or {}).items():
            if meta.get(key) != value:
                raise DatasetMismatchError(
                    f"dataset at {source} was collected with {key}={meta.get(key)!r}, "
                    f"expected {key}={value!r}; collect new data for this configuration"
                )
        data._next_traj = int(meta["next_traj"])
        if meta["open_traj"] is not None:
            data._open_traj = torch.tensor(meta["open_traj"], dtype=torch.long)
        return data


#: Entries of a dataset's record that describe the stored data, not its provenance.
_RECORD_ONLY = (
    "format",
    "num_transitions",
    "capacity",
    "next_traj",
    "open_traj",
    "sha256",
    "keys",
    "package_version",
)


def _check_record(meta: Any, where: str, source: str) -> list[NestedKey]:
    """The stored keys of a dataset record; raises on a record of another format or shape."""
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        hint = (
            " (written by an older version whose checksum did not cover the metadata: "
            "collect or save it again)"
            if found == "torchrl_mbmf.transitions/1"
            else ""
        )
        raise CorruptDatasetError(f"{source} has format {found!r}, expected {_FORMAT!r}{hint}")
    required = ("num_transitions", "sha256", "keys", "next_traj", "open_traj")
    missing = [k for k in required if k not in meta]
    if missing:
        raise CorruptDatasetError(f"{where} lacks the entries {missing}")
    keys = [tuple(k) if isinstance(k, list) else k for k in meta["keys"]]
    if len(keys) != 6 or not isinstance(keys[3], tuple) or len(keys[3]) != 2:
        raise CorruptDatasetError(f"{where} has an invalid key list {meta['keys']!r}")
    return keys


def collect_random_transitions(
    env: EnvBase,
    num_steps: int,
    *,
    dataset: TransitionDataset | None = None,
    seed: int | None = None,
    progress: bool = False,
    chunk: int = 1000,
    state_key: NestedKey = STATE_KEY,
) -> TransitionDataset:
    """Runs a uniform-random policy in the real env and stores its transitions.

    With ``N`` batched copies each copy takes ``ceil(num_steps / N)`` steps, so the number of
    transitions is ``num_steps`` rounded up to a multiple of ``N``. Episodes that end are reset
    and continue. These are real env steps: count them in every budget.

    Args:
        env: the real env (batched or not).
        num_steps: number of real transitions to collect.

    Keyword Args:
        dataset: dataset to append to. Defaults to a new one with ``env_metadata(env)``.
        seed: seeds the env and the action sampling. Defaults to ``None``.
        progress: show a tqdm bar. Defaults to ``False``.
        chunk: steps per env between two appends to the dataset. Defaults to ``1000``.
        state_key: the env's state key, that of a new dataset. Defaults to
            :data:`~torchrl_mbmf.envs.STATE_KEY` (``"observation"`` for a plain ``GymEnv``).

    Returns:
        The dataset.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 300, seed=0)
        >>> len(data), data.metadata["seed"]
        (300, 0)
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if dataset is None:
        dataset = TransitionDataset({**env_metadata(env), "seed": seed}, state_key=state_key)
    n_envs = max(1, env.batch_size.numel())
    steps_per_env = -(-num_steps // n_envs)
    generator = torch.Generator()
    if seed is not None:
        env.set_seed(seed)
        generator.manual_seed(seed)
    spec = env.full_action_spec_unbatched[env.action_key]
    low, high = spec.space.low, spec.space.high
    shape = (*env.batch_size, *spec.shape)
    bar = tqdm(total=steps_per_env * n_envs, desc="random data", unit="step", disable=not progress)
    td = env.reset()
    done_steps = 0
    with torch.no_grad():
        while done_steps < steps_per_env:
            steps = min(chunk, steps_per_env - done_steps)
            frames = []
            for _ in range(steps):
                u = torch.rand(shape, generator=generator, dtype=low.dtype)
                td.set(env.action_key, low + (high - low) * u)
                td, td_next = env.step_and_maybe_reset(td)
                frames.append(td)
                td = td_next
            batch = torch.stack(frames, dim=env.batch_dims)
            dataset.extend(batch)
            done_steps += steps
            bar.update(steps * n_envs)
    bar.close()
    return dataset
