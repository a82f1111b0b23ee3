from torchrl_mbmf.trainers.config import METHODS, ConfigError, validate_train_config
from torchrl_mbmf.trainers.dynamics import FitHistory, fit_dynamics
from torchrl_mbmf.trainers.loop import Trainer, seed_everything

__all__ = [
    "METHODS",
    "ConfigError",
    "FitHistory",
    "Trainer",
    "fit_dynamics",
    "seed_everything",
    "validate_train_config",
]
