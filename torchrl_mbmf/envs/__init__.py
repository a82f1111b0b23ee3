from torchrl_mbmf.envs.ensemble_env import EnsembleLearnedDynamicsEnv
from torchrl_mbmf.envs.factory import action_bounds, env_metadata, make_env
from torchrl_mbmf.envs.gym_state import make_gym_state_env
from torchrl_mbmf.envs.half_cheetah import HALF_CHEETAH_ID, make_half_cheetah_env
from torchrl_mbmf.envs.keys import (
    ACTUATOR_TORQUES_KEY,
    FORWARD_VELOCITY_KEY,
    HEAD_HEIGHT_KEY,
    JOINT_ANGLES_KEY,
    JOINT_VELOCITIES_KEY,
    OBSERVATION_KEY,
    STATE_KEY,
)
from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv
from torchrl_mbmf.envs.physics_info import PhysicsInfo
from torchrl_mbmf.envs.tasks import TASK_LAYOUTS, TaskLayout, task_layout
from torchrl_mbmf.envs.terminations import (
    TerminationFn,
    termination_rule,
    termination_rule_of_env,
)
from torchrl_mbmf.envs.transforms import (
    REWARDS,
    DefaultReward,
    HeadPenReward,
    ShinPenReward,
    StateToObservation,
    make_reward,
)

__all__ = [
    "ACTUATOR_TORQUES_KEY",
    "FORWARD_VELOCITY_KEY",
    "HALF_CHEETAH_ID",
    "HEAD_HEIGHT_KEY",
    "JOINT_ANGLES_KEY",
    "JOINT_VELOCITIES_KEY",
    "OBSERVATION_KEY",
    "REWARDS",
    "STATE_KEY",
    "TASK_LAYOUTS",
    "DefaultReward",
    "EnsembleLearnedDynamicsEnv",
    "HeadPenReward",
    "LearnedDynamicsEnv",
    "PhysicsInfo",
    "ShinPenReward",
    "StateToObservation",
    "TaskLayout",
    "TerminationFn",
    "action_bounds",
    "env_metadata",
    "make_env",
    "make_gym_state_env",
    "make_half_cheetah_env",
    "make_reward",
    "task_layout",
    "termination_rule",
    "termination_rule_of_env",
]
