"""The real-transition dataset the world model is fitted on, saved with its provenance.

The dataset is split by concern: episode bookkeeping in :mod:`torchrl_mbmf.data.episodes`,
saving and loading in :mod:`torchrl_mbmf.data.dataset_files`; the names stay importable
from here.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from torchrl_mbmf.checks import check_number
from torchrl_mbmf.data.dataset_files import (
    FORMAT_WITHOUT_TERMINATED,
    TERMINATED_KEY,
    CorruptDatasetError,
    DatasetFiles,
    DatasetMismatchError,
)
from torchrl_mbmf.data.episodes import (
    TRAJ_KEY,
    TrajectoryIds,
    consecutive_windows,
    episode_ends,
)
from torchrl_mbmf.envs.factory import env_metadata
from torchrl_mbmf.envs.keys import STATE_KEY

__all__ = [
    "TRAJ_KEY",
    "CorruptDatasetError",
    "DatasetMismatchError",
    "TransitionDataset",
    "collect_random_transitions",
    "consecutive_windows",
    "episode_ends",
]


class TransitionDataset(DatasetFiles):
    """All real transitions ``(s, a, r, s')`` of a run, in a replay buffer stored on disk.

    The world model is fitted on every real transition collected so far (thesis section 5.1).
    Transitions are kept in a :class:`~torchrl.data.TensorDictReplayBuffer` over a
    :class:`~torchrl.data.LazyMemmapStorage` (memory-mapped files that grow with the data).
    Only what the world model needs is stored: ``state``, ``action``, ``("next", "state")``,
    ``("next", "reward")``, ``("next", "done")`` (any episode end: termination or time limit),
    ``("next", "terminated")`` (the real env's termination alone, for a learned termination
    head) and a trajectory id (:class:`~torchrl_mbmf.data.episodes.TrajectoryIds`).

    Transitions without ``terminated`` flags (a batch with ``done`` only, or a dataset saved
    before they were stored) make a dataset whose terminal transitions are unknown:
    :attr:`stores_terminated` is false and :meth:`terminated` refuses. Saving and loading
    (atomic, checksummed, never unpickling) come from the base class
    :class:`~torchrl_mbmf.data.dataset_files.DatasetFiles`. ``extend`` refuses transitions
    with a NaN or Inf in any stored field.

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
        >>> len(data), data.tensors()["state"].shape, data.terminated().any().item()
        (50, torch.Size([50, 3]), False)
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
        self.episodes = TrajectoryIds()
        # Whether ``terminated`` is stored: ``None`` until the first extend decides it.
        self._terminated: bool | None = None
        # Trailing shape and dtype of each stored field, fixed by the first ``extend``.
        self._layout: Layout | None = None

    def __len__(self) -> int:
        return len(self.buffer)

    @property
    def stores_terminated(self) -> bool:
        """Whether the real env's ``terminated`` flag of each transition is stored."""
        return self._terminated is not False

    @property
    def keys(self) -> list[NestedKey]:
        """The stored keys."""
        terminated = [TERMINATED_KEY] if self.stores_terminated else []
        return [
            self.state_key,
            self.action_key,
            ("next", self.state_key),
            ("next", self.reward_key),
            ("next", "done"),
            *terminated,
            TRAJ_KEY,
        ]

    def extend(self, batch: TensorDictBase) -> None:
        """Appends real transitions from ``env.rollout`` or a collector batch.

        Args:
            batch: ``[T]`` (one env) or ``[N, T]`` (``N`` batched envs) transitions. Episodes
                continue across calls: the last step of each env in one batch and the first of
                the next belong to the same episode unless it was done.

        Raises:
            ValueError: on a batch of another shape, an empty batch, missing keys (among them
                ``("next", "terminated")`` once the dataset stores it), a stored field of
                another size or dtype than the dataset holds (floating fields must be
                ``float32``: wrap a float64 env in ``DoubleToFloat``), a NaN or Inf in a stored
                field (nothing is stored), or when full.
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
        fields = self.keys[:4]
        missing = [k for k in fields if k not in batch.keys(True)]
        has_terminated = TERMINATED_KEY in batch.keys(True)
        if self._terminated and not has_terminated:
            missing.append(TERMINATED_KEY)
        if missing:
            raise ValueError(f"transitions lack keys {missing}; present: {batch.keys(True)}")
        self._check_layout(batch)
        # One vectorised check per field, before anything is stored.
        for name in fields:
            if not torch.isfinite(batch.get(name)).all():
                raise ValueError(f"transitions contain NaN or Inf in {name!r}; nothing was stored")
        done = episode_ends(batch)
        if self._terminated is None:
            self._terminated = has_terminated
        nxt = {
            self.state_key: batch.get(("next", self.state_key)),
            self.reward_key: batch.get(("next", self.reward_key)),
            "done": done.unsqueeze(-1),
        }
        if self._terminated:
            nxt["terminated"] = batch.get(TERMINATED_KEY).reshape(n_envs, steps, 1).bool()
        flat = TensorDict(
            {
                self.state_key: batch.get(self.state_key),
                self.action_key: batch.get(self.action_key),
                "next": nxt,
                TRAJ_KEY: self.episodes.assign(done),
            },
            batch_size=[n_envs, steps],
        ).reshape(-1)
        self.buffer.extend(flat.to(torch.device("cpu")))

    def _check_layout(self, batch: TensorDictBase) -> None:
        """Refuses fields whose size or dtype differ from the stored ones (or are not float32)."""
        layout = _batch_layout(batch, self.keys[:4])
        if self._layout is None and len(self) > 0:
            stored = self.tensors()
            self._layout = {
                k: (tuple(stored.get(k).shape[1:]), stored.get(k).dtype) for k in layout
            }
        if self._layout is None:
            _check_first_states(layout, self.state_key, self.metadata)
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

    def tensors(self) -> TensorDictBase:
        """All stored transitions as one ``[N]`` TensorDict (a view of the storage)."""
        if len(self) == 0:
            raise ValueError("the dataset is empty")
        return self.buffer.storage[: len(self)]

    def terminated(self) -> torch.Tensor:
        """The real env's ``terminated`` flag of every stored transition, bool ``[N]``.

        Raises:
            ValueError: the dataset is empty, or does not store the flags (saved in format
                ``torchrl_mbmf.transitions/2``, or filled with batches holding ``done`` only):
                ``done`` also marks time-limit truncations, so they are not guessed from it.
        """
        if not self.stores_terminated:
            raise ValueError(
                "this dataset does not store the real env's ('next', 'terminated') flags (it "
                f"was saved in format {FORMAT_WITHOUT_TERMINATED!r}, or filled with transitions "
                "holding 'done' only), so its terminal transitions are unknown ('done' also "
                "marks time-limit truncations); collect the data again with this version"
            )
        return self.tensors().get(TERMINATED_KEY).reshape(-1)

    def trajectories(self) -> list[torch.Tensor]:
        """Row indices of each episode, in time order (for open-loop multi-step evaluation).

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

        For multi-step model losses; no window crosses a done, a truncation or a reset between
        two ``extend`` calls (see :func:`~torchrl_mbmf.data.episodes.consecutive_windows`).

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


#: Trailing shape and dtype of each stored field.
Layout = dict[NestedKey, tuple[tuple[int, ...], torch.dtype]]


def _batch_layout(batch: TensorDictBase, fields: list[NestedKey]) -> Layout:
    """The trailing shape and dtype of ``fields`` in an ``[N, T]`` batch; floats must be float32."""
    layout = {}
    for name in fields:
        value = batch.get(name)
        layout[name] = (tuple(value.shape[2:]), value.dtype)
        if value.dtype.is_floating_point and value.dtype != torch.float32:
            raise ValueError(
                f"transitions' {name!r} is {value.dtype}, expected torch.float32 (the world "
                "model's dtype): wrap a float64 env in torchrl's DoubleToFloat transform"
            )
    return layout


def _check_first_states(layout: Layout, state_key: NestedKey, metadata: Mapping[str, Any]) -> None:
    """The first batch's state and next state agree, and match ``metadata["state_shape"]``."""
    shape, next_shape = layout[state_key][0], layout[("next", state_key)][0]
    want = metadata.get("state_shape")
    if want is not None and list(shape) != list(want):
        raise ValueError(
            f"transitions' {state_key!r} has trailing shape {list(shape)}, but the "
            f"dataset's metadata says state_shape={list(want)} (env_id="
            f"{metadata['env_id']!r}); nothing was stored"
        )
    if next_shape != shape:
        raise ValueError(
            f"transitions' state has trailing shape {list(shape)} but their next state "
            f"{list(next_shape)}; nothing was stored"
        )


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
        shape = list(env.observation_spec[state_key].shape[-1:])
        meta = {**env_metadata(env), "seed": seed, "state_shape": shape}
        dataset = TransitionDataset(meta, state_key=state_key)
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
