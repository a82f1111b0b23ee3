from torchrl_mbmf.objectives.dynamics_loss import DynamicsLoss, MultiStepDynamicsLoss
from torchrl_mbmf.objectives.fused_ppo import FusedPPOUpdate, ppo_update
from torchrl_mbmf.objectives.fused_sac import FusedSACUpdate, sac_update_step

__all__ = [
    "DynamicsLoss",
    "FusedPPOUpdate",
    "FusedSACUpdate",
    "MultiStepDynamicsLoss",
    "ppo_update",
    "sac_update_step",
]
