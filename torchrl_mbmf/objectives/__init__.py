from torchrl_mbmf.objectives.dynamics_loss import DynamicsLoss

__all__ = ["DynamicsLoss"]
