from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel

__all__ = ["DeltaDynamicsModel"]
