"""One entry point that builds any supported real env from config values."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torchrl.data import Bounded
from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv

from torchrl_mbmf.envs.gym_state import make_gym_state_env
from torchrl_mbmf.envs.half_cheetah import HALF_CHEETAH_ID, make_half_cheetah_env
from torchrl_mbmf.envs.keys import OBSERVATION_KEY, STATE_KEY
from torchrl_mbmf.envs.tasks import task_layout
from torchrl_mbmf.envs.transforms.rewards import REWARDS, ForwardPenaltyReward

#: Reward name meaning "the env's own reward" for envs other than HalfCheetah.
NATIVE_REWARD = "default"


def make_env(
    env_id: str,
    *,
    reward: str = "default",
    reward_kwargs: Mapping[str, Any] | None = None,
    num_envs: int = 1,
    seed: int | None = None,
    device: str | torch.device = "cpu",
    state_key: str = STATE_KEY,
    observation_key: str = OBSERVATION_KEY,
    **gym_kwargs: Any,
) -> TransformedEnv:
    """Builds a real env for any Gymnasium id, with the thesis rewards on HalfCheetah.

    ``HalfCheetah-v5`` goes through :func:`make_half_cheetah_env` (any of its rewards). Any
    other id goes through :func:`make_gym_state_env` with the task's own reward (healthy reward
    and terminations included), which only ``reward="default"`` selects. A task of
    :data:`~torchrl_mbmf.envs.tasks.TASK_LAYOUTS` gets its layout: the model ``state`` holds the
    root positions first (``exclude_current_positions_from_observation=False`` for the MuJoCo
    locomotion tasks) and the policy ``observation`` leaves them out; any other id keeps its
    observation as the state and shows all of it to the policy. Episodes end as Gymnasium ends
    them: ``terminated`` when the task says so, ``truncated`` at its time limit.

    Args:
        env_id: Gymnasium id.

    Keyword Args:
        reward: reward name. Defaults to ``"default"``.
        reward_kwargs: reward constructor arguments (HalfCheetah only). Defaults to none.
        num_envs: copies stepped together. Defaults to ``1``.
        seed: env seed. Defaults to ``None``.
        device: device of the tensors. Defaults to ``"cpu"``.
        state_key: key of the model state. Defaults to :data:`~torchrl_mbmf.envs.STATE_KEY`.
        observation_key: key of the policy observation. Defaults to
            :data:`~torchrl_mbmf.envs.OBSERVATION_KEY`.
        **gym_kwargs: passed to ``gym.make``.

    Raises:
        ValueError: for an unknown reward, a thesis reward asked of another task, or a
            ``gym_kwargs`` entry that would take the positions out of a known task's state.

    Examples:
        >>> from torchrl_mbmf.envs import make_env
        >>> make_env("Pendulum-v1", seed=0).rollout(2)["next", "state"].shape
        torch.Size([2, 3])
        >>> td = make_env("Hopper-v5", seed=0).rollout(2)
        >>> td["next", "state"].shape, td["next", "observation"].shape
        (torch.Size([2, 12]), torch.Size([2, 11]))
    """
    if reward not in REWARDS:
        raise ValueError(f"unknown reward {reward!r}; valid rewards are {sorted(REWARDS)}")
    if env_id == HALF_CHEETAH_ID:
        return make_half_cheetah_env(
            reward,
            num_envs=num_envs,
            seed=seed,
            device=device,
            reward_kwargs=reward_kwargs,
            state_key=state_key,
            observation_key=observation_key,
            **gym_kwargs,
        )
    if reward != NATIVE_REWARD or reward_kwargs:
        raise ValueError(
            f"reward={reward!r} with kwargs {dict(reward_kwargs or {})} is defined for "
            f"{HALF_CHEETAH_ID} only (the thesis' reward variants); {env_id!r} takes "
            f"reward={NATIVE_REWARD!r} (its own reward) with no kwargs"
        )
    layout = task_layout(env_id)
    if layout is not None:  # the layout's own message, without make_gym_state_env's hint
        gym_kwargs = layout.make_kwargs(gym_kwargs)
    return make_gym_state_env(
        env_id,
        num_envs=num_envs,
        seed=seed,
        device=device,
        state_key=state_key,
        observation_key=observation_key,
        **gym_kwargs,
    )


def flat_transforms(transform: Transform) -> list[Transform]:
    """The transforms of ``transform``, nested :class:`~torchrl.envs.Compose` unpacked.

    A :class:`~torchrl.envs.TransformedEnv` built with one transform holds it as it is, not in
    a ``Compose``; this lists both the same way.

    Args:
        transform: a transform or a ``Compose`` of them (an env's ``.transform``).

    Examples:
        >>> from torchrl.envs import Compose, DoubleToFloat, StepCounter
        >>> from torchrl_mbmf.envs.factory import flat_transforms
        >>> nested = Compose(Compose(StepCounter()), DoubleToFloat())
        >>> [type(t).__name__ for t in flat_transforms(nested)]
        ['StepCounter', 'DoubleToFloat']
    """
    if isinstance(transform, Compose):
        return [t for inner in transform for t in flat_transforms(inner)]
    return [transform]


def env_metadata(env: EnvBase) -> dict[str, Any]:
    """The Gymnasium id and the reward (name and parameters) of a real env.

    Recorded with datasets and checkpoints so that data collected under one env or reward is
    never reused for another. Any env built on one Gymnasium env works: the builders of this
    package, a plain :class:`~torchrl.envs.GymEnv` or :class:`~torchrl.envs.GymWrapper`, with
    any transforms (single or composed, nested or not) around it.

    Args:
        env: a real env.

    Returns:
        ``{"env_id": str, "reward": {"name": str, ...parameters}}``; envs without a thesis
        reward transform report ``{"name": "default"}`` (their own reward).

    Raises:
        ValueError: ``env`` does not wrap a Gymnasium env with a registered id.

    Examples:
        >>> from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv
        >>> from torchrl_mbmf.envs import env_metadata, make_env
        >>> env_metadata(make_env("HalfCheetah-v5", reward="head_pen"))["reward"]["threshold"]
        -0.2
        >>> env_metadata(TransformedEnv(GymEnv("Pendulum-v1"), DoubleToFloat()))["env_id"]
        'Pendulum-v1'
    """
    reward: dict[str, Any] = {"name": NATIVE_REWARD}
    node: EnvBase = env
    while isinstance(node, TransformedEnv):
        for t in flat_transforms(node.transform):
            if isinstance(t, ForwardPenaltyReward):
                reward = dict(t.parameters_dict())
        node = node.base_env
    gym_env = getattr(node, "_env", None)
    if gym_env is not None and hasattr(gym_env, "envs"):
        gym_env = gym_env.envs[0]
    spec = getattr(gym_env, "spec", None)
    if spec is None:
        raise ValueError(
            f"cannot find the Gymnasium id of {type(node).__name__}: env_metadata expects an "
            "env built on one Gymnasium env (GymEnv, GymWrapper or this package's builders), "
            "with any transforms around it"
        )
    return {"env_id": spec.id, "reward": reward}


def action_bounds(env: EnvBase) -> tuple[float, float]:
    """The action range of an env, as the world model's ``action_low`` and ``action_high``.

    Args:
        env: an env with a bounded continuous action spec whose dims share one range (every
            MuJoCo task of Gymnasium, ``Pendulum-v1``).

    Returns:
        ``(low, high)`` of the action spec (``(-2.0, 2.0)`` for Pendulum).

    Raises:
        ValueError: the action spec is not bounded, or its dims have different ranges.

    Examples:
        >>> from torchrl_mbmf.envs import action_bounds, make_env
        >>> action_bounds(make_env("Pendulum-v1")), action_bounds(make_env("InvertedPendulum-v5"))
        ((-2.0, 2.0), (-3.0, 3.0))
    """
    spec = env.full_action_spec_unbatched[env.action_key]
    if not isinstance(spec, Bounded):
        raise ValueError(
            f"the action spec of {env.action_key!r} is {type(spec).__name__}; the world model "
            "needs a Bounded action spec (its low and high become the model's action range)"
        )
    low, high = spec.space.low.unique(), spec.space.high.unique()
    if low.numel() != 1 or high.numel() != 1:
        raise ValueError(
            f"the action spec of {env.action_key!r} has per-dimension bounds low={spec.space.low} "
            f"high={spec.space.high}; the world model takes one range for every action dim"
        )
    return float(low), float(high)
