"""The records of a world-model fit, its early-stopping criteria and its optimiser."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar, Literal, get_args

import torch

__all__ = [
    "EarlyStopping",
    "EnsembleFitHistory",
    "FitHistory",
    "FitRecord",
    "check_early_stopping",
    "dynamics_optimizer",
]

#: Early-stopping criteria of a fit with a multi-step term: ``"objective"``, the held-out
#: value of the trained loss (one-step + weight x multi-step); ``"one_step"``, the held-out
#: one-step loss alone. Identical when ``multi_step == 1``.
EarlyStopping = Literal["objective", "one_step"]


def check_early_stopping(value: Any, *, key: str = "early_stopping") -> EarlyStopping:
    """Checks an early-stopping criterion (see :data:`EarlyStopping`).

    Args:
        value: the criterion.
        key: its name in the error message. Defaults to ``"early_stopping"``.

    Examples:
        >>> from torchrl_mbmf.world_model.fit_history import check_early_stopping
        >>> check_early_stopping("one_step")
        'one_step'
    """
    allowed = get_args(EarlyStopping)
    if value not in allowed:
        raise ValueError(f"{key}={value!r} is not a criterion; allowed: {list(allowed)}")
    return value


@dataclass
class FitRecord:
    """What every world-model fit records: losses per epoch, the kept epoch, the split sizes.

    Attributes:
        train_loss: mean training loss of each epoch.
        val_loss: held-out loss after each epoch.
        best_epoch: epoch (0-based) whose weights were kept; ``-1`` when no epoch improved on
            the starting weights, which are then kept.
        best_val_loss: held-out loss of the kept weights.
        stopped_early: whether early stopping ended the fit before ``max_epochs``.
        num_train: training transitions.
        num_val: held-out transitions.
        seconds: wall time of the fit.

    Examples:
        >>> from torchrl_mbmf.world_model.fit_history import FitRecord
        >>> FitRecord([1.0, 0.5], [1.1, 0.6]).to_dict()["epochs"]
        2
    """

    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = -1
    best_val_loss: float = float("inf")
    stopped_early: bool = False
    num_train: int = 0
    num_val: int = 0
    seconds: float = 0.0

    #: fields left out of :meth:`to_dict`.
    unserialised: ClassVar[tuple[str, ...]] = ()

    @property
    def epochs(self) -> int:
        """Number of epochs run."""
        return len(self.train_loss)

    def to_dict(self) -> dict[str, object]:
        """JSON-serialisable form (with ``epochs``)."""
        out = {k: v for k, v in asdict(self).items() if k not in self.unserialised}
        return {**out, "epochs": self.epochs}


@dataclass
class FitHistory(FitRecord):
    """Per-epoch record of a world-model fit.

    Attributes:
        train_loss: mean one-step training loss (scaled MSE, eq. 17) of each epoch; with a
            multi-step term the optimised loss is this plus ``multi_step_weight`` times
            ``train_multi_step_loss``.
        val_loss: held-out one-step loss after each epoch (the early-stopping criterion when
            ``multi_step == 1``).
        best_epoch: epoch (0-based) whose weights were kept (the lowest early-stopping
            criterion); ``-1`` when no epoch improved on the starting weights, which are then
            kept.
        best_val_loss: held-out one-step loss of the kept weights.
        stopped_early: whether early stopping ended the fit before ``max_epochs``.
        num_train: training transitions.
        num_val: held-out transitions.
        seconds: wall time of the fit.
        multi_step: rollout length ``k`` of the multi-step term (``1``: none).
        multi_step_weight: weight of the multi-step term.
        num_windows: training windows of ``k`` consecutive transitions (``0`` when ``k == 1``).
        num_val_windows: windows that contain a held-out transition (see ``val_multi_step_loss``).
        train_multi_step_loss: mean ``k``-step open-loop loss of the training windows in each
            epoch (empty when ``k == 1``).
        val_multi_step_loss: ``k``-step open-loop loss after each epoch on the windows that
            contain at least one held-out transition. Empty when ``k == 1``; NaN if there is
            no such window.
        best_val_multi_step_loss: ``val_multi_step_loss`` of the kept weights (``None``
            when ``k == 1``).
        early_stopping: the criterion that chose the kept weights (see
            :data:`EarlyStopping`).

    Examples:
        >>> from torchrl_mbmf.world_model import FitHistory
        >>> FitHistory([1.0, 0.5], [1.1, 0.6], best_epoch=1, best_val_loss=0.6).epochs
        2
    """

    multi_step: int = 1
    multi_step_weight: float = 1.0
    num_windows: int = 0
    num_val_windows: int = 0
    train_multi_step_loss: list[float] = field(default_factory=list)
    val_multi_step_loss: list[float] = field(default_factory=list)
    best_val_multi_step_loss: float | None = None
    early_stopping: str = "objective"


@dataclass
class EnsembleFitHistory(FitRecord):
    """Per-epoch record of an ensemble fit.

    Attributes:
        train_loss: mean training loss of each epoch (MSE, or Gaussian NLL for a probabilistic
            ensemble), averaged over members, each on its own bootstrap sample.
        val_loss: held-out MSE of the members' means (scaled units) after each epoch,
            averaged over members: the early-stopping criterion.
        best_epoch: epoch (0-based) whose weights were kept; ``-1`` when no epoch improved on
            the starting weights, which are then kept.
        best_val_loss: held-out loss of the kept weights.
        stopped_early: whether early stopping ended the fit before ``max_epochs``.
        num_train: transitions in the training split (each member draws as many).
        num_val: held-out transitions.
        seconds: wall time of the fit.
        member_val_loss: held-out MSE of each member with the kept weights.
        num_members: ensemble size ``K``.
        bootstrap: whether each member trained on its own bootstrap resample.
        unique_fraction: per member, the share of distinct training transitions in its
            bootstrap sample (about 0.632 for large splits; 1.0 without bootstrap).
        val_indices: indices (into the fitted data) of the held-out split, which no member
            trained on: the data to calibrate the disagreement threshold on. Not serialised.

    Examples:
        >>> from torchrl_mbmf.world_model.ensemble_fit import EnsembleFitHistory
        >>> h = EnsembleFitHistory([1.0, 0.5], [1.1, 0.6], member_val_loss=[0.5, 0.7])
        >>> h.epochs, h.to_dict()["member_val_loss"]
        (2, [0.5, 0.7])
    """

    member_val_loss: list[float] = field(default_factory=list)
    num_members: int = 0
    bootstrap: bool = True
    unique_fraction: list[float] = field(default_factory=list)
    val_indices: torch.Tensor | None = field(default=None, repr=False)

    unserialised: ClassVar[tuple[str, ...]] = ("val_indices",)


def dynamics_optimizer(
    model: torch.nn.Module, *, lr: float = 1e-4, fused_adam: bool = False
) -> torch.optim.Adam:
    """The world model's Adam, to pass to every :func:`fit_dynamics` refit of a run.

    The thesis' stock :class:`torch.optim.Adam` by default; ``fused_adam=True`` is PyTorch's
    fused kernel (faster, but other float rounding: no longer bit-identical to the thesis
    fit; see ``docs/design/world_model_fit.md``).

    Args:
        model: the world model.

    Keyword Args:
        lr: learning rate. Defaults to ``1e-4`` (thesis table 7).
        fused_adam: use the fused Adam kernel (changes float rounding). Defaults to ``False``.

    Returns:
        The optimiser over ``model.parameters()``.

    Raises:
        ValueError: if ``lr`` is not a positive finite number.

    Examples:
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.fit import dynamics_optimizer
        >>> optimizer = dynamics_optimizer(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
        >>> optimizer.defaults["lr"], optimizer.defaults["fused"]
        (0.0001, None)
    """
    if isinstance(lr, bool) or not isinstance(lr, int | float) or not 0 < lr < math.inf:
        raise ValueError(f"lr must be a positive finite number, got {lr!r}")
    if fused_adam:
        return torch.optim.Adam(model.parameters(), lr=lr, fused=True)
    return torch.optim.Adam(model.parameters(), lr=lr)
