"""HalfCheetah-v5 with the thesis state, observation and reward variants."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torchrl.envs import TransformedEnv

from torchrl_mbmf.envs.gym_state import make_gym_state_env
from torchrl_mbmf.envs.keys import (
    ACTUATOR_TORQUES_KEY,
    FORWARD_VELOCITY_KEY,
    HEAD_HEIGHT_KEY,
    JOINT_ANGLES_KEY,
    JOINT_VELOCITIES_KEY,
    OBSERVATION_KEY,
    STATE_KEY,
)
from torchrl_mbmf.envs.physics_info import HALF_CHEETAH_JOINTS, PhysicsInfo
from torchrl_mbmf.envs.tasks import TASK_LAYOUTS
from torchrl_mbmf.envs.transforms.rewards import REWARDS, make_reward

#: Gymnasium id of the environment the thesis' experiments run on (v3 in the thesis; v5 here).
HALF_CHEETAH_ID = "HalfCheetah-v5"


def make_half_cheetah_env(
    reward: str = "default",
    *,
    num_envs: int = 1,
    seed: int | None = None,
    device: str | torch.device = "cpu",
    reward_kwargs: Mapping[str, Any] | None = None,
    state_key: str = STATE_KEY,
    observation_key: str = OBSERVATION_KEY,
    **gym_kwargs: Any,
) -> TransformedEnv:
    """Builds HalfCheetah-v5 as the thesis uses it, as a TorchRL env.

    Keys (float32): ``state`` is the 18-dim thesis state (torso x position first, then the 17
    standard observations); ``observation`` is the 17-dim policy view without x. The physics
    the rewards and the gait analysis need (``forward_velocity``, ``head_height``,
    ``joint_angles``, ``joint_velocities``, ``actuator_torques``) is read from MuJoCo through the
    env's info reader. ``reward`` selects the thesis reward transform that writes ``reward``;
    ``episode_reward`` (its running return) and ``step_count`` are tracked.

    Args:
        reward: ``"default"``, ``"head_pen"`` or ``"shin_pen"``. Defaults to ``"default"``.

    Keyword Args:
        num_envs: copies stepped together in one vector env (batch ``[num_envs]``).
            Defaults to ``1``.
        seed: env seed (copy ``i`` gets ``seed + i``). Defaults to ``None``.
        device: device of the returned tensors. Defaults to ``"cpu"``.
        reward_kwargs: constructor arguments of the reward transform (thresholds, weights).
            Defaults to the thesis values.
        state_key: key of the 18-dim state. Defaults to :data:`STATE_KEY`.
        observation_key: key of the 17-dim observation. Defaults to :data:`OBSERVATION_KEY`.
        **gym_kwargs: passed to ``gym.make`` (for example ``max_episode_steps``).

    Raises:
        ValueError: for an unknown ``reward`` (the message lists the valid names), or
            ``exclude_current_positions_from_observation=True`` (the state starts with x).

    Examples:
        >>> from torchrl_mbmf.envs import make_half_cheetah_env
        >>> env = make_half_cheetah_env("shin_pen", seed=0)
        >>> td = env.rollout(3)
        >>> td["next", "state"].shape, td["next", "observation"].shape
        (torch.Size([3, 18]), torch.Size([3, 17]))
    """
    if reward not in REWARDS:
        raise ValueError(f"unknown reward {reward!r}; valid rewards are {sorted(REWARDS)}")
    reward_transform = make_reward(reward, **dict(reward_kwargs or {}))
    n_joints = len(HALF_CHEETAH_JOINTS)
    info_specs = {
        FORWARD_VELOCITY_KEY: (1,),
        HEAD_HEIGHT_KEY: (1,),
        JOINT_ANGLES_KEY: (n_joints,),
        JOINT_VELOCITIES_KEY: (n_joints,),
        ACTUATOR_TORQUES_KEY: (n_joints,),
    }
    # the thesis state: the x position first (Gymnasium's positions kept), hidden from the policy
    layout = TASK_LAYOUTS[HALF_CHEETAH_ID]
    return make_gym_state_env(
        HALF_CHEETAH_ID,
        num_envs=num_envs,
        seed=seed,
        device=device,
        drop_state_dims=layout.hidden_dims,
        info_specs=info_specs,
        wrap=PhysicsInfo,
        transforms=[reward_transform],
        state_key=state_key,
        observation_key=observation_key,
        **layout.make_kwargs(gym_kwargs),
    )
