from torchrl_mbmf.envs.transforms.observation import StateToObservation
from torchrl_mbmf.envs.transforms.rewards import (
    REWARDS,
    DefaultReward,
    ForwardPenaltyReward,
    HeadPenReward,
    ShinPenReward,
    make_reward,
)

__all__ = [
    "REWARDS",
    "DefaultReward",
    "ForwardPenaltyReward",
    "HeadPenReward",
    "ShinPenReward",
    "StateToObservation",
    "make_reward",
]
