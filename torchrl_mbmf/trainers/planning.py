"""The model-based part of a run: world model, its data, its refits and the MPC planner.

Built from the ``world_model`` and ``planner`` config groups with the components' own
constructors (which validate their arguments); the loop sees :class:`WorldModelPart`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.envs.ensemble_env import EnsembleLearnedDynamicsEnv
from torchrl_mbmf.envs.factory import env_metadata
from torchrl_mbmf.envs.keys import STATE_KEY
from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel
from torchrl_mbmf.modules.planners import (
    EnsemblePolicyGuidedPlanner,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
)
from torchrl_mbmf.trainers.dynamics import fit_dynamics, fit_dynamics_kwargs
from torchrl_mbmf.trainers.ensemble_fit import calibrate_disagreement_threshold, fit_ensemble
from torchrl_mbmf.trainers.fit_records import heldout_open_loop_errors, save_fit_snapshot

__all__ = ["WorldModelPart", "make_planner", "make_world_model"]

#: Refinement settings a ``planner`` group passes to the policy-guided planners.
REFINEMENT_KEYS: dict[str, type] = {
    "iterations": int,
    "num_elites": int,
    "policy_fraction": float,
    "temperature": float,
    "min_std": float,
}


def make_world_model(
    world_model: Mapping[str, Any], env: EnvBase
) -> DeltaDynamicsModel | EnsembleDeltaDynamicsModel:
    """The world model a ``world_model`` config group describes, sized from ``env``.

    Args:
        world_model: the ``world_model`` group (``hidden_sizes``, ``ensemble_size``,
            ``probabilistic``).
        env: the real env (state and action sizes).

    Examples:
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.trainers.planning import make_world_model
        >>> model = make_world_model({"hidden_sizes": [8]}, make_env("Pendulum-v1"))
        >>> type(model).__name__
        'DeltaDynamicsModel'
    """
    state_dim = env.full_observation_spec_unbatched[STATE_KEY].shape[-1]
    action_dim = env.full_action_spec_unbatched[env.action_key].shape[-1]
    hidden = tuple(world_model["hidden_sizes"])
    members = int(world_model.get("ensemble_size", 1))
    if members > 1:
        return EnsembleDeltaDynamicsModel(
            state_dim,
            action_dim,
            num_members=members,
            hidden_sizes=hidden,
            probabilistic=bool(world_model.get("probabilistic", False)),
        )
    return DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=hidden)


def make_planner(
    planner: Mapping[str, Any],
    model_env: EnvBase,
    actor: TensorDictModuleBase,
    *,
    guided: bool,
    value_module: TensorDictModuleBase | None = None,
) -> TensorDictModuleBase:
    """The MPC planner a ``planner`` config group describes.

    Args:
        planner: the ``planner`` group.
        model_env: the learned-dynamics env the planner imagines in (an ensemble env picks
            the ensemble planner).
        actor: the policy (the prior of the guided planners; the random-shooting planner
            only records its log-probabilities).

    Keyword Args:
        guided: the policy-guided planner (``ppo_mpc``, ``sac_mpc``) or random shooting (``mpc``).
        value_module: the terminal value (used when ``planner.terminal_value`` is true).

    Examples:
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, make_ppo_actor_critic
        >>> from torchrl_mbmf.trainers.planning import make_planner
        >>> env = make_env("Pendulum-v1")
        >>> actor, _ = make_ppo_actor_critic(env, hidden_sizes=(8,))
        >>> model_env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), env)
        >>> cfg = {"num_candidates": 4, "horizon": 2, "discount": 1.0}
        >>> type(make_planner(cfg, model_env, actor, guided=True)).__name__
        'PolicyGuidedMPCPlanner'
    """
    kwargs: dict[str, Any] = {
        "num_candidates": int(planner["num_candidates"]),
        "horizon": int(planner["horizon"]),
        "discount": float(planner["discount"]),
    }
    if planner.get("terminal_value", False):
        kwargs["value_module"] = value_module
    if not guided:
        return RandomShootingMPCPlanner(model_env, actor=actor, **kwargs)
    if planner.get("refinement"):
        kwargs["refinement"] = str(planner["refinement"])
        kwargs.update({key: cast(planner[key]) for key, cast in REFINEMENT_KEYS.items()})
    if isinstance(model_env, EnsembleLearnedDynamicsEnv):
        # Candidate i rolls in member i mod K; with world_model.adaptive_horizon the
        # threshold is calibrated at every refit (None until the first one).
        return EnsemblePolicyGuidedPlanner(model_env, actor, **kwargs)
    return PolicyGuidedMPCPlanner(model_env, actor, **kwargs)


class WorldModelPart:
    """World model, optimiser, real-transition dataset and planner of a model-based run.

    Args:
        cfg: the training config (reads ``world_model``, ``planner``, ``method``, ``seed``).
        env: the real env.
        agent: the agent whose actor guides the planner (and whose value ends its rollouts).
        device: device of the model and planner.

    Examples:
        >>> from torchrl_mbmf.trainers.planning import WorldModelPart
        >>> WorldModelPart.CALIBRATED
        'disagreement_threshold'
    """

    #: The progress entry that keeps the calibrated disagreement threshold across a resume.
    CALIBRATED = "disagreement_threshold"
    #: The progress entry holding the dataset's length at the last fit (rows after it are
    #: held-out data of the policy's own episodes for the model that fit produced).
    LAST_FIT = "last_fit_transitions"

    def __init__(self, cfg: Any, env: EnvBase, agent: Any, device: torch.device) -> None:
        self.cfg = cfg.world_model
        self.model = make_world_model(self.cfg, env).to(device)
        if self.model.ensemble_size > 1:
            model_env = EnsembleLearnedDynamicsEnv(self.model, env)
        else:
            model_env = LearnedDynamicsEnv(self.model, env)
        self.optim = torch.optim.Adam(self.model.parameters(), lr=float(self.cfg.lr))
        self.seed = int(cfg.seed)
        self.dataset = TransitionDataset({**env_metadata(env), "seed": self.seed})
        value = agent.terminal_value() if cfg.planner.get("terminal_value", False) else None
        self.planner = make_planner(
            cfg.planner,
            model_env,
            agent.actor,
            guided=cfg.method != "mpc",
            value_module=value,
        )

    def checkpoint_components(self) -> dict[str, Any]:
        """The tensor state a checkpoint holds (the dataset apart)."""
        return {"world_model": self.model, "model_optim": self.optim}

    def restore(self, progress: Mapping[str, Any]) -> None:
        """Sets the planner's calibrated threshold from a resumed progress record."""
        threshold = progress.get(self.CALIBRATED)
        if threshold is not None:
            self.planner.disagreement_threshold = float(threshold)

    @staticmethod
    def planner_scalars(batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """The planner's statistics in a collected batch (none for a batch without them)."""
        keys = batch.keys(True)
        if ("planner", "best_return") not in keys:
            return {}
        out = {
            "planner/best_return": batch["planner", "best_return"].mean(),
            "planner/mean_return": batch["planner", "mean_return"].mean(),
        }
        for name in ("effective_horizon", "disagreement"):
            if ("planner", name) in keys:
                out[f"planner/{name}"] = batch["planner", name].float().mean()
        return out

    def refit(
        self, seed: int, progress: dict[str, Any], run_dir: Path | None = None
    ) -> dict[str, float]:
        """Refits the model on every real transition so far; returns the scalars to log.

        With ``world_model.adaptive_horizon`` the ensemble's disagreement threshold is
        calibrated on the fit's held-out split (which no member trained on) and recorded in
        ``progress``. Before the fit, the single model being replaced is scored open loop on the
        transitions collected since its own fit (``model/heldout_*``, with its own generator:
        no training number changes); after it, with ``world_model.save_fits`` (the default)
        and a ``run_dir``, the new weights are kept under ``run_dir/world_models/``.

        Args:
            seed: seed of the fit's split and minibatch order.
            progress: the progress record (receives the calibrated threshold and the dataset's
                length at this fit).
            run_dir: the run folder for the fit snapshots (``None``: none kept).
        """
        wm = self.cfg
        since = progress.get(self.LAST_FIT)
        heldout: dict[str, float] = {}
        if since is not None and isinstance(self.model, DeltaDynamicsModel):
            heldout = heldout_open_loop_errors(
                self.model, self.dataset, since=int(since), seed=self.seed
            )
        start = time.perf_counter()
        if self.model.ensemble_size > 1:
            history = fit_ensemble(
                self.model,
                self.dataset,
                batch_size=int(wm.batch_size),
                max_epochs=int(wm.max_epochs),
                val_fraction=float(wm.val_fraction),
                patience=int(wm.patience),
                seed=seed,
                optimizer=self.optim,
            )
        else:
            history = fit_dynamics(
                self.model, self.dataset, **fit_dynamics_kwargs(wm), seed=seed, optimizer=self.optim
            )
        scalars = {
            "model/train_loss": history.train_loss[-1],
            "model/val_loss": history.best_val_loss,
            "model/epochs": history.epochs,
            "model/transitions": len(self.dataset),
        }
        if getattr(history, "multi_step", 1) > 1:
            scalars["model/train_multi_step_loss"] = history.train_multi_step_loss[-1]
            scalars["model/val_multi_step_loss"] = history.best_val_multi_step_loss
        if self.model.ensemble_size > 1 and wm.get("adaptive_horizon"):
            threshold = self._calibrate(history.val_indices)
            progress[self.CALIBRATED] = threshold
            self.planner.disagreement_threshold = threshold
            scalars["model/disagreement_threshold"] = threshold
        progress[self.LAST_FIT] = len(self.dataset)
        if run_dir is not None and wm.get("save_fits", True):
            save_fit_snapshot(self.model, run_dir, len(self.dataset))
        scalars["time/model_fit_s"] = time.perf_counter() - start
        return {**heldout, **scalars}

    def _calibrate(self, idx: torch.Tensor) -> float:
        data = self.dataset
        td = data.tensors()[idx]
        calibration = calibrate_disagreement_threshold(
            self.model,
            td.get(data.state_key).float(),
            td.get(data.action_key).float(),
            td.get(("next", data.state_key)).float(),
            quantile=float(self.cfg.disagreement_quantile),
        )
        return float(calibration.threshold)
