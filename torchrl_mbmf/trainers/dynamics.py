"""Supervised fitting of the world model on real transitions (thesis section 5.2, table 7)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, get_args

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_mbmf.data.transitions import TransitionDataset, _done_of, consecutive_windows
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.dynamics_loss import (
    DynamicsLoss,
    check_multi_step,
    check_multi_step_weight,
)

__all__ = [
    "EarlyStopping",
    "FitHistory",
    "dynamics_optimizer",
    "fit_dynamics",
    "fit_dynamics_kwargs",
]

#: Early-stopping criteria of :func:`fit_dynamics` with a multi-step term: ``"objective"``,
#: the held-out value of the trained loss (one-step + weight x multi-step); ``"one_step"``,
#: the held-out one-step loss alone. Identical when ``multi_step == 1``.
EarlyStopping = Literal["objective", "one_step"]

logger = logging.getLogger(__name__)

# The window order of the multi-step term has its own generator, seeded from ``seed`` with
# this offset, so the split and the one-step minibatch order are those of a one-step fit.
_WINDOW_SEED_OFFSET = 1_000_003


@dataclass
class FitHistory:
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
            contain at least one held-out transition (never trained on as a window; their
            other transitions are training data of the one-step term, so the score is only
            partly held out). Empty when ``k == 1``; NaN if there is no such window.
        best_val_multi_step_loss: ``val_multi_step_loss`` of the kept weights (``None``
            when ``k == 1``).
        early_stopping: the criterion that chose the kept weights (see
            :data:`EarlyStopping`).

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
    multi_step: int = 1
    multi_step_weight: float = 1.0
    num_windows: int = 0
    num_val_windows: int = 0
    train_multi_step_loss: list[float] = field(default_factory=list)
    val_multi_step_loss: list[float] = field(default_factory=list)
    best_val_multi_step_loss: float | None = None
    early_stopping: str = "objective"

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


def _transition_windows(data: TransitionDataset | TensorDictBase, length: int) -> torch.Tensor:
    """``[W, length]`` row indices (rows of :func:`_transition_tensors`) of episode windows."""
    if isinstance(data, TransitionDataset):
        return data.windows(length)
    # A TensorDict [..., T]: time is its last batch dimension; episodes end at done steps.
    try:
        done = _done_of(data)
    except KeyError as err:
        raise ValueError(
            f"multi_step={length} needs ('next', 'done') (or terminated/truncated) flags in the "
            "TensorDict to find episode boundaries"
        ) from err
    done = done.reshape(-1, data.shape[-1])
    start = torch.ones_like(done)
    start[:, 1:] = done[:, :-1]
    flat = data.reshape(-1)
    return consecutive_windows(
        start.reshape(-1).long().cumsum(0),
        done.reshape(-1),
        flat.get("state"),
        flat.get(("next", "state")),
        length,
    )


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
        "early_stopping": _check_early_stopping(
            world_model.get("early_stopping", "objective"), key="world_model.early_stopping"
        ),
    }


def dynamics_optimizer(
    model: torch.nn.Module, *, lr: float = 1e-4, fused_adam: bool = False
) -> torch.optim.Adam:
    """The world model's Adam, to pass to every :func:`fit_dynamics` refit of a run.

    The default is the thesis' optimiser, :class:`torch.optim.Adam` with its stock settings:
    the optimiser :func:`fit_dynamics` builds when it is given none. ``fused_adam=True`` asks
    for PyTorch's fused kernel instead (``Adam(fused=True)``), one pass over each parameter
    per step instead of about seven: the same update formula, but computed in another order,
    so the weights differ from the stock Adam's in the last float bits (on the order of
    ``1e-8`` after tens of steps) and a fit is no longer bit-identical to the thesis loop.

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
        >>> from torchrl_mbmf.trainers.dynamics import dynamics_optimizer
        >>> optimizer = dynamics_optimizer(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
        >>> optimizer.defaults["lr"], optimizer.defaults["fused"]
        (0.0001, None)
    """
    if isinstance(lr, bool) or not isinstance(lr, int | float) or not 0 < lr < math.inf:
        raise ValueError(f"lr must be a positive finite number, got {lr!r}")
    if fused_adam:
        return torch.optim.Adam(model.parameters(), lr=lr, fused=True)
    return torch.optim.Adam(model.parameters(), lr=lr)


def _check_early_stopping(value: Any, *, key: str = "early_stopping") -> EarlyStopping:
    allowed = get_args(EarlyStopping)
    if value not in allowed:
        raise ValueError(f"{key}={value!r} is not a criterion; allowed: {list(allowed)}")
    return value


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
    multi_step: int = 1,
    multi_step_weight: float = 1.0,
    early_stopping: EarlyStopping = "objective",
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
            across refits). Defaults to a new stock Adam (:func:`dynamics_optimizer`).
        multi_step: length ``k`` of the open-loop rollouts of the multi-step term; ``1``
            turns it off. Defaults to ``1``.
        multi_step_weight: weight of the multi-step term (``>= 0``; ignored when
            ``multi_step == 1``). Defaults to ``1.0``.
        early_stopping: held-out criterion of early stopping and of the kept weights,
            ``"objective"`` or ``"one_step"`` (the same when ``multi_step == 1``).
            Defaults to ``"objective"``.

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
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    if batch_size < 1 or max_epochs < 1 or patience < 1:
        raise ValueError(
            f"batch_size, max_epochs and patience must be >= 1, got {batch_size}, "
            f"{max_epochs}, {patience}"
        )
    multi_step = check_multi_step(multi_step)
    multi_step_weight = check_multi_step_weight(multi_step_weight)
    early_stopping = _check_early_stopping(early_stopping)
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
    rollout = None
    if multi_step > 1:
        # The rollouts rescale at every step, so they read the raw tensors.
        rollout = _MultiStepWindows(data, multi_step, tensors, train_idx, device)
    del tensors
    train_x, train_y = inputs[train_idx], targets[train_idx]
    val_x, val_y = inputs[val_idx], targets[val_idx]
    del inputs, targets
    if optimizer is None:
        optimizer = dynamics_optimizer(model, lr=lr)
    history = FitHistory(
        num_train=len(train_idx),
        num_val=n_val,
        multi_step=multi_step,
        multi_step_weight=multi_step_weight,
        early_stopping=early_stopping,
    )
    if rollout is not None:
        history.num_windows = rollout.num_train
        history.num_val_windows = rollout.num_val
        window_generator = torch.Generator()
        if seed is not None:
            window_generator.manual_seed(seed + _WINDOW_SEED_OFFSET)
        else:
            window_generator.seed()

    def val_loss() -> float:
        with torch.no_grad():
            return float(loss_module.scaled_loss(val_x, val_y))

    def score(one_step: float, multi: float) -> float:
        """Early-stopping criterion of a multi-step fit."""
        if early_stopping == "one_step" or math.isnan(multi):
            return one_step
        return one_step + multi_step_weight * multi

    best = val_loss()
    best_one_step = best
    if rollout is not None:
        best_multi = rollout.val_loss(loss_module)
        best = score(best_one_step, best_multi)
        if math.isnan(best_multi) and early_stopping == "objective":
            logger.warning(
                "fit_dynamics: no %d-step window holds a held-out transition; early stopping "
                "on the one-step loss",
                multi_step,
            )
    best_state = _StateSnapshot(model)
    history.best_epoch = -1
    bad_epochs = 0
    n_train = len(train_idx)
    # Each epoch gathers the training split once, in the epoch's shuffled order, into these
    # buffers; its minibatches are then contiguous slices holding exactly the rows that
    # ``train_x[order[i : i + batch_size]]`` would gather.
    epoch_x, epoch_y = torch.empty_like(train_x), torch.empty_like(train_y)
    bar = tqdm(range(max_epochs), desc="world model", unit="epoch", disable=not progress)
    for epoch in bar:
        order = torch.randperm(n_train, generator=generator).to(device)
        torch.index_select(train_x, 0, order, out=epoch_x)
        torch.index_select(train_y, 0, order, out=epoch_y)
        total = torch.zeros((), device=device)
        if rollout is not None:
            rollout.start_epoch(window_generator)
        for i in range(0, n_train, batch_size):
            batch_x, batch_y = epoch_x[i : i + batch_size], epoch_y[i : i + batch_size]
            size = batch_x.shape[0]
            loss = loss_module.scaled_loss(batch_x, batch_y)
            total += loss.detach() * size
            if rollout is not None:
                multi = loss_module.multi_step_loss(*rollout.next_batch(size))
                rollout.record(multi, size)
                loss = loss + multi_step_weight * multi
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        train_loss = float(total) / n_train
        history.train_loss.append(train_loss)
        current = val_loss()
        history.val_loss.append(current)
        postfix = {"train": f"{train_loss:.4f}", "val": f"{current:.4f}"}
        if rollout is not None:
            history.train_multi_step_loss.append(rollout.epoch_loss())
            history.val_multi_step_loss.append(rollout.val_loss(loss_module))
            postfix["train_k"] = f"{history.train_multi_step_loss[-1]:.4f}"
            postfix["val_k"] = f"{history.val_multi_step_loss[-1]:.4f}"
        bar.set_postfix(**postfix)
        criterion = current
        if rollout is not None:
            criterion = score(current, history.val_multi_step_loss[-1])
        if criterion < best:
            best, bad_epochs, history.best_epoch = criterion, 0, epoch
            best_one_step = current
            if rollout is not None:
                best_multi = history.val_multi_step_loss[-1]
            best_state.save()
        else:
            bad_epochs += 1
            if bad_epochs >= patience:
                history.stopped_early = epoch + 1 < max_epochs
                break
    bar.close()
    history.best_val_loss = best_one_step
    if rollout is not None:
        history.best_val_multi_step_loss = best_multi
    best_state.restore()
    history.seconds = time.perf_counter() - start
    logger.info(
        "fit_dynamics: %d epochs, best val loss %.5f at epoch %d (%.1fs)",
        history.epochs,
        history.best_val_loss,
        history.best_epoch,
        history.seconds,
    )
    if rollout is not None:
        logger.info(
            "fit_dynamics: %d-step loss (weight %g) on %d windows: train %.5f (last epoch), "
            "val %.5f (kept weights; early stopping on %s)",
            multi_step,
            multi_step_weight,
            history.num_windows,
            history.train_multi_step_loss[-1],
            best_multi,
            early_stopping,
        )
    return history


class _StateSnapshot:
    """A copy of a model's ``state_dict`` kept in preallocated tensors (the best epoch's)."""

    def __init__(self, model: torch.nn.Module) -> None:
        self.model = model
        self.saved = {k: v.detach().clone() for k, v in model.state_dict().items()}

    def save(self) -> None:
        """Copies the model's current state into the snapshot."""
        with torch.no_grad():
            for key, value in self.model.state_dict().items():
                self.saved[key].copy_(value)

    def restore(self) -> None:
        """Loads the snapshot back into the model."""
        self.model.load_state_dict(self.saved)


