from torchrl_mbmf.modules.actors import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel
from torchrl_mbmf.modules.planners import (
    EnsemblePolicyGuidedPlanner,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
)
from torchrl_mbmf.modules.termination import LearnedTermination

__all__ = [
    "DeltaDynamicsModel",
    "EnsembleDeltaDynamicsModel",
    "EnsemblePolicyGuidedPlanner",
    "LearnedTermination",
    "PolicyGuidedMPCPlanner",
    "RandomShootingMPCPlanner",
    "make_ppo_actor_critic",
    "make_sac_actor_critic",
]
