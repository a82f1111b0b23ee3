from torchrl_mbmf.modules.planners.common import (
    Plan,
    ShootingPlanner,
    discounted_return,
    expand_candidates,
    gather_candidate,
    select_best,
)
from torchrl_mbmf.modules.planners.ensemble_guided import EnsemblePlan, EnsemblePolicyGuidedPlanner
from torchrl_mbmf.modules.planners.fast_model import CachedModelStep, ModelLayers
from torchrl_mbmf.modules.planners.policy_guided import PolicyGuidedMPCPlanner
from torchrl_mbmf.modules.planners.policy_rollout import PolicyRollout
from torchrl_mbmf.modules.planners.random_shooting import RandomShootingMPCPlanner
from torchrl_mbmf.modules.planners.sampling import ActorSampler
from torchrl_mbmf.modules.planners.values import MinQValue

__all__ = [
    "ActorSampler",
    "CachedModelStep",
    "EnsemblePlan",
    "EnsemblePolicyGuidedPlanner",
    "MinQValue",
    "ModelLayers",
    "Plan",
    "PolicyGuidedMPCPlanner",
    "PolicyRollout",
    "RandomShootingMPCPlanner",
    "ShootingPlanner",
    "discounted_return",
    "expand_candidates",
    "gather_candidate",
    "select_best",
]
