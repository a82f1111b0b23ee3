"""A lean single-process collector for the gymnasium envs this package builds."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    GymWrapper,
    RenameTransform,
    RewardSum,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import ExplorationType, RandomPolicy, set_exploration_type
from torchrl.modules import ProbabilisticActor

from torchrl_mbmf.envs.transforms import ForwardPenaltyReward, StateToObservation
from torchrl_mbmf.modules.planners.sampling import ActorSampler

#: Keys of the done signals, root and ``"next"``.
DONE_KEYS: tuple[str, ...] = ("done", "terminated", "truncated")


@dataclass
class CollectorTimes:
    """Seconds spent by a :class:`LeanCollector` since it was built.

    Attributes:
        env_s: real env steps and resets, and turning their outputs into tensors (the
            transforms' work).
        act_s: the policy (actor, planner or random actions).

    Examples:
        >>> from torchrl_mbmf.collectors import CollectorTimes
        >>> CollectorTimes(env_s=1.0, act_s=2.0).total_s
        3.0
    """

    env_s: float = 0.0
    act_s: float = 0.0

    @property
    def total_s(self) -> float:
        """``env_s + act_s``."""
        return self.env_s + self.act_s


@dataclass
class _Layout:
    """What the lean path needs to know of a supported env (read once from its transforms)."""

    gym_envs: list[Any]
    batch_shape: tuple[int, ...]
    info_keys: list[str]
    state_key: NestedKey
    observation: StateToObservation
    reward: ForwardPenaltyReward | None
    reward_dtype: torch.dtype
    double_keys: set[str] = field(default_factory=set)


def _layout(env: EnvBase) -> _Layout | None:
    """The structure of an env built by ``make_gym_state_env``, or ``None`` if it is another."""
    if not isinstance(env, TransformedEnv) or not isinstance(env.base_env, GymWrapper):
        return None
    transforms = list(env.transform) if isinstance(env.transform, Compose) else [env.transform]
    kinds = [type(t) for t in transforms]
    if len(kinds) < 4 or kinds[0] is not DoubleToFloat:
        return None
    i = 1
    state_key: NestedKey = "observation"
    if kinds[i] is RenameTransform:
        rename = transforms[i]
        if list(rename.in_keys) != ["observation"] or len(rename.out_keys) != 1:
            return None
        state_key = rename.out_keys[0]
        i += 1
    if kinds[i] is not StateToObservation or transforms[i].in_keys[0] != state_key:
        return None
    observation = transforms[i]
    i += 1
    reward = None
    if i < len(kinds) and isinstance(transforms[i], ForwardPenaltyReward):
        reward = transforms[i]
        i += 1
    if kinds[i:] != [StepCounter, RewardSum]:
        return None
    counter, rsum = transforms[i:]
    if counter.max_steps is not None or list(rsum.in_keys) != ["reward"]:
        return None
    base = env.base_env
    gym_env = base._env
    if base.batch_size.numel() != 1 or len(base.batch_size) > 1:
        return None  # vector envs keep the stock collector (their info layout differs)
    reader_keys = [
        k for reader in base.info_dict_reader for k in getattr(reader, "keys", None) or []
    ]
    obs_keys = set(base.observation_spec.keys()) - {"observation"}
    if set(reader_keys) != obs_keys:
        return None
    return _Layout(
        gym_envs=[gym_env],
        batch_shape=tuple(base.batch_size),
        info_keys=reader_keys,
        state_key=state_key,
        observation=observation,
        reward=reward,
        reward_dtype=base.full_reward_spec_unbatched["reward"].dtype,
        double_keys=set(transforms[0].in_keys),
    )


def _has_full_spec(policy: Any) -> bool:
    spec = getattr(policy, "spec", None)
    return spec is not None and all(v is not None for v in spec.values(True, True))


def _root_td(
    lay: _Layout, obs: np.ndarray, info: list[np.ndarray], count: int, running: np.float32
) -> TensorDict:
    """The root entries the stock env hands the policy at a step."""
    state = torch.from_numpy(obs).to(torch.float32)
    entries: dict[NestedKey, torch.Tensor] = {
        lay.state_key: state,
        lay.observation.out_keys[0]: lay.observation.observation(state),
        "step_count": torch.tensor([count]),
        "episode_reward": torch.tensor([running], dtype=torch.float32),
    }
    for key, value in zip(lay.info_keys, info, strict=True):
        entries[key] = torch.from_numpy(value).to(torch.float32)
    for key in DONE_KEYS:
        entries[key] = torch.zeros(1, dtype=torch.bool)
    return TensorDict(entries, batch_size=[])


@dataclass
class _Steps:
    """The NumPy arrays of one batch's steps, filled one step at a time."""

    root_obs: np.ndarray
    next_obs: np.ndarray
    root_info: list[np.ndarray]
    next_info: list[np.ndarray]
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    root_count: np.ndarray
    traj: np.ndarray

    @classmethod
    def empty(cls, n: int, obs: np.ndarray, info: list[np.ndarray]) -> _Steps:
        """Room for ``n`` steps of observations like ``obs`` and info entries like ``info``."""
        return cls(
            root_obs=np.empty((n, obs.shape[0])),
            next_obs=np.empty((n, obs.shape[0])),
            root_info=[np.empty((n, v.shape[0])) for v in info],
            next_info=[np.empty((n, v.shape[0])) for v in info],
            rewards=np.empty(n),
            terminated=np.zeros(n, dtype=bool),
            truncated=np.zeros(n, dtype=bool),
            root_count=np.empty(n, dtype=np.int64),
            traj=np.empty(n, dtype=np.int64),
        )

    def record_root(
        self, t: int, obs: np.ndarray, info: list[np.ndarray], count: int, traj: int
    ) -> None:
        """Step ``t``'s root entries."""
        self.root_obs[t] = obs
        for j, v in enumerate(info):
            self.root_info[j][t] = v
        self.root_count[t] = count
        self.traj[t] = traj

    def carry_roots(self, n: int, recorded: list[int]) -> None:
        """Fills the root observation and info of the first ``n`` steps but ``recorded``.

        Each is the previous step's ``"next"`` entry (the same array the loop would have
        copied).

        Args:
            n: the steps taken.
            recorded: the steps whose root entries :meth:`record_root` wrote (step 0 and
                every step after a reset).
        """
        carried = np.ones(n, dtype=bool)
        carried[recorded] = False
        rows = np.flatnonzero(carried)
        if rows.size:
            self.root_obs[rows] = self.next_obs[rows - 1]
            for root, nxt in zip(self.root_info, self.next_info, strict=True):
                root[rows] = nxt[rows - 1]

    def record_next(
        self,
        t: int,
        obs: np.ndarray,
        info: list[np.ndarray],
        reward: float,
        terminated: bool,
        truncated: bool,
    ) -> None:
        """Step ``t``'s ``"next"`` entries."""
        self.next_obs[t] = obs
        for j, v in enumerate(info):
            self.next_info[j][t] = v
        self.rewards[t] = reward
        self.terminated[t] = terminated
        self.truncated[t] = truncated

    def first(self, n: int) -> _Steps:
        """The first ``n`` steps (views)."""
        if n == self.rewards.shape[0]:
            return self
        return _Steps(
            root_obs=self.root_obs[:n],
            next_obs=self.next_obs[:n],
            root_info=[v[:n] for v in self.root_info],
            next_info=[v[:n] for v in self.next_info],
            rewards=self.rewards[:n],
            terminated=self.terminated[:n],
            truncated=self.truncated[:n],
            root_count=self.root_count[:n],
            traj=self.traj[:n],
        )


def _episode_returns(
    reward: torch.Tensor, root_count: np.ndarray, start_return: np.float32
) -> tuple[torch.Tensor, torch.Tensor]:
    """``RewardSum``'s running return before and after each step, accumulated as it does.

    In float32, one step at a time, restarting at 0 where ``root_count`` is 0.
    """
    n = reward.shape[0]
    r = reward[:, 0].numpy().astype(np.float32)
    ep_root = np.empty(n, dtype=np.float32)
    ep_next = np.empty(n, dtype=np.float32)
    running = np.float32(start_return)
    for t in range(n):
        if root_count[t] == 0:
            running = np.float32(0.0)
        ep_root[t] = running
        running = np.float32(running + r[t])
        ep_next[t] = running
    return (
        torch.from_numpy(ep_root).to(reward.dtype)[:, None],
        torch.from_numpy(ep_next).to(reward.dtype)[:, None],
    )


def _batch_of(
    lay: _Layout,
    steps: _Steps,
    action_key: NestedKey,
    start_return: np.float32,
    actions: list[torch.Tensor],
) -> TensorDict:
    """The batch the transform stack would give for the recorded steps (no policy outputs)."""
    n = steps.rewards.shape[0]
    f32 = torch.float32
    root_state = torch.from_numpy(steps.root_obs).to(f32)
    next_state = torch.from_numpy(steps.next_obs).to(f32)
    obs_key = lay.observation.out_keys[0]
    root: dict[NestedKey, Any] = {
        lay.state_key: root_state,
        obs_key: lay.observation.observation(root_state),
    }
    nxt: dict[NestedKey, Any] = {
        lay.state_key: next_state,
        obs_key: lay.observation.observation(next_state),
    }
    for key, r_val, n_val in zip(lay.info_keys, steps.root_info, steps.next_info, strict=True):
        root[key] = torch.from_numpy(r_val).to(f32)
        nxt[key] = torch.from_numpy(n_val).to(f32)
    root[action_key] = torch.stack(actions)
    term = torch.from_numpy(steps.terminated)[:, None]
    trunc = torch.from_numpy(steps.truncated)[:, None]
    nxt["terminated"] = term
    nxt["truncated"] = trunc
    nxt["done"] = term | trunc
    for key in DONE_KEYS:
        root[key] = torch.zeros(n, 1, dtype=torch.bool)
    count = torch.from_numpy(steps.root_count)[:, None]
    root["step_count"] = count
    nxt["step_count"] = count + 1
    root["collector"] = TensorDict({"traj_ids": torch.from_numpy(steps.traj)}, batch_size=[n])
    batch = TensorDict({**root, "next": TensorDict(nxt, batch_size=[n])}, batch_size=[n])
    if lay.reward is not None:
        reward = lay.reward.compute(batch, batch.get("next"))
    else:
        reward = torch.from_numpy(steps.rewards).to(lay.reward_dtype)[:, None]
    batch.set(("next", "reward"), reward)
    ep_root, ep_next = _episode_returns(reward, steps.root_count, start_return)
    batch.set("episode_reward", ep_root)
    batch.set(("next", "episode_reward"), ep_next)
    return batch


class LeanCollector:
    """Collects batches like :class:`torchrl.collectors.Collector`, at a fraction of its cost.

    A drop-in for ``Collector(env, policy, frames_per_batch=..., total_frames=-1)`` on the
    single envs of :func:`~torchrl_mbmf.envs.make_gym_state_env`: the same batches, key for
    key and value for value, with the transforms' work done once per batch instead of once
    per step. It resets the env when built (seed it before). :meth:`supports` tells whether
    an env has the layout it knows. How it matches the stock collector:
    ``docs/design/collectors.md``.

    Args:
        env: a real env from :func:`~torchrl_mbmf.envs.make_gym_state_env` (one copy,
            ``num_envs=1``).
        policy: a TensorDict module writing ``"action"`` (actor, planner or
            :class:`~torchrl.envs.utils.RandomPolicy`).

    Keyword Args:
        frames_per_batch: real steps per batch.
        total_frames: steps in total, ``-1`` for no end. Defaults to ``-1``.
        exploration_type: the exploration mode the policy runs under. Defaults to
            ``ExplorationType.RANDOM`` (the stock collector's default).
        policy_device: where the policy's parameters live: its inputs are moved there and
            its outputs back to the CPU. Defaults to ``None`` (the CPU).

    Raises:
        ValueError: if the env is not of a supported layout, or for a non-positive
            ``frames_per_batch``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.collectors import LeanCollector
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> actor, _ = make_ppo_actor_critic(env, hidden_sizes=(8,))
        >>> collector = LeanCollector(env, actor, frames_per_batch=16, total_frames=32)
        >>> [batch["next", "reward"].shape for batch in collector]
        [torch.Size([16, 1]), torch.Size([16, 1])]
    """

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase | Callable[[TensorDictBase], TensorDictBase],
        *,
        frames_per_batch: int,
        total_frames: int = -1,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        policy_device: torch.device | str | None = None,
    ) -> None:
        if isinstance(frames_per_batch, bool) or int(frames_per_batch) < 1:
            raise ValueError(f"frames_per_batch must be an integer >= 1, got {frames_per_batch!r}")
        if int(total_frames) != -1 and int(total_frames) < 1:
            raise ValueError(f"total_frames must be -1 or >= 1, got {total_frames!r}")
        layout = _layout(env)
        if layout is None:
            raise ValueError(
                f"LeanCollector supports single envs built by make_gym_state_env / make_env "
                f"(GymWrapper + DoubleToFloat, state/observation split, optional reward, "
                f"StepCounter, RewardSum); got {env!r}: use torchrl.collectors.Collector"
            )
        self.env = env
        self.policy = policy
        self.frames_per_batch = int(frames_per_batch)
        self.total_frames = int(total_frames)
        self.times = CollectorTimes()
        self._layout = layout
        self._action_key = env.action_key
        self._action_spec = env.full_action_spec_unbatched[self._action_key]
        self.exploration_type = exploration_type
        device = torch.device("cpu") if policy_device is None else torch.device(policy_device)
        self._device = None if device.type == "cpu" else device
        self._sampler: ActorSampler | None = None
        self._random = isinstance(policy, RandomPolicy)
        if isinstance(policy, ProbabilisticActor) and exploration_type == ExplorationType.RANDOM:
            sampler = ActorSampler(policy)
            keys = {*sampler.param_keys, self._action_key, "action_log_prob"}
            if sampler.is_fast and len(sampler.param_keys) == 2 and set(policy.out_keys) == keys:
                self._sampler = sampler
        self._frames = 0
        self._next_traj = 0
        self._traj = 0
        self._count = 0
        self._running = np.float32(0.0)
        # As the stock collector: reset now, and call a policy that declares no complete output
        # spec once on the reset entries (the stock collector does so to find its output keys;
        # a random policy or a planner draws random numbers there, and so must this one).
        self._current = self._reset()
        if self._sampler is None and not _has_full_spec(policy):
            with torch.no_grad():
                td = self._root_td(*self._current)
                policy(td if self._device is None else td.to(self._device))

    @staticmethod
    def supports(env: EnvBase) -> bool:
        """Whether ``env`` has the layout the lean path knows.

        Args:
            env: any TorchRL env.

        Examples:
            >>> from torchrl_mbmf.collectors import LeanCollector
            >>> from torchrl_mbmf.envs import make_env
            >>> LeanCollector.supports(make_env("HalfCheetah-v5"))
            True
        """
        return _layout(env) is not None

    # ------------------------------------------------------------------ helpers
    def _info_arrays(self, info: dict[str, Any]) -> list[np.ndarray]:
        return [np.asarray(info[k], dtype=np.float64).reshape(-1) for k in self._layout.info_keys]

    def _reset(self) -> tuple[np.ndarray, list[np.ndarray]]:
        obs, info = self._layout.gym_envs[0].reset()
        self._traj = self._next_traj
        self._next_traj += 1
        self._count = 0
        self._running = np.float32(0.0)
        return np.asarray(obs, dtype=np.float64), self._info_arrays(info)

    def _root_td(self, obs: np.ndarray, info: list[np.ndarray]) -> TensorDict:
        return _root_td(self._layout, obs, info, self._count, self._running)

    def _act(
        self, obs: np.ndarray, info: list[np.ndarray], draw: Callable[..., Any] | None
    ) -> tuple[torch.Tensor, Any]:
        """The policy's action at this step (on the CPU) and its outputs to keep, or ``None``.

        ``draw`` is the sampler's draw for this batch (the weights do not change within it).
        """
        device = self._device
        if draw is not None:
            policy_obs = self._layout.observation.observation(
                torch.from_numpy(obs).to(torch.float32)
            )
            if device is not None:
                policy_obs = policy_obs.to(device)
            action, params = draw(policy_obs)
            return (action if device is None else action.cpu()), params
        if self._random:
            return self.policy.action_spec.rand().get(self._action_key), None
        td = self._root_td(obs, info)
        out = self.policy(td if device is None else td.to(device))
        if device is not None:
            out = out.to("cpu")
        return out.get(self._action_key), out

    def _add_policy_outputs(self, batch: TensorDict, outputs: list[Any]) -> None:
        """Writes what the policy wrote besides the action (the sampler's for the whole batch)."""
        if self._sampler is not None:
            params = [torch.stack(p).cpu() for p in zip(*outputs, strict=True)]
            for key, value in zip(self._sampler.param_keys, params, strict=True):
                batch.set(key, value)
            action = batch.get(self._action_key)
            batch.set("action_log_prob", self._sampler.distribution(*params).log_prob(action))
        elif outputs:
            stacked = torch.stack(outputs)
            for key in stacked.keys(True, True):
                if key not in batch.keys(True, True):
                    batch.set(key, stacked.get(key))

    # --------------------------------------------------------------------- loop
    def __iter__(self) -> Iterator[TensorDictBase]:
        while self.total_frames == -1 or self._frames < self.total_frames:
            yield self._collect()

    def episode(self, max_steps: int = 100_000) -> TensorDictBase:
        """Steps until the first episode end (or ``max_steps``) and returns those steps.

        On a fresh collector this is ``env.rollout(max_steps, policy)``: the env is not reset
        after the episode's end, and the frame count is not advanced.

        Args:
            max_steps: the most steps. Defaults to ``100_000``.

        Examples:
            >>> from torchrl.envs.utils import ExplorationType
            >>> from torchrl_mbmf.collectors import LeanCollector
            >>> from torchrl_mbmf.envs import make_env
            >>> from torchrl_mbmf.modules import make_ppo_actor_critic
            >>> env = make_env("Pendulum-v1", seed=0)
            >>> actor, _ = make_ppo_actor_critic(env, hidden_sizes=(8,))
            >>> collector = LeanCollector(env, actor, frames_per_batch=1,
            ...                           exploration_type=ExplorationType.DETERMINISTIC)
            >>> collector.episode().shape
            torch.Size([200])
        """
        return self._collect(max_steps, stop_at_done=True)

    def _collect(self, n: int | None = None, stop_at_done: bool = False) -> TensorDictBase:
        gym_env = self._layout.gym_envs[0]
        count_frames = n is None
        n = self.frames_per_batch if n is None else int(n)
        clock = time.perf_counter
        t0 = clock()
        if self._current is None:
            self._current = self._reset()
        obs, info = self._current
        steps = _Steps.empty(n, obs, info)
        start_return = self._running
        actions: list[torch.Tensor] = []
        outputs: list[Any] = []
        act_s = 0.0
        ended = False
        # step 0 and the steps after a reset record their root entries; the others' are the
        # previous step's "next" entries, copied once for the batch (carry_roots)
        recorded: list[int] = []
        fresh = True
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            # nothing changes the policy's weights while this loop runs
            draw = None if self._sampler is None else self._sampler.sampler_for_fixed_weights()
            for t in range(n):
                if fresh:
                    steps.record_root(t, obs, info, self._count, self._traj)
                    recorded.append(t)
                    fresh = False
                else:
                    steps.root_count[t] = self._count
                    steps.traj[t] = self._traj
                a0 = clock()
                action, out = self._act(obs, info, draw)
                if out is not None:
                    outputs.append(out)
                act_s += clock() - a0
                actions.append(action)
                obs, reward, term, trunc, step_info = gym_env.step(action.numpy())
                obs = np.asarray(obs, dtype=np.float64)
                info = self._info_arrays(step_info)
                steps.record_next(t, obs, info, reward, term, trunc)
                self._count += 1
                if term or trunc:
                    if stop_at_done:  # as env.rollout: no reset after the episode's end
                        n, ended = t + 1, True
                        break
                    obs, info = self._reset()
                    fresh = True
        self._current = None if ended else (obs, info)
        steps.carry_roots(n, recorded)
        steps = steps.first(n)
        batch = _batch_of(self._layout, steps, self._action_key, start_return, actions)
        self._add_policy_outputs(batch, outputs)
        if not (steps.terminated[-1] or steps.truncated[-1]):
            # the episode in progress carries its running return into the next batch
            self._running = np.float32(batch.get(("next", "episode_reward"))[-1, 0].item())
        if count_frames:
            self._frames += n
        self.times.act_s += act_s
        self.times.env_s += clock() - t0 - act_s
        return batch

    def shutdown(self) -> None:
        """Nothing to release (kept for the stock collector's interface)."""
