from torchrl_mbmf.modules.planners.common import ShootingPlanner
from torchrl_mbmf.modules.planners.ensemble_guided import EnsemblePlan, EnsemblePolicyGuidedPlanner
from torchrl_mbmf.modules.planners.fast_model import CachedModelStep, ModelLayers
from torchrl_mbmf.modules.planners.policy_guided import PolicyGuidedMPCPlanner
from torchrl_mbmf.modules.planners.policy_rollout import PolicyRollout
from torchrl_mbmf.modules.planners.random_shooting import RandomShootingMPCPlanner
from torchrl_mbmf.modules.planners.rollout import (
    ImaginedRollout,
    MemberTransition,
    SequenceMixture,
    TrustedHorizon,
    imagine,
    learned_model,
    model_transition,
)
from torchrl_mbmf.modules.planners.sampling import ActorSampler
from torchrl_mbmf.modules.planners.stages import (
    Plan,
    counted_steps,
    discounted_return,
    expand_candidates,
    gather_candidate,
    select_best,
    terminated_return,
    truncated_return,
)
from torchrl_mbmf.modules.planners.values import MinQValue

__all__ = [
    "ActorSampler",
    "CachedModelStep",
    "EnsemblePlan",
    "EnsemblePolicyGuidedPlanner",
    "ImaginedRollout",
    "MemberTransition",
    "MinQValue",
    "ModelLayers",
    "Plan",
    "PolicyGuidedMPCPlanner",
    "PolicyRollout",
    "RandomShootingMPCPlanner",
    "SequenceMixture",
    "ShootingPlanner",
    "TrustedHorizon",
    "counted_steps",
    "discounted_return",
    "expand_candidates",
    "gather_candidate",
    "imagine",
    "learned_model",
    "model_transition",
    "select_best",
    "terminated_return",
    "truncated_return",
]
