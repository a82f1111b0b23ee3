"""Fitting the world model: the one fitter, its data split, history, ensembles and snapshots.

Also MBPO's branched model rollouts (:class:`BranchedRollouts`), which learn from it.

Used alone by the analysis and the benchmarks; nothing here imports the training loop.
"""

from torchrl_mbmf.world_model.branched_rollouts import (
    BranchedRollouts,
    RandomMemberEnv,
    check_mbpo_config,
    policy_as_planner,
)
from torchrl_mbmf.world_model.ensemble_fit import (
    DisagreementCalibration,
    calibrate_disagreement_threshold,
    fit_ensemble,
)
from torchrl_mbmf.world_model.fit import fit_dynamics, fit_dynamics_kwargs, fit_world_model
from torchrl_mbmf.world_model.fit_data import transition_tensors
from torchrl_mbmf.world_model.fit_history import (
    EnsembleFitHistory,
    FitHistory,
    dynamics_optimizer,
)
from torchrl_mbmf.world_model.snapshots import (
    fit_snapshots,
    heldout_open_loop_errors,
    load_fit_snapshot,
    save_fit_snapshot,
)
from torchrl_mbmf.world_model.termination_fit import fit_termination

__all__ = [
    "BranchedRollouts",
    "DisagreementCalibration",
    "EnsembleFitHistory",
    "FitHistory",
    "RandomMemberEnv",
    "calibrate_disagreement_threshold",
    "check_mbpo_config",
    "dynamics_optimizer",
    "fit_dynamics",
    "fit_dynamics_kwargs",
    "fit_ensemble",
    "fit_snapshots",
    "fit_termination",
    "fit_world_model",
    "heldout_open_loop_errors",
    "load_fit_snapshot",
    "policy_as_planner",
    "save_fit_snapshot",
    "transition_tensors",
]
