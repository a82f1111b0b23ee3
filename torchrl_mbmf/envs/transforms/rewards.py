"""The thesis' reward functions (eq. 16, 18 and table 4) as TorchRL transforms.

Each reward is ``forward_weight * x_velocity - penalty``; they differ in the penalty. They read
the physics written by :class:`~torchrl_mbmf.envs.physics_info.PhysicsInfo` (through the env's
info reader) from the ``"next"`` tensordict, so they work on a live env (``TransformedEnv``,
``Compose``, batched envs) and on stored transitions sampled from a replay buffer alike.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec
from torchrl.envs.transforms import Transform

from torchrl_mbmf.envs.keys import FORWARD_VELOCITY_KEY, HEAD_HEIGHT_KEY, JOINT_ANGLES_KEY


def _finite(value: object, name: str, *, minimum: float | None = None) -> float:
    """``value`` as a float, refusing non-numbers, NaN/Inf and values below ``minimum``."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not number or not math.isfinite(value) or (minimum is not None and value < minimum):
        expected = "a finite number" if minimum is None else f"a number >= {minimum:g}"
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return float(value)


class ForwardPenaltyReward(Transform):
    """Base of the thesis rewards: ``reward = forward_weight * velocity - penalty(td, next)``.

    Subclasses define :meth:`penalty` and :meth:`parameters_dict`; :meth:`compute` evaluates the
    reward of any batch of transitions (a live env step, a whole collected batch or replay
    samples alike), which is what the env's step and :class:`~torchrl_mbmf.collectors.LeanCollector`
    both call.

    Keyword Args:
        forward_weight: weight of the forward velocity.
        velocity_key: key (under ``"next"``) of the forward velocity.
        reward_key: reward key written under ``"next"``.
        extra_next_keys: other ``"next"`` keys the penalty reads.
        root_keys: root keys the penalty reads (for example the action).

    Examples:
        >>> from torchrl_mbmf.envs.transforms import DefaultReward, ForwardPenaltyReward
        >>> isinstance(DefaultReward(), ForwardPenaltyReward)
        True
    """

    #: Name under which the reward is registered (``make_half_cheetah_env(reward=...)``).
    name: str = ""

    def __init__(
        self,
        *,
        forward_weight: float,
        velocity_key: NestedKey,
        reward_key: NestedKey,
        extra_next_keys: Sequence[NestedKey] = (),
        root_keys: Sequence[NestedKey] = (),
    ) -> None:
        super().__init__(in_keys=[velocity_key, *extra_next_keys], out_keys=[reward_key])
        self.forward_weight = _finite(forward_weight, "forward_weight")
        self.velocity_key = velocity_key
        self.reward_key = reward_key
        self._root_keys = tuple(root_keys)

    def penalty(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> torch.Tensor:
        """Penalty ``[*batch, 1]`` of the transitions; subclasses define it."""
        raise NotImplementedError

    def parameters_dict(self) -> dict[str, object]:
        """The reward's name and constructor parameters, recorded with datasets and runs."""
        raise NotImplementedError

    def compute(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> torch.Tensor:
        """Reward ``[*batch, 1]`` from the root tensordict (action) and the next one (physics)."""
        velocity = _physics_column(next_tensordict, self.velocity_key)
        penalty = self.penalty(tensordict, next_tensordict)
        return (self.forward_weight * velocity - penalty).to(torch.float32)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.reward_key, self.compute(tensordict, next_tensordict))
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return tensordict_reset

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Recomputes ``("next", reward_key)`` of stored transitions (replay-buffer samples)."""
        if "next" not in tensordict:
            raise KeyError(
                f"{type(self).__name__} needs transitions with a 'next' entry holding "
                f"{self.velocity_key!r}; got keys {sorted(map(str, tensordict.keys()))}"
            )
        next_td = tensordict.get("next")
        next_td.set(self.reward_key, self.compute(tensordict, next_td))
        return tensordict

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Writing to a replay buffer stores data as it is; rewards are only recomputed on read.
        return tensordict

    def transform_reward_spec(self, reward_spec: TensorSpec) -> TensorSpec:
        """The reward spec, unchanged (the reward keeps its shape and dtype)."""
        return reward_spec

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v}" for k, v in self.parameters_dict().items() if k != "name")
        return f"{type(self).__name__}({params})"


def _physics_column(next_tensordict: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """The scalar physics quantity ``key`` as ``[*batch, 1]``; refuses other shapes and NaN/Inf."""
    value = next_tensordict.get(key)
    batch = tuple(next_tensordict.batch_size)
    if tuple(value.shape) == batch:
        value = value.unsqueeze(-1)
    if tuple(value.shape) != (*batch, 1):
        raise ValueError(
            f"{key!r} must hold one number per transition, shape {[*batch, 1]} or {list(batch)}, "
            f"got shape {list(value.shape)}"
        )
    if not torch.isfinite(value).all():
        raise ValueError(f"{key!r} holds NaN or Inf: {value.flatten().tolist()[:8]}")
    return value


class DefaultReward(ForwardPenaltyReward):
    """HalfCheetah's own reward: ``x_velocity - ctrl_cost_weight * sum(action**2)`` (thesis eq. 16).

    Reproduces gymnasium's ``HalfCheetah-v5`` reward; provided as a transform so that all three
    thesis rewards are built, logged and recorded the same way.

    Keyword Args:
        forward_weight: weight of the forward velocity. Defaults to ``1.0``.
        ctrl_cost_weight: weight of the squared-action penalty. Defaults to ``0.1``.
        action_key: key of the action that was applied. Defaults to ``"action"``.
        velocity_key: key (under ``"next"``) of the forward velocity. Defaults to
            :data:`~torchrl_mbmf.envs.FORWARD_VELOCITY_KEY`.
        reward_key: reward key written under ``"next"``. Defaults to ``"reward"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.envs.transforms import DefaultReward
        >>> td = TensorDict(action=torch.ones(6), next=TensorDict(forward_velocity=torch.ones(1)))
        >>> DefaultReward()(td)["next", "reward"]
        tensor([0.4000])
    """

    name = "default"

    def __init__(
        self,
        *,
        forward_weight: float = 1.0,
        ctrl_cost_weight: float = 0.1,
        action_key: NestedKey = "action",
        velocity_key: NestedKey = FORWARD_VELOCITY_KEY,
        reward_key: NestedKey = "reward",
    ) -> None:
        super().__init__(
            forward_weight=forward_weight,
            velocity_key=velocity_key,
            reward_key=reward_key,
            root_keys=(action_key,),
        )
        self.ctrl_cost_weight = _finite(ctrl_cost_weight, "ctrl_cost_weight", minimum=0)
        self.action_key = action_key

    def penalty(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> torch.Tensor:
        """``ctrl_cost_weight * sum(action**2)`` over the last dim."""
        action = tensordict.get(self.action_key)
        return self.ctrl_cost_weight * action.double().pow(2).sum(-1, keepdim=True)

    def parameters_dict(self) -> dict[str, object]:
        """See base class."""
        return {
            "name": self.name,
            "forward_weight": self.forward_weight,
            "ctrl_cost_weight": self.ctrl_cost_weight,
        }


class HeadPenReward(ForwardPenaltyReward):
    """Thesis HeadPen: ``x_velocity - penalty`` when the head has dropped below a threshold.

    The penalty applies when the head's height, relative to its height in the initial pose, is
    below ``threshold`` after the step (the thesis' ``head_y < -0.2``; the cheetah tips over past
    it). There is no action cost.

    Keyword Args:
        threshold: relative head height (m) below which the penalty applies. Defaults to ``-0.2``.
        penalty_weight: the penalty. Defaults to ``0.1``.
        forward_weight: weight of the forward velocity. Defaults to ``1.0``.
        head_height_key: key (under ``"next"``) of the relative head height. Defaults to
            :data:`~torchrl_mbmf.envs.HEAD_HEIGHT_KEY`.
        velocity_key: key (under ``"next"``) of the forward velocity. Defaults to
            :data:`~torchrl_mbmf.envs.FORWARD_VELOCITY_KEY`.
        reward_key: reward key written under ``"next"``. Defaults to ``"reward"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.envs.transforms import HeadPenReward
        >>> nxt = TensorDict(forward_velocity=torch.tensor([[1.0], [1.0]]),
        ...                  head_height=torch.tensor([[-0.3], [0.0]]), batch_size=[2])
        >>> HeadPenReward()(TensorDict(next=nxt, batch_size=[2]))["next", "reward"]
        tensor([[0.9000],
                [1.0000]])
    """

    name = "head_pen"

    def __init__(
        self,
        *,
        threshold: float = -0.2,
        penalty_weight: float = 0.1,
        forward_weight: float = 1.0,
        head_height_key: NestedKey = HEAD_HEIGHT_KEY,
        velocity_key: NestedKey = FORWARD_VELOCITY_KEY,
        reward_key: NestedKey = "reward",
    ) -> None:
        super().__init__(
            forward_weight=forward_weight,
            velocity_key=velocity_key,
            reward_key=reward_key,
            extra_next_keys=(head_height_key,),
        )
        self.threshold = _finite(threshold, "threshold")
        self.penalty_weight = _finite(penalty_weight, "penalty_weight", minimum=0)
        self.head_height_key = head_height_key

    def penalty(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> torch.Tensor:
        """``penalty_weight`` where the next head height is below ``threshold``, else 0."""
        head = _physics_column(next_tensordict, self.head_height_key)
        return self.penalty_weight * (head < self.threshold).to(torch.float64)

    def parameters_dict(self) -> dict[str, object]:
        """See base class."""
        return {
            "name": self.name,
            "forward_weight": self.forward_weight,
            "threshold": self.threshold,
            "penalty_weight": self.penalty_weight,
        }


class ShinPenReward(ForwardPenaltyReward):
    """Thesis ShinPen: ``x_velocity`` minus a penalty per front-leg joint bent too far back.

    ``penalty = sum_j penalty_weights[j] * [angle_j > thresholds[j]]`` over the front thigh,
    shin and foot (thesis table 4: 0.1 each, thresholds 0.2, 0 and 0 rad), read from the joint
    angles after the step. There is no action cost.

    Keyword Args:
        thresholds: angle thresholds (rad) of the penalised joints. Defaults to ``(0.2, 0.0, 0.0)``.
        penalty_weights: penalty of each joint. Defaults to ``(0.1, 0.1, 0.1)``.
        joint_indices: positions of the penalised joints in ``joint_angles``. Defaults to
            ``(3, 4, 5)`` (fthigh, fshin, ffoot).
        forward_weight: weight of the forward velocity. Defaults to ``1.0``.
        joint_angles_key: key (under ``"next"``) of the joint angles. Defaults to
            :data:`~torchrl_mbmf.envs.JOINT_ANGLES_KEY`.
        velocity_key: key (under ``"next"``) of the forward velocity. Defaults to
            :data:`~torchrl_mbmf.envs.FORWARD_VELOCITY_KEY`.
        reward_key: reward key written under ``"next"``. Defaults to ``"reward"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.envs.transforms import ShinPenReward
        >>> nxt = TensorDict(forward_velocity=torch.ones(1),
        ...                  joint_angles=torch.tensor([0., 0., 0., 0.3, 0.1, -0.1]))
        >>> ShinPenReward()(TensorDict(next=nxt))["next", "reward"]
        tensor([0.8000])
    """

    name = "shin_pen"

    def __init__(
        self,
        *,
        thresholds: Sequence[float] = (0.2, 0.0, 0.0),
        penalty_weights: Sequence[float] = (0.1, 0.1, 0.1),
        joint_indices: Sequence[int] = (3, 4, 5),
        forward_weight: float = 1.0,
        joint_angles_key: NestedKey = JOINT_ANGLES_KEY,
        velocity_key: NestedKey = FORWARD_VELOCITY_KEY,
        reward_key: NestedKey = "reward",
    ) -> None:
        if not len(thresholds) == len(penalty_weights) == len(joint_indices):
            raise ValueError(
                "thresholds, penalty_weights and joint_indices must have the same length, got "
                f"{len(thresholds)}, {len(penalty_weights)} and {len(joint_indices)}"
            )
        super().__init__(
            forward_weight=forward_weight,
            velocity_key=velocity_key,
            reward_key=reward_key,
            extra_next_keys=(joint_angles_key,),
        )
        self.thresholds = tuple(_finite(t, f"thresholds[{i}]") for i, t in enumerate(thresholds))
        self.penalty_weights = tuple(
            _finite(w, f"penalty_weights[{i}]", minimum=0) for i, w in enumerate(penalty_weights)
        )
        for i, j in enumerate(joint_indices):
            if isinstance(j, bool) or not isinstance(j, int) or j < 0:
                raise ValueError(f"joint_indices[{i}] must be an integer >= 0, got {j!r}")
        self.joint_indices = tuple(int(i) for i in joint_indices)
        self.joint_angles_key = joint_angles_key
        self.register_buffer(
            "_thresholds", torch.tensor(self.thresholds, dtype=torch.float64), persistent=False
        )
        self.register_buffer(
            "_weights", torch.tensor(self.penalty_weights, dtype=torch.float64), persistent=False
        )

    def penalty(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> torch.Tensor:
        """Weighted count of penalised joints beyond their thresholds."""
        angles = next_tensordict.get(self.joint_angles_key)
        if angles.shape[-1] <= max(self.joint_indices):
            raise ValueError(
                f"{self.joint_angles_key!r} has {angles.shape[-1]} joints, joint_indices="
                f"{self.joint_indices} needs at least {max(self.joint_indices) + 1}"
            )
        front = angles[..., list(self.joint_indices)].double()
        if not torch.isfinite(front).all():
            raise ValueError(
                f"{self.joint_angles_key!r} holds NaN or Inf at joints {self.joint_indices}"
            )
        thresholds = self._thresholds.to(front.device)
        weights = self._weights.to(front.device)
        return ((front > thresholds).double() * weights).sum(-1, keepdim=True)

    def parameters_dict(self) -> dict[str, object]:
        """See base class."""
        return {
            "name": self.name,
            "forward_weight": self.forward_weight,
            "thresholds": list(self.thresholds),
            "penalty_weights": list(self.penalty_weights),
            "joint_indices": list(self.joint_indices),
        }


#: Reward name -> transform class, as accepted by ``make_half_cheetah_env(reward=...)``.
REWARDS: dict[str, type[ForwardPenaltyReward]] = {
    cls.name: cls for cls in (DefaultReward, HeadPenReward, ShinPenReward)
}


def make_reward(name: str, **kwargs: object) -> ForwardPenaltyReward:
    """Builds a reward transform from its name.

    Args:
        name: one of ``"default"``, ``"head_pen"``, ``"shin_pen"``.
        **kwargs: constructor arguments of that reward (thresholds, weights, keys).

    Raises:
        ValueError: if ``name`` is not a known reward.

    Examples:
        >>> from torchrl_mbmf.envs.transforms import make_reward
        >>> make_reward("head_pen", threshold=-0.25)
        HeadPenReward(forward_weight=1.0, threshold=-0.25, penalty_weight=0.1)
    """
    try:
        cls = REWARDS[name]
    except KeyError:
        raise ValueError(f"unknown reward {name!r}; valid rewards are {sorted(REWARDS)}") from None
    return cls(**kwargs)  # type: ignore[arg-type]
