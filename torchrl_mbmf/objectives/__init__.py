from torchrl_mbmf.objectives.dynamics_loss import DynamicsLoss, MultiStepDynamicsLoss

__all__ = ["DynamicsLoss", "MultiStepDynamicsLoss"]
