from torchrl_mbmf.trainers.dynamics import FitHistory, fit_dynamics

__all__ = ["FitHistory", "fit_dynamics"]
