from torchrl_mbmf.trainers.config import METHODS, ConfigError, validate_train_config
from torchrl_mbmf.trainers.dynamics import FitHistory, fit_dynamics
from torchrl_mbmf.trainers.export import load_policy, save_policy
from torchrl_mbmf.trainers.loop import Trainer, seed_everything
from torchrl_mbmf.trainers.ppo import ppo_update
from torchrl_mbmf.trainers.sac import FusedSACUpdate, sac_update_step

__all__ = [
    "METHODS",
    "ConfigError",
    "FitHistory",
    "FusedSACUpdate",
    "Trainer",
    "fit_dynamics",
    "load_policy",
    "ppo_update",
    "sac_update_step",
    "save_policy",
    "seed_everything",
    "validate_train_config",
]
