"""Supervised fitting of the world model on real transitions (thesis section 5.2, table 7).

:func:`fit_dynamics` is the thesis' entry point to the one world-model fitter,
:func:`~torchrl_mbmf.trainers.world_model_fit.fit_world_model`, for one network.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tensordict import TensorDictBase

from torchrl_mbmf.checks import check_multi_step, check_multi_step_weight
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.trainers.fit_data import MultiStepWindows, transition_tensors
from torchrl_mbmf.trainers.fit_history import (
    EarlyStopping,
    FitHistory,
    check_early_stopping,
    dynamics_optimizer,
)
from torchrl_mbmf.trainers.world_model_fit import fit_world_model

__all__ = [
    "EarlyStopping",
    "FitHistory",
    "MultiStepWindows",
    "dynamics_optimizer",
    "fit_dynamics",
    "fit_dynamics_kwargs",
    "transition_tensors",
]


def fit_dynamics_kwargs(world_model: Mapping[str, Any]) -> dict[str, Any]:
    """The keyword arguments of :func:`fit_dynamics` set by a ``world_model`` config node.

    One place maps the config keys to the fit (``lr``, ``batch_size``, ``max_epochs``,
    ``val_fraction``, ``patience``, ``multi_step``, ``multi_step_weight``,
    ``early_stopping``), so every caller passes the same settings. ``multi_step``,
    ``multi_step_weight`` and ``early_stopping`` default to ``1``, ``1.0`` and
    ``"objective"`` (the thesis' one-step fit) when a config predates them.

    Args:
        world_model: the ``world_model`` config (a ``DictConfig`` or a mapping).

    Returns:
        Keyword arguments for :func:`fit_dynamics` (add ``seed``, ``progress``, ``optimizer``).

    Raises:
        ValueError: naming ``world_model.multi_step``, ``world_model.multi_step_weight`` or
            ``world_model.early_stopping`` if it is invalid.

    Examples:
        >>> from torchrl_mbmf.trainers.dynamics import fit_dynamics_kwargs
        >>> kwargs = fit_dynamics_kwargs({"lr": 1e-4, "batch_size": 512, "max_epochs": 200,
        ...                               "val_fraction": 0.1, "patience": 10, "multi_step": 5})
        >>> kwargs["multi_step"], kwargs["multi_step_weight"]
        (5, 1.0)
    """
    return {
        "lr": float(world_model["lr"]),
        "batch_size": int(world_model["batch_size"]),
        "max_epochs": int(world_model["max_epochs"]),
        "val_fraction": float(world_model["val_fraction"]),
        "patience": int(world_model["patience"]),
        "multi_step": check_multi_step(
            world_model.get("multi_step", 1), key="world_model.multi_step"
        ),
        "multi_step_weight": check_multi_step_weight(
            world_model.get("multi_step_weight", 1.0), key="world_model.multi_step_weight"
        ),
        "early_stopping": check_early_stopping(
            world_model.get("early_stopping", "objective"), key="world_model.early_stopping"
        ),
    }


def fit_dynamics(
    model: DeltaDynamicsModel, data: TransitionDataset | TensorDictBase, **kwargs: Any
) -> FitHistory:
    """Fits the world model on real transitions with Adam and early stopping.

    The thesis' settings (table 7): Adam at lr 1e-4, batch 512, up to 200 epochs, early stopping
    on a held-out split. The scaler is fitted on the training split (``fit_normalizer``), the
    weights of the best held-out epoch are restored at the end, and the model keeps training
    from its current weights (refits during training warm-start).

    With ``multi_step = k > 1`` every minibatch step also rolls the model open loop over as
    many windows of ``k`` consecutive real transitions of one episode (never across a done,
    truncation or reset, see :meth:`~torchrl_mbmf.data.TransitionDataset.windows`) and adds
    ``multi_step_weight`` times their ``k``-step loss
    (:meth:`~torchrl_mbmf.objectives.DynamicsLoss.multi_step_loss`) to the one-step loss;
    gradients flow through the rollout. Only windows whose ``k`` transitions all lie in the
    training split are trained on, so held-out transitions stay unseen. The split and the
    one-step minibatch order are those of the one-step fit with the same seed (the windows'
    order comes from a second generator), so with ``multi_step=1`` (the default, the thesis)
    the fit is bit-identical to one without the option, and a one-step and a multi-step fit
    differ only in the loss.

    Early stopping and the kept weights follow ``early_stopping``. The default,
    ``"objective"``, scores each epoch by the held-out value of the loss being trained:
    one-step loss + ``multi_step_weight`` x the ``k``-step loss of the windows that contain a
    held-out transition (a random transition split leaves almost no window wholly held out,
    a share ``val_fraction ** k``; these windows were never trained on as windows, though
    their other transitions were). Selecting on the one-step loss alone (``"one_step"``) can
    undo the multi-step training: the one-step loss prefers exactly the one-step-optimal
    weights whose errors compound, so it may restore an early epoch (on the noisy toy system
    of the tests it kept epoch 6 of 40 and lost the whole gain for one seed in eight). Both
    are logged every epoch (:class:`FitHistory`); with ``multi_step=1`` they coincide.

    The loop is kept tight without changing a bit of the result: the data are scaled once,
    each epoch gathers the training split once in the epoch's shuffled order (its minibatches
    are then contiguous slices), the hidden ReLUs run in place
    (:meth:`~torchrl_mbmf.objectives.DynamicsLoss.scaled_loss`) and the best weights are
    copied into preallocated tensors. On one CPU thread about three quarters of a step is
    then the network's matrix products; the stock Adam is most of the rest, and
    :func:`dynamics_optimizer` with ``fused_adam=True`` (opt-in, other float rounding)
    removes most of it. A cap on the epochs of a refit is ``max_epochs`` (a capped fit is
    exactly the first ``max_epochs`` epochs of the uncapped one).

    Args:
        model: the world model, trained in place.
        data: a :class:`~torchrl_mbmf.data.TransitionDataset` or a TensorDict of transitions
            (``state``, ``action``, ``("next", "state")``, ``("next", "reward")``).

    Keyword Args:
        **kwargs: the settings of
            :func:`~torchrl_mbmf.trainers.world_model_fit.fit_world_model` (``lr``,
            ``batch_size``, ``max_epochs``, ``val_fraction``, ``patience``,
            ``fit_normalizer``, ``seed``, ``progress``, ``optimizer``, ``multi_step``,
            ``multi_step_weight``, ``early_stopping``), the thesis' values by default.

    Returns:
        The :class:`FitHistory`.

    Raises:
        ValueError: on NaN/Inf data, too little data, invalid settings (the message names the
            argument), or, with ``multi_step > 1``, no ``k``-step window in the training split.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.trainers import fit_dynamics
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 400, seed=0)
        >>> model = DeltaDynamicsModel(3, 1, hidden_sizes=(32, 32))
        >>> history = fit_dynamics(model, data, lr=1e-3, batch_size=64, max_epochs=5, seed=0)
        >>> history.val_loss[-1] < history.val_loss[0]
        True
        >>> history = fit_dynamics(model, data, batch_size=64, max_epochs=1, seed=0, multi_step=3)
        >>> history.num_windows > 0, len(history.train_multi_step_loss)
        (True, 1)
    """
    if getattr(model, "ensemble_size", 1) > 1:
        raise ValueError(
            f"fit_dynamics trains one network, got an ensemble ({type(model).__name__} with "
            f"ensemble_size={model.ensemble_size}); fit it with "
            "torchrl_mbmf.trainers.ensemble_fit.fit_ensemble (or fit_world_model)"
        )
    return fit_world_model(model, data, **kwargs)
