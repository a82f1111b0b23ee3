"""Supervised fitting of the world model on real transitions (thesis section 5.2, table 7)."""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import asdict, dataclass, field

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.dynamics_loss import DynamicsLoss

logger = logging.getLogger(__name__)


@dataclass
class FitHistory:
    """Per-epoch record of a world-model fit.

    Attributes:
        train_loss: mean training loss (scaled MSE) of each epoch.
        val_loss: held-out loss after each epoch.
        best_epoch: epoch (0-based) whose weights were kept; ``-1`` when no epoch improved on
            the starting weights, which are then kept.
        best_val_loss: held-out loss of the kept weights.
        stopped_early: whether early stopping ended the fit before ``max_epochs``.
        num_train: training transitions.
        num_val: held-out transitions.
        seconds: wall time of the fit.

    Examples:
        >>> from torchrl_mbmf.trainers import FitHistory
        >>> FitHistory([1.0, 0.5], [1.1, 0.6], best_epoch=1, best_val_loss=0.6).epochs
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

    @property
    def epochs(self) -> int:
        """Number of epochs run."""
        return len(self.train_loss)

    def to_dict(self) -> dict[str, object]:
        """JSON-serialisable form."""
        return {**asdict(self), "epochs": self.epochs}


def _transition_tensors(
    data: TransitionDataset | TensorDictBase,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    if isinstance(data, TransitionDataset):
        td = data.tensors()
        keys = (data.state_key, data.action_key, ("next", data.state_key))
        reward_key = ("next", data.reward_key)
    else:
        td = data.reshape(-1)
        keys = ("state", "action", ("next", "state"))
        reward_key = ("next", "reward")
    out = [td.get(k).float() for k in keys]
    reward = td.get(reward_key).float().reshape(-1, 1)
    names = ("state", "action", "next state", "reward")
    for name, value in zip(names, [*out, reward], strict=True):
        if not torch.isfinite(value).all():
            bad = int((~torch.isfinite(value)).any(-1).sum())
            raise ValueError(f"{name} has NaN or Inf in {bad} transitions; refusing to fit on them")
    return out[0], out[1], out[2], reward


def fit_dynamics(
    model: DeltaDynamicsModel,
    data: TransitionDataset | TensorDictBase,
    *,
    lr: float = 1e-4,
    batch_size: int = 512,
    max_epochs: int = 200,
    val_fraction: float = 0.1,
    patience: int = 10,
    fit_normalizer: bool = True,
    seed: int | None = None,
    progress: bool = False,
    optimizer: torch.optim.Optimizer | None = None,
) -> FitHistory:
    """Fits the world model on real transitions with Adam and early stopping.

    The thesis' settings (table 7): Adam at lr 1e-4, batch 512, up to 200 epochs, early stopping
    on a held-out split. The scaler is fitted on the training split (``fit_normalizer``), the
    weights of the best held-out epoch are restored at the end, and the model keeps training
    from its current weights (refits during training warm-start).

    Args:
        model: the world model, trained in place.
        data: a :class:`~torchrl_mbmf.data.TransitionDataset` or a TensorDict of transitions
            (``state``, ``action``, ``("next", "state")``, ``("next", "reward")``).

    Keyword Args:
        lr: Adam learning rate (ignored when ``optimizer`` is given). Defaults to ``1e-4``.
        batch_size: minibatch size. Defaults to ``512``.
        max_epochs: maximum number of passes over the training split. Defaults to ``200``.
        val_fraction: share of transitions held out for early stopping. Defaults to ``0.1``.
        patience: epochs without held-out improvement before stopping. Defaults to ``10``.
        fit_normalizer: refit the scaling statistics on the training split first.
            Defaults to ``True``.
        seed: seed of the split and the minibatch order. Defaults to ``None``.
        progress: show a tqdm bar over epochs. Defaults to ``False``.
        optimizer: optimiser over ``model.parameters()`` to continue with (its state persists
            across refits). Defaults to a new Adam.

    Returns:
        The :class:`FitHistory`.

    Raises:
        ValueError: on NaN/Inf data, too little data, or invalid settings.

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
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    if batch_size < 1 or max_epochs < 1 or patience < 1:
        raise ValueError(
            f"batch_size, max_epochs and patience must be >= 1, got {batch_size}, "
            f"{max_epochs}, {patience}"
        )
    start = time.perf_counter()
    state, action, next_state, reward = _transition_tensors(data)
    n = state.shape[0]
    n_val = max(1, round(n * val_fraction))
    if n - n_val < 2:
        raise ValueError(f"need at least {n_val + 2} transitions to fit, got {n}")
    device = next(model.parameters()).device
    generator = torch.Generator()
    if seed is not None:
        generator.manual_seed(seed)
    else:
        generator.seed()
    perm = torch.randperm(n, generator=generator)
    val_idx, train_idx = perm[:n_val], perm[n_val:]
    tensors = [t.to(device) for t in (state, action, next_state, reward)]
    if fit_normalizer:
        model.fit_normalizer(*(t[train_idx] for t in tensors))
    loss_module = DynamicsLoss(model)
    # The scaler is fixed during the fit: scale everything once, then train on index slices.
    with torch.no_grad():
        inputs, targets = loss_module.scaled_pairs(*tensors)
    del tensors
    train_x, train_y = inputs[train_idx], targets[train_idx]
    val_x, val_y = inputs[val_idx], targets[val_idx]
    del inputs, targets
    if optimizer is None:
        optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    history = FitHistory(num_train=len(train_idx), num_val=n_val)

    def val_loss() -> float:
        with torch.no_grad():
            return float(loss_module.scaled_loss(val_x, val_y))

    best = val_loss()
    best_state = copy.deepcopy(model.state_dict())
    history.best_epoch = -1
    bad_epochs = 0
    n_train = len(train_idx)
    bar = tqdm(range(max_epochs), desc="world model", unit="epoch", disable=not progress)
    for epoch in bar:
        order = torch.randperm(n_train, generator=generator).to(device)
        total = torch.zeros((), device=device)
        for i in range(0, n_train, batch_size):
            idx = order[i : i + batch_size]
            loss = loss_module.scaled_loss(train_x[idx], train_y[idx])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * idx.numel()
        train_loss = float(total) / n_train
        history.train_loss.append(train_loss)
        current = val_loss()
        history.val_loss.append(current)
        bar.set_postfix(train=f"{train_loss:.4f}", val=f"{current:.4f}")
        if current < best:
            best, bad_epochs, history.best_epoch = current, 0, epoch
            best_state = copy.deepcopy(model.state_dict())
        else:
            bad_epochs += 1
            if bad_epochs >= patience:
                history.stopped_early = epoch + 1 < max_epochs
                break
    bar.close()
    history.best_val_loss = best
    model.load_state_dict(best_state)
    history.seconds = time.perf_counter() - start
    logger.info(
        "fit_dynamics: %d epochs, best val loss %.5f at epoch %d (%.1fs)",
        history.epochs,
        history.best_val_loss,
        history.best_epoch,
        history.seconds,
    )
    return history
