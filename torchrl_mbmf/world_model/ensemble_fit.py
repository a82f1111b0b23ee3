"""Bootstrapped fitting of the ensemble world model and calibration of its disagreement."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel, check_ensemble
from torchrl_mbmf.world_model.fit import fit_world_model
from torchrl_mbmf.world_model.fit_history import EnsembleFitHistory

logger = logging.getLogger(__name__)

_EVAL_CHUNK = 8192


def fit_ensemble(
    model: EnsembleDeltaDynamicsModel, data: TransitionDataset | TensorDictBase, **kwargs: Any
) -> EnsembleFitHistory:
    """Fits every member on its own bootstrap resample, with early stopping on a held-out split.

    A thin entry point to :func:`~torchrl_mbmf.world_model.fit.fit_world_model`: the split
    and scaling of :func:`~torchrl_mbmf.world_model.fit_dynamics`, all members in one batched
    step, early stopping on the members' mean held-out MSE. Design:
    ``docs/design/world_model_fit.md``.

    Args:
        model: the ensemble, trained in place.
        data: a :class:`~torchrl_mbmf.data.TransitionDataset` or a TensorDict of transitions
            (``state``, ``action``, ``("next", "state")``, ``("next", "reward")``).

    Keyword Args:
        **kwargs: the settings of
            :func:`~torchrl_mbmf.world_model.fit.fit_world_model` (``lr``,
            ``batch_size`` per member, ``max_epochs``, ``val_fraction``, ``patience``,
            ``bootstrap``, ``fit_normalizer``, ``seed``, ``progress``, ``optimizer``).

    Returns:
        The :class:`EnsembleFitHistory`.

    Raises:
        TypeError: if ``model`` is not an ensemble.
        ValueError: on NaN/Inf data, too little data, or invalid settings.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.ensemble_fit import fit_ensemble
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 400, seed=0)
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(32, 32))
        >>> history = fit_ensemble(model, data, lr=1e-3, batch_size=64, max_epochs=5, seed=0)
        >>> history.val_loss[-1] < history.val_loss[0], len(history.member_val_loss)
        (True, 3)
    """
    check_ensemble(model, "model")  # one network (ensemble_size=1): fit_dynamics
    return fit_world_model(model, data, **kwargs)


@dataclass
class DisagreementCalibration:
    """A disagreement threshold picked on held-out real transitions, with diagnostics.

    Attributes:
        threshold: the picked threshold (pass it as the planner's ``disagreement_threshold``).
        quantile: the quantile of the held-out disagreement it is.
        num_transitions: held-out transitions used.
        error_below: mean one-step normalised error of the transitions whose disagreement is
            at most ``threshold``.
        error_above: the same for the transitions above it (``nan`` if there are none).
        rank_correlation: Spearman rank correlation between disagreement and one-step error
            (near 0 means the disagreement says little about the model's error on this data).

    Examples:
        >>> from torchrl_mbmf.world_model.ensemble_fit import DisagreementCalibration
        >>> DisagreementCalibration(0.2, 0.9, 100, 0.01, 0.05, 0.4).threshold
        0.2
    """

    threshold: float
    quantile: float
    num_transitions: int
    error_below: float
    error_above: float
    rank_correlation: float


def _ranks(x: torch.Tensor) -> torch.Tensor:
    ranks = torch.empty_like(x)
    ranks[x.argsort()] = torch.arange(x.numel(), dtype=x.dtype, device=x.device)
    return ranks


@torch.no_grad()
def calibrate_disagreement_threshold(
    model: EnsembleDeltaDynamicsModel,
    states: torch.Tensor,
    actions: torch.Tensor,
    next_states: torch.Tensor,
    quantile: float = 0.9,
    *,
    batch_size: int = _EVAL_CHUNK,
) -> DisagreementCalibration:
    """Picks the planner's disagreement threshold from held-out real transitions.

    The threshold is the ``quantile`` of the ensemble's disagreement
    (:meth:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel.disagreement`) over held-out real
    ``(s, a)`` pairs (never the training data: the threshold would be too strict). The next
    states only feed the diagnostics. Why: ``docs/design/world_model_fit.md``.

    Args:
        model: the fitted ensemble.
        states: held-out states ``[N, state_dim]``.
        actions: their actions ``[N, action_dim]``.
        next_states: their real next states ``[N, state_dim]``.
        quantile: quantile of the held-out disagreement taken as the threshold, in (0, 1].
            Defaults to ``0.9``.

    Keyword Args:
        batch_size: transitions per forward pass (memory bound). Defaults to ``8192``.

    Returns:
        The :class:`DisagreementCalibration`.

    Raises:
        ValueError: on a wrong quantile or shapes, or when the disagreement is 0 on all
            transitions (one member, or identical members): no positive threshold exists.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.ensemble_fit import calibrate_disagreement_threshold
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(16,))
        >>> s, a = torch.randn(200, 3), torch.rand(200, 1) * 2 - 1
        >>> cal = calibrate_disagreement_threshold(model, s, a, s + 0.1, quantile=0.9)
        >>> round((model.disagreement(s, a) <= cal.threshold).float().mean().item(), 3)
        0.9
    """
    if not isinstance(model, DeltaDynamicsModel):
        raise TypeError(f"model must be a DeltaDynamicsModel, got {type(model).__name__}")
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must be in (0, 1], got {quantile}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if states.dim() != 2 or states.shape != next_states.shape:
        raise ValueError(
            f"states and next_states must both be [N, state_dim], got {tuple(states.shape)} "
            f"and {tuple(next_states.shape)}"
        )
    if actions.dim() != 2 or actions.shape[0] != states.shape[0]:
        raise ValueError(
            f"actions must be [N={states.shape[0]}, action_dim], got {tuple(actions.shape)}"
        )
    n = states.shape[0]
    if n < 1:
        raise ValueError("need at least one held-out transition")
    device, dtype = model.state_loc.device, model.state_loc.dtype
    disagreement, error = [], []
    for i in range(0, n, batch_size):
        s = states[i : i + batch_size].to(device=device, dtype=dtype)
        a = actions[i : i + batch_size].to(device=device, dtype=dtype)
        s2 = next_states[i : i + batch_size].to(device=device, dtype=dtype)
        mean = model.predict_scaled_members(s, a)[0]
        target = (s2 - s - model.delta_loc) / model.delta_scale
        disagreement.append(model.disagreement_of_scaled(mean))
        error.append((mean[..., : model.state_dim].mean(0) - target).pow(2).mean(-1))
    d, e = torch.cat(disagreement), torch.cat(error)
    threshold = float(torch.quantile(d, quantile))
    if threshold <= 0.0:
        raise ValueError(
            f"the {quantile} quantile of the held-out disagreement is {threshold}: the members "
            f"agree exactly (num_members={model.num_members}); no positive threshold exists"
        )
    below = d <= threshold
    error_below = float(e[below].mean())
    error_above = float(e[~below].mean()) if (~below).any() else float("nan")
    if n > 1:
        rd, re = _ranks(d), _ranks(e)
        corr = float(torch.corrcoef(torch.stack([rd, re]))[0, 1])
    else:
        corr = float("nan")
    result = DisagreementCalibration(threshold, float(quantile), n, error_below, error_above, corr)
    logger.info(
        "disagreement threshold %.4g (q=%.2f of %d transitions): one-step error %.4g below, "
        "%.4g above, rank correlation %.3f",
        threshold,
        quantile,
        n,
        error_below,
        error_above,
        corr,
    )
    return result


__all__ = [
    "DisagreementCalibration",
    "EnsembleFitHistory",
    "calibrate_disagreement_threshold",
    "fit_ensemble",
]
