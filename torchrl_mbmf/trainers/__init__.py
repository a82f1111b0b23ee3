"""The training loop and its parts: schedule, hooks, agents, build, config, the world-model part.

Names that lived here before the package was split keep working for one release: importing
them (``torchrl_mbmf.trainers.fit_dynamics``, ``torchrl_mbmf.trainers.dataset_replay``) warns
with a :class:`DeprecationWarning` that names their new home (:data:`MOVED_MODULES`,
:data:`MOVED_NAMES`, through :mod:`torchrl_mbmf.moved`).
"""

from __future__ import annotations

import sys

from torchrl_mbmf.checks import TrainingDivergedError
from torchrl_mbmf.moved import MovedModule, moved_attribute
from torchrl_mbmf.trainers.agents import PPOAgent, SACAgent
from torchrl_mbmf.trainers.config import METHODS, ConfigError, validate_train_config
from torchrl_mbmf.trainers.loop import Trainer, seed_everything
from torchrl_mbmf.trainers.planning import WorldModelPart
from torchrl_mbmf.trainers.schedule import Actor, Phase, PhaseSchedule
from torchrl_mbmf.trainers.settings import TrainConfig

__all__ = [
    "METHODS",
    "MOVED_MODULES",
    "MOVED_NAMES",
    "Actor",
    "ConfigError",
    "PPOAgent",
    "Phase",
    "PhaseSchedule",
    "SACAgent",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "WorldModelPart",
    "seed_everything",
    "validate_train_config",
]

#: Former modules of this package and the modules that now hold their names (searched in
#: order). Kept for one release.
MOVED_MODULES: dict[str, tuple[str, ...]] = {
    "world_model_fit": ("torchrl_mbmf.world_model.fit",),
    "dynamics": ("torchrl_mbmf.world_model.fit",),
    "fit_data": ("torchrl_mbmf.world_model.fit_data",),
    "fit_history": ("torchrl_mbmf.world_model.fit_history",),
    "fit_records": ("torchrl_mbmf.world_model.snapshots",),
    "ensemble_fit": ("torchrl_mbmf.world_model.ensemble_fit",),
    "checkpointing": ("torchrl_mbmf.runs.storage",),
    "resume": (
        "torchrl_mbmf.runs.checkpoint",
        "torchrl_mbmf.runs.resume",
        "torchrl_mbmf.runs.layout",
    ),
    "resume_logs": ("torchrl_mbmf.runs.logs",),
    "dataset_replay": ("torchrl_mbmf.runs.dataset_replay",),
    "export": ("torchrl_mbmf.runs.export",),
    "guards": ("torchrl_mbmf.checks",),
    "ppo": ("torchrl_mbmf.objectives.fused_ppo",),
    "sac": (
        "torchrl_mbmf.objectives.fused_sac",
        "torchrl_mbmf.data.replay",
        "torchrl_mbmf.device",
    ),
    "device": ("torchrl_mbmf.device",),
    "signals": ("torchrl_mbmf.runs.signals",),
}

#: Former names of this package and the modules that now hold them. Kept for one release.
MOVED_NAMES: dict[str, str] = {
    "DisagreementCalibration": "torchrl_mbmf.world_model.ensemble_fit",
    "EnsembleFitHistory": "torchrl_mbmf.world_model.fit_history",
    "FitHistory": "torchrl_mbmf.world_model.fit_history",
    "FusedPPOUpdate": "torchrl_mbmf.objectives.fused_ppo",
    "FusedSACUpdate": "torchrl_mbmf.objectives.fused_sac",
    "RunCheckpoint": "torchrl_mbmf.runs.checkpoint",
    "calibrate_disagreement_threshold": "torchrl_mbmf.world_model.ensemble_fit",
    "fit_dynamics": "torchrl_mbmf.world_model.fit",
    "fit_dynamics_kwargs": "torchrl_mbmf.world_model.fit",
    "fit_ensemble": "torchrl_mbmf.world_model.ensemble_fit",
    "fit_world_model": "torchrl_mbmf.world_model.fit",
    "load_policy": "torchrl_mbmf.runs.export",
    "ppo_update": "torchrl_mbmf.objectives.fused_ppo",
    "sac_update_step": "torchrl_mbmf.objectives.fused_sac",
    "save_policy": "torchrl_mbmf.runs.export",
    "transition_tensors": "torchrl_mbmf.world_model.fit_data",
}


for _name, _targets in MOVED_MODULES.items():
    sys.modules.setdefault(f"{__name__}.{_name}", MovedModule(f"{__name__}.{_name}", _targets))


def __getattr__(name: str) -> object:
    if name in MOVED_MODULES:
        return sys.modules[f"{__name__}.{name}"]
    return moved_attribute(__name__, name, MOVED_NAMES)
