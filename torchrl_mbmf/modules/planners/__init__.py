from torchrl_mbmf.modules.planners.common import Plan, ShootingPlanner, select_best
from torchrl_mbmf.modules.planners.policy_guided import PolicyGuidedMPCPlanner
from torchrl_mbmf.modules.planners.random_shooting import RandomShootingMPCPlanner
from torchrl_mbmf.modules.planners.sampling import ActorSampler

__all__ = [
    "ActorSampler",
    "Plan",
    "PolicyGuidedMPCPlanner",
    "RandomShootingMPCPlanner",
    "ShootingPlanner",
    "select_best",
]
