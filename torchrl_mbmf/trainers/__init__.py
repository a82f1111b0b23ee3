from torchrl_mbmf.trainers.agents import PPOAgent, SACAgent
from torchrl_mbmf.trainers.config import METHODS, ConfigError, validate_train_config
from torchrl_mbmf.trainers.dynamics import FitHistory, fit_dynamics, fit_dynamics_kwargs
from torchrl_mbmf.trainers.ensemble_fit import (
    DisagreementCalibration,
    EnsembleFitHistory,
    calibrate_disagreement_threshold,
    fit_ensemble,
)
from torchrl_mbmf.trainers.export import load_policy, save_policy
from torchrl_mbmf.trainers.fit_data import transition_tensors
from torchrl_mbmf.trainers.guards import TrainingDivergedError
from torchrl_mbmf.trainers.loop import Trainer, seed_everything
from torchrl_mbmf.trainers.planning import WorldModelPart
from torchrl_mbmf.trainers.ppo import FusedPPOUpdate, ppo_update
from torchrl_mbmf.trainers.resume import RunCheckpoint
from torchrl_mbmf.trainers.sac import FusedSACUpdate, sac_update_step
from torchrl_mbmf.trainers.schedule import Actor, Phase, PhaseSchedule
from torchrl_mbmf.trainers.world_model_fit import fit_world_model

__all__ = [
    "METHODS",
    "Actor",
    "ConfigError",
    "DisagreementCalibration",
    "EnsembleFitHistory",
    "FitHistory",
    "FusedPPOUpdate",
    "FusedSACUpdate",
    "PPOAgent",
    "Phase",
    "PhaseSchedule",
    "RunCheckpoint",
    "SACAgent",
    "Trainer",
    "TrainingDivergedError",
    "WorldModelPart",
    "calibrate_disagreement_threshold",
    "fit_dynamics",
    "fit_dynamics_kwargs",
    "fit_ensemble",
    "fit_world_model",
    "load_policy",
    "ppo_update",
    "sac_update_step",
    "save_policy",
    "seed_everything",
    "transition_tensors",
    "validate_train_config",
]