class _MultiStepWindows:
    """Windows of ``k`` consecutive transitions for the multi-step term of one fit."""

    def __init__(
        self,
        data: TransitionDataset | TensorDictBase,
        length: int,
        tensors: list[torch.Tensor],
        train_idx: torch.Tensor,
        device: torch.device,
    ) -> None:
        self.state, self.action, self.next_state, self.reward = tensors
        windows = _transition_windows(data, length)
        in_train = torch.zeros(self.state.shape[0], dtype=torch.bool)
        in_train[train_idx] = True
        inside = in_train[windows].all(1)
        self.train = windows[inside].to(device)
        self.val = windows[~inside].to(device)
        self.num_train, self.num_val = self.train.shape[0], self.val.shape[0]
        if self.num_train == 0:
            raise ValueError(
                f"multi_step={length}: no {length} consecutive transitions of one episode lie "
                f"in the training split ({windows.shape[0]} windows in all); use a smaller "
                "multi_step or more data"
            )
        self.device = device

    def tensors(self, rows: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(state0, actions, next_states, rewards)`` of windows ``rows [B, k]``."""
        return self.state[rows[:, 0]], self.action[rows], self.next_state[rows], self.reward[rows]

    def start_epoch(self, generator: torch.Generator) -> None:
        """Draws the epoch's window order."""
        self.order = torch.randperm(self.num_train, generator=generator).to(self.device)
        self.offset = 0
        self.total = torch.zeros((), device=self.device)
        self.count = 0

    def next_batch(self, size: int) -> tuple[torch.Tensor, ...]:
        """The next ``size`` windows of the epoch's order (cycling when it runs out)."""
        pos = (torch.arange(size, device=self.device) + self.offset) % self.num_train
        self.offset += size
        return self.tensors(self.train[self.order[pos]])

    def record(self, loss: torch.Tensor, size: int) -> None:
        """Adds a minibatch's multi-step loss to the epoch's mean."""
        self.total += loss.detach() * size
        self.count += size

    def epoch_loss(self) -> float:
        """Mean multi-step loss of the epoch's minibatches."""
        return float(self.total) / max(1, self.count)

    def val_loss(self, loss_module: DynamicsLoss, chunk: int = 4096) -> float:
        """Multi-step loss of the windows that contain a held-out transition."""
        if self.num_val == 0:
            return math.nan
        total = 0.0
        with torch.no_grad():
            for i in range(0, self.num_val, chunk):
                rows = self.val[i : i + chunk]
                err = loss_module.rollout_squared_errors(*self.tensors(rows))
                total += float(err.mean()) * rows.shape[0]
        return total / self.num_val
