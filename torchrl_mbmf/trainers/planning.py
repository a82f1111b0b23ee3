"""The model-based part of a run: world model, its data, its refits and the MPC planner.

Built from the ``world_model`` and ``planner`` config groups; the loop sees
:class:`WorldModelPart`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_mbmf.checks import Setting, check_arguments, settings
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.envs.ensemble_env import EnsembleLearnedDynamicsEnv
from torchrl_mbmf.envs.factory import env_metadata
from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.planners import (
    EnsemblePolicyGuidedPlanner,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
)
from torchrl_mbmf.moved import moved_attribute
from torchrl_mbmf.trainers.agents import Agent
from torchrl_mbmf.trainers.schedule import Progress
from torchrl_mbmf.world_model import networks
from torchrl_mbmf.world_model.ensemble_fit import calibrate_disagreement_threshold, fit_ensemble
from torchrl_mbmf.world_model.fit import fit_dynamics, fit_dynamics_kwargs
from torchrl_mbmf.world_model.snapshots import heldout_open_loop_errors, save_fit_snapshot
from torchrl_mbmf.world_model.termination_fit import fit_termination

__all__ = ["WorldModelPart", "make_planner"]

#: Names that moved to another module (kept here for one release, with a warning).
MOVED_NAMES: dict[str, str] = {
    "make_termination_head": "torchrl_mbmf.world_model.networks",
    "make_world_model": "torchrl_mbmf.world_model.networks",
}

log = logging.getLogger(__name__)


def make_planner(
    model_env: EnvBase,
    actor: TensorDictModuleBase,
    guided: bool = True,
    value_module: TensorDictModuleBase | None = None,
    *,
    num_candidates: int,
    horizon: int,
    discount: float = 1.0,
    terminal_value: bool = False,
    refinement: str | None = None,
    iterations: int = 2,
    policy_fraction: float = 1 / 3,
    num_elites: int = 3,
    temperature: float = 1.0,
    min_std: float = 0.05,
) -> TensorDictModuleBase:
    """The MPC planner of the ``planner`` config group (its ``_target_``).

    Args:
        model_env: the learned-dynamics env the planner imagines in (an ensemble env picks
            the ensemble planner).
        actor: the policy (the prior of the guided planners; the random-shooting planner
            only records its log-probabilities).
        guided: the policy-guided planner (``ppo_mpc``, ``sac_mpc``) or random shooting
            (``mpc``). Defaults to ``True``.
        value_module: the terminal value (used when ``terminal_value`` is true).

    Keyword Args:
        num_candidates: candidate action sequences (each key checked by the planner).
        horizon: imagined steps.
        discount: reward discount of a candidate's score. Defaults to ``1.0``.
        terminal_value: add ``discount^h V(s_h)`` to each score. Defaults to ``False``.
        refinement: ``None``, ``"cem"`` or ``"mppi"`` (guided planners; the keys below
            reach them only with a refinement). Defaults to ``None``.
        iterations: refinement rounds. Defaults to ``2``.
        policy_fraction: share of candidates kept from the policy. Defaults to ``1/3``.
        num_elites: CEM elites. Defaults to ``3``.
        temperature: MPPI temperature. Defaults to ``1.0``.
        min_std: smallest refinement std. Defaults to ``0.05``.

    Examples:
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, make_ppo_actor_critic
        >>> from torchrl_mbmf.trainers.planning import make_planner
        >>> env = make_env("Pendulum-v1")
        >>> actor, _ = make_ppo_actor_critic(env, hidden_sizes=(8,))
        >>> model_env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), env)
        >>> planner = make_planner(model_env, actor, num_candidates=4, horizon=2)
        >>> type(planner).__name__
        'PolicyGuidedMPCPlanner'
    """
    check_arguments(settings(flag=("terminal_value",)), locals())
    kwargs: dict[str, Any] = {
        "num_candidates": num_candidates,
        "horizon": horizon,
        "discount": discount,
    }
    if terminal_value:
        kwargs["value_module"] = value_module
    if not guided:
        return RandomShootingMPCPlanner(model_env, actor=actor, **kwargs)
    if refinement is not None:
        kwargs.update(
            refinement=refinement,
            iterations=iterations,
            num_elites=num_elites,
            policy_fraction=policy_fraction,
            temperature=temperature,
            min_std=min_std,
        )
    if isinstance(model_env, EnsembleLearnedDynamicsEnv):
        # Candidate i rolls in member i mod K; with world_model.adaptive_horizon the
        # threshold is calibrated at every refit (None until the first one).
        return EnsemblePolicyGuidedPlanner(model_env, actor, **kwargs)
    return PolicyGuidedMPCPlanner(model_env, actor, **kwargs)


class WorldModelPart:
    """World model, optimiser, real-transition dataset and planner of a model-based run.

    The ``world_model`` group's builder (``docs/design/world_model_fit.md``).

    Args:
        env: the real env.
        agent: the agent whose actor guides the planner (and whose value ends its rollouts).
        device: device of the model and planner.
        planner: builds the planner from keyword arguments ``model_env``, ``actor``,
            ``guided`` and ``value_module`` (the agent's value), e.g. :func:`make_planner`
            with the ``planner`` group's keys bound, or the group through
            :func:`~torchrl_mbmf.trainers.components.instantiate_group`.
        seed: the run's seed (the dataset's record and the held-out scoring).
        guided: the policy-guided planner (else random shooting, ``mpc``). Defaults to ``True``.

    Keyword Args:
        hidden_sizes: the network's hidden layers.
        ensemble_size: the network's members (1: the thesis' single model).
        probabilistic: Gaussian outputs (ensemble only). Defaults to ``False``.
        lr: the fit's Adam learning rate (as every fit key, passed to
            :func:`~torchrl_mbmf.world_model.fit.fit_dynamics`).
        batch_size: the fit's minibatch size.
        max_epochs: the fit's epoch limit.
        val_fraction: the fit's held-out fraction (early stopping).
        patience: epochs without held-out improvement before the fit stops.
        multi_step: the k of the multi-step model loss (1: off, the thesis). Defaults to ``1``.
        multi_step_weight: its weight beside the one-step loss. Defaults to ``1.0``.
        early_stopping: the held-out criterion, ``objective`` or ``one_step``. Defaults to
            ``"objective"``.
        random_steps: random-policy real steps before the first fit.
        refit_every: policy updates between refits (``mpc``, ``ppo_mpc``).
        save_fits: keep each fit's weights under the run folder. Defaults to ``True``.
        adaptive_horizon: calibrate the ensemble planner's disagreement threshold at every
            refit. Defaults to ``False``.
        disagreement_quantile: the held-out quantile of that threshold. Defaults to ``0.9``.
        learn_termination: fit a :class:`~torchrl_mbmf.modules.LearnedTermination` head after
            every model fit; it ends imagined episodes instead of the task's rule. Defaults to
            ``False``.

    Examples:
        >>> from torchrl_mbmf.trainers.planning import WorldModelPart
        >>> WorldModelPart.CALIBRATED
        'disagreement_threshold'
    """

    #: The progress entry that keeps the calibrated disagreement threshold across a resume.
    CALIBRATED = "disagreement_threshold"
    #: The progress entry holding the dataset's length at the last fit.
    LAST_FIT = "last_fit_transitions"
    #: The range of each argument the part reads itself, checked by the constructor.
    ARGUMENTS: dict[str, Setting] = settings(
        positive_int=("random_steps", "refit_every", "batch_size", "max_epochs", "patience"),
        positive=("lr",),
        flag=("save_fits", "adaptive_horizon", "learn_termination"),
        fraction=("val_fraction", "disagreement_quantile"),
    )

    def __init__(
        self,
        env: EnvBase,
        agent: Agent,
        device: torch.device,
        planner: Callable[..., TensorDictModuleBase],
        seed: int,
        guided: bool = True,
        *,
        hidden_sizes: Sequence[int],
        lr: float,
        batch_size: int,
        max_epochs: int,
        val_fraction: float,
        patience: int,
        random_steps: int,
        refit_every: int,
        save_fits: bool = True,
        multi_step: int = 1,
        multi_step_weight: float = 1.0,
        early_stopping: str = "objective",
        ensemble_size: int = 1,
        probabilistic: bool = False,
        adaptive_horizon: bool = False,
        disagreement_quantile: float = 0.9,
        learn_termination: bool = False,
    ) -> None:
        check_arguments(self.ARGUMENTS, locals())
        self.fit_kwargs = fit_dynamics_kwargs(
            {
                "lr": lr,
                "batch_size": batch_size,
                "max_epochs": max_epochs,
                "val_fraction": val_fraction,
                "patience": patience,
                "multi_step": multi_step,
                "multi_step_weight": multi_step_weight,
                "early_stopping": early_stopping,
            }
        )
        self.random_steps, self.refit_every = random_steps, refit_every
        self.save_fits, self.adaptive_horizon = save_fits, adaptive_horizon
        self.disagreement_quantile = float(disagreement_quantile)
        self.model = networks.make_world_model(
            env,
            hidden_sizes=hidden_sizes,
            ensemble_size=ensemble_size,
            probabilistic=probabilistic,
        ).to(device)
        self.termination = (
            networks.make_termination_head(env, self.model.state_dim, device)
            if learn_termination
            else None
        )
        env_cls = EnsembleLearnedDynamicsEnv if self.model.ensemble_size > 1 else LearnedDynamicsEnv
        model_env = env_cls(self.model, env, termination_fn=self.termination)
        self.optim = torch.optim.Adam(self.model.parameters(), lr=float(lr))
        self.seed = int(seed)
        meta = {**env_metadata(env), "seed": self.seed, "state_shape": [self.model.state_dim]}
        self.dataset = TransitionDataset(meta)
        # the agent's value: the planner's terminal value with planner.terminal_value=true
        value = agent.terminal_value()
        self.planner = planner(
            model_env=model_env, actor=agent.actor, guided=guided, value_module=value
        )

    def checkpoint_components(self) -> dict[str, Any]:
        """The tensor state a checkpoint holds (the dataset apart)."""
        head = {} if self.termination is None else {"termination_head": self.termination}
        return {"world_model": self.model, "model_optim": self.optim, **head}

    def trained_modules(self) -> list[torch.nn.Module]:
        """The networks fitted here: the world model (and the termination head, if learned)."""
        return [self.model] + ([] if self.termination is None else [self.termination])

    def restore(self, progress: Progress) -> None:
        """Sets the planner's calibrated threshold from a resumed progress record.

        Raises:
            ValueError: with ``learn_termination``, a resumed dataset without ``terminated``
                flags (saved before they were stored).
        """
        if self.termination is not None and not self.dataset.stores_terminated:
            self.dataset.terminated()  # raises, naming the dataset's format
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

    def refit(self, seed: int, progress: Progress, run_dir: Path | None = None) -> dict[str, float]:
        """Refits the model on every real transition so far; returns the scalars to log.

        Args:
            seed: seed of the fit's split and minibatch order.
            progress: the progress record (receives the calibrated threshold and the dataset's
                length at this fit).
            run_dir: the run folder for the fit snapshots (``None``: none kept).
        """
        fit = self.fit_kwargs
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
                **{k: fit[k] for k in ("batch_size", "max_epochs", "val_fraction", "patience")},
                seed=seed,
                optimizer=self.optim,
            )
        else:
            history = fit_dynamics(self.model, self.dataset, **fit, seed=seed, optimizer=self.optim)
        scalars = {
            "model/train_loss": history.train_loss[-1],
            "model/val_loss": history.best_val_loss,
            "model/epochs": history.epochs,
            "model/transitions": len(self.dataset),
        }
        if getattr(history, "multi_step", 1) > 1:
            scalars["model/train_multi_step_loss"] = history.train_multi_step_loss[-1]
            scalars["model/val_multi_step_loss"] = history.best_val_multi_step_loss
        if self.termination is not None:
            scalars.update(self._fit_termination(seed))
        if self.model.ensemble_size > 1 and self.adaptive_horizon:
            threshold = self._calibrate(history.val_indices)
            progress[self.CALIBRATED] = threshold
            self.planner.disagreement_threshold = threshold
            scalars["model/disagreement_threshold"] = threshold
        progress[self.LAST_FIT] = len(self.dataset)
        if run_dir is not None and self.save_fits:
            save_fit_snapshot(self.model, run_dir, len(self.dataset))
        scalars["time/model_fit_s"] = time.perf_counter() - start
        return {**heldout, **scalars}

    def _fit_termination(self, seed: int) -> dict[str, float]:
        """Refits the termination head on every real next state and its ``terminated`` flag."""
        fit = fit_termination(self.termination, self.dataset, seed=seed)
        return {
            "model/termination_val_accuracy": fit.val_accuracy,
            "model/termination_val_balanced_accuracy": fit.val_balanced_accuracy,
            "model/termination_val_terminal": float(fit.val_terminal),
        }

    def _calibrate(self, idx: torch.Tensor) -> float:
        data = self.dataset
        td = data.tensors()[idx]
        calibration = calibrate_disagreement_threshold(
            self.model,
            td.get(data.state_key).float(),
            td.get(data.action_key).float(),
            td.get(("next", data.state_key)).float(),
            quantile=self.disagreement_quantile,
        )
        return float(calibration.threshold)


def __getattr__(name: str) -> object:
    return moved_attribute(__name__, name, MOVED_NAMES)
