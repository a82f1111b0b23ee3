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

    A thin entry point to the one fitter,
    :func:`~torchrl_mbmf.world_model.fit.fit_world_model`. The data handling is
    :func:`~torchrl_mbmf.trainers.fit_dynamics`' (the same split for the
    same ``seed``, scaler fitted on the training split, data scaled once, best held-out weights
    restored at the end, warm start from the current weights). Then each member ``k`` draws
    ``num_train`` indices with replacement from the training split (a torch ``Generator``
    seeded by ``seed``; ``bootstrap=False`` gives every member the whole split), and every
    epoch visits each member's sample in its own random order. One minibatch step takes
    ``batch_size`` rows for every member at once, ``[K, batch_size, in]``, runs all members in
    one batched forward and minimises the sum over members of their losses (so each member gets
    exactly the gradient of its own loss; Adam is element-wise, so one optimiser over the
    stacked weights equals one per member). The early-stopping metric is the held-out MSE of
    each member's mean prediction, averaged over members (also for a probabilistic ensemble,
    whose NLL can keep falling by shrinking variances while its means overfit).

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

    The rule: the threshold is the ``quantile`` of the ensemble's disagreement
    (:meth:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel.disagreement`) over held-out real
    ``(s, a)`` pairs. On real data the model's one-step error is what the fit accepted (its
    held-out loss), so a disagreement up to the level of the ``quantile`` of real transitions
    counts as "as sure as on real data"; an imagined step beyond it is less familiar to the
    ensemble than ``1 - quantile`` of the real data, and the planner stops trusting the model
    there. Pass transitions the ensemble was not trained on (a held-out split or fresh data);
    on its own training data the disagreement is lower and the threshold too strict.

    The next states are used for diagnostics only: the mean one-step normalised error (mean
    over state dims of the squared error of the members' mean delta, in ``delta_scale`` units)
    below and above the threshold, and its rank correlation with the disagreement; a useful
    disagreement has ``error_above > error_below`` and a positive correlation (both are logged).

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
