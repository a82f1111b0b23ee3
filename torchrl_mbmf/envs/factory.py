"""One entry point that builds any supported real env from config values."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_mbmf.envs.gym_state import make_gym_state_env
from torchrl_mbmf.envs.half_cheetah import HALF_CHEETAH_ID, make_half_cheetah_env
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
    **gym_kwargs: Any,
) -> TransformedEnv:
    """Builds a real env by gymnasium id, with the thesis rewards on HalfCheetah.

    ``HalfCheetah-v5`` goes through :func:`make_half_cheetah_env` (any of its rewards); any other
    id (for example ``Pendulum-v1``) through :func:`make_gym_state_env` with its own reward, which
    only ``reward="default"`` selects.

    Args:
        env_id: gymnasium id.

    Keyword Args:
        reward: reward name. Defaults to ``"default"``.
        reward_kwargs: reward constructor arguments (HalfCheetah only). Defaults to none.
        num_envs: copies stepped together. Defaults to ``1``.
        seed: env seed. Defaults to ``None``.
        device: device of the tensors. Defaults to ``"cpu"``.
        **gym_kwargs: passed to ``gym.make``.

    Raises:
        ValueError: for an unknown reward, or a thesis reward asked of another env.

    Examples:
        >>> from torchrl_mbmf.envs import make_env
        >>> make_env("Pendulum-v1", seed=0).rollout(2)["next", "state"].shape
        torch.Size([2, 3])
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
            **gym_kwargs,
        )
    if reward != NATIVE_REWARD or reward_kwargs:
        raise ValueError(
            f"reward={reward!r} with kwargs {dict(reward_kwargs or {})} is defined for "
            f"{HALF_CHEETAH_ID} only; {env_id!r} supports reward={NATIVE_REWARD!r} (its own "
            "reward) with no kwargs"
        )
    return make_gym_state_env(env_id, num_envs=num_envs, seed=seed, device=device, **gym_kwargs)


def env_metadata(env: EnvBase) -> dict[str, Any]:
    """The gymnasium id and the reward (name and parameters) of an env built by this package.

    Recorded with datasets and checkpoints so that data collected under one env or reward is
    never reused for another.

    Args:
        env: a real env from :func:`make_env`, :func:`make_half_cheetah_env` or
            :func:`make_gym_state_env`.

    Returns:
        ``{"env_id": str, "reward": {"name": str, ...parameters}}``; envs without a thesis
        reward transform report ``{"name": "default"}`` (their own reward).

    Examples:
        >>> from torchrl_mbmf.envs import env_metadata, make_env
        >>> env_metadata(make_env("HalfCheetah-v5", reward="head_pen"))["reward"]["threshold"]
        -0.2
    """
    reward: dict[str, Any] = {"name": NATIVE_REWARD}
    node: EnvBase = env
    while isinstance(node, TransformedEnv):
        for t in node.transform:
            if isinstance(t, ForwardPenaltyReward):
                reward = dict(t.parameters_dict())
        node = node.base_env
    gym_env = getattr(node, "_env", None)
    if gym_env is not None and hasattr(gym_env, "envs"):
        gym_env = gym_env.envs[0]
    spec = getattr(gym_env, "spec", None)
    if spec is None:
        raise ValueError(f"cannot find the gymnasium id of {type(node).__name__}")
    return {"env_id": spec.id, "reward": reward}
