"""The one world-model fitter: Adam with early stopping, for one model or an ensemble.

:func:`fit_world_model` fits one network or an ensemble; :func:`fit_dynamics` is the thesis'
entry point for one network (section 5.2, table 7), :func:`fit_dynamics_kwargs` maps a
``world_model`` config node to its settings.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from tqdm.auto import tqdm

from torchrl_mbmf.checks import check_multi_step, check_multi_step_weight
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.dynamics_loss import DynamicsLoss
from torchrl_mbmf.world_model.fit_data import (
    FitSplit,
    MultiStepWindows,
    StateSnapshot,
    check_fit_settings,
    seeded_generator,
    split_for_fit,
    transition_tensors,
)
from torchrl_mbmf.world_model.fit_history import (
    EarlyStopping,
    EnsembleFitHistory,
    FitHistory,
    check_early_stopping,
    dynamics_optimizer,
)

__all__ = [
    "EarlyStopping",
    "FitHistory",
    "MultiStepWindows",
    "dynamics_optimizer",
    "fit_dynamics",
    "fit_dynamics_kwargs",
    "fit_world_model",
    "transition_tensors",
]

logger = logging.getLogger(__name__)

# The window order of the multi-step term has its own generator, seeded from ``seed`` with
# this offset, so the split and the one-step minibatch order are those of a one-step fit.
_WINDOW_SEED_OFFSET = 1_000_003
_EVAL_CHUNK = 8192


# ----------------------------------------------------------------------- objectives
class _OneStep:
    """One network on shuffled minibatches, plus the optional multi-step term."""

    desc = "world model"

    def __init__(self, model, data, split: FitSplit, *, seed, multi_step, weight, criterion):
        self.loss = DynamicsLoss(model)
        self.split, self.weight, self.criterion = split, weight, criterion
        self.rollout = None
        self.history = FitHistory(
            num_train=len(split.train_idx),
            num_val=len(split.val_idx),
            multi_step=multi_step,
            multi_step_weight=weight,
            early_stopping=criterion,
        )
        if multi_step > 1:
            # The rollouts rescale at every step, so they read the raw tensors.
            self.rollout = MultiStepWindows(
                data, multi_step, split.tensors, split.train_idx, split.device
            )
            self.history.num_windows = self.rollout.num_train
            self.history.num_val_windows = self.rollout.num_val
            self.windows = seeded_generator(None if seed is None else seed + _WINDOW_SEED_OFFSET)
        split.tensors = None
        # Each epoch gathers the training split once, in the epoch's shuffled order, into
        # these buffers; its minibatches are then contiguous slices holding exactly the rows
        # that ``train_x[order[i : i + batch_size]]`` would gather.
        self.epoch_x = torch.empty_like(split.train_x)
        self.epoch_y = torch.empty_like(split.train_y)

    def _val_one_step(self) -> float:
        with torch.no_grad():
            return float(self.loss.scaled_loss(self.split.val_x, self.split.val_y))

    def _score(self, one_step: float, multi: float) -> float:
        if self.criterion == "one_step" or math.isnan(multi):
            return one_step
        return one_step + self.weight * multi

    def initial(self) -> float:
        self.best_one_step = best = self._val_one_step()
        if self.rollout is not None:
            self.best_multi = self.rollout.val_loss(self.loss)
            best = self._score(best, self.best_multi)
            if math.isnan(self.best_multi) and self.criterion == "objective":
                logger.warning(
                    "fit_dynamics: no %d-step window holds a held-out transition; early "
                    "stopping on the one-step loss",
                    self.history.multi_step,
                )
        return best

    def train_epoch(self, optimizer: torch.optim.Optimizer, batch_size: int) -> float:
        split, rollout = self.split, self.rollout
        n_train = split.train_x.shape[0]
        order = torch.randperm(n_train, generator=split.generator).to(split.device)
        torch.index_select(split.train_x, 0, order, out=self.epoch_x)
        torch.index_select(split.train_y, 0, order, out=self.epoch_y)
        total = torch.zeros((), device=split.device)
        if rollout is not None:
            rollout.start_epoch(self.windows)
        for i in range(0, n_train, batch_size):
            batch_x, batch_y = self.epoch_x[i : i + batch_size], self.epoch_y[i : i + batch_size]
            size = batch_x.shape[0]
            loss = self.loss.scaled_loss(batch_x, batch_y)
            total += loss.detach() * size
            if rollout is not None:
                multi = self.loss.multi_step_loss(*rollout.next_batch(size))
                rollout.record(multi, size)
                loss = loss + self.weight * multi
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        return float(total) / n_train

    def evaluate(self, postfix: dict[str, str]) -> float:
        h = self.history
        self.current = self._val_one_step()
        h.val_loss.append(self.current)
        postfix["val"] = f"{self.current:.4f}"
        if self.rollout is None:
            return self.current
        h.train_multi_step_loss.append(self.rollout.epoch_loss())
        h.val_multi_step_loss.append(self.rollout.val_loss(self.loss))
        postfix["train_k"] = f"{h.train_multi_step_loss[-1]:.4f}"
        postfix["val_k"] = f"{h.val_multi_step_loss[-1]:.4f}"
        return self._score(self.current, h.val_multi_step_loss[-1])

    def keep(self) -> None:
        self.best_one_step = self.current
        if self.rollout is not None:
            self.best_multi = self.history.val_multi_step_loss[-1]

    def finish(self) -> None:
        self.history.best_val_loss = self.best_one_step
        if self.rollout is not None:
            self.history.best_val_multi_step_loss = self.best_multi


class _Members:
    """``K`` stacked members, each on its own (bootstrap) sample in its own order."""

    desc = "ensemble"

    def __init__(self, model: DeltaDynamicsModel, split: FitSplit, *, bootstrap: bool):
        self.model, self.split = model, split
        k, n_train = model.num_members, split.train_x.shape[0]
        if bootstrap:
            samples = torch.randint(n_train, (k, n_train), generator=split.generator)
        else:
            samples = torch.arange(n_train).expand(k, n_train)
        ordered = samples.sort(dim=1).values
        distinct = 1 + (ordered[:, 1:] != ordered[:, :-1]).sum(1)
        self.samples = samples.to(split.device)
        self.history = EnsembleFitHistory(
            num_train=n_train,
            num_val=len(split.val_idx),
            num_members=k,
            bootstrap=bool(bootstrap),
            unique_fraction=(distinct / n_train).tolist(),
            val_indices=split.val_idx,
        )

    def _member_mse(self) -> torch.Tensor:
        """Held-out MSE ``[K]`` of every member's mean, in chunks (K copies of activations)."""
        inputs, targets = self.split.val_x, self.split.val_y
        n = inputs.shape[0]
        total = inputs.new_zeros(self.model.num_members)
        with torch.no_grad():
            for i in range(0, n, _EVAL_CHUNK):
                x, y = inputs[i : i + _EVAL_CHUNK], targets[i : i + _EVAL_CHUNK]
                total += self.model.member_mse(x, y) * x.shape[0]
        return total / n

    def initial(self) -> float:
        self.best_members = self._member_mse()
        return float(self.best_members.mean())

    def train_epoch(self, optimizer: torch.optim.Optimizer, batch_size: int) -> float:
        split, (k, n_train) = self.split, self.samples.shape
        # an independent random order of every member's sample: [K, n_train] row indices
        order = torch.rand(k, n_train, generator=split.generator).argsort(dim=1).to(split.device)
        rows = self.samples.gather(1, order)
        total = torch.zeros(k, device=split.device)
        for i in range(0, n_train, batch_size):
            idx = rows[:, i : i + batch_size]
            losses = self.model.member_loss(split.train_x[idx], split.train_y[idx])
            optimizer.zero_grad(set_to_none=True)
            losses.sum().backward()
            optimizer.step()
            total += losses.detach() * idx.shape[1]
        return float(total.mean()) / n_train

    def evaluate(self, postfix: dict[str, str]) -> float:
        self.current = self._member_mse()
        value = float(self.current.mean())
        self.history.val_loss.append(value)
        postfix["val"] = f"{value:.4f}"
        return value

    def keep(self) -> None:
        self.best_members = self.current

    def finish(self) -> None:
        self.history.best_val_loss = float(self.best_members.mean())
        self.history.member_val_loss = [float(v) for v in self.best_members]


def _early_stopping_loop(
    objective, model, optimizer, *, batch_size, max_epochs, patience, progress
):
    """Trains epochs until ``patience`` epochs bring no held-out improvement; keeps the best."""
    history = objective.history
    best = objective.initial()
    snapshot = StateSnapshot(model)
    bad_epochs = 0
    bar = tqdm(range(max_epochs), desc=objective.desc, unit="epoch", disable=not progress)
    for epoch in bar:
        train_loss = objective.train_epoch(optimizer, batch_size)
        history.train_loss.append(train_loss)
        postfix = {"train": f"{train_loss:.4f}"}
        criterion = objective.evaluate(postfix)
        bar.set_postfix(**postfix)
        if criterion < best:
            best, bad_epochs, history.best_epoch = criterion, 0, epoch
            objective.keep()
            snapshot.save()
        else:
            bad_epochs += 1
            if bad_epochs >= patience:
                history.stopped_early = epoch + 1 < max_epochs
                break
    bar.close()
    objective.finish()
    snapshot.restore()


def with_transition_keys(
    data: TransitionDataset | TensorDictBase,
    state_key: NestedKey | None = None,
    action_key: NestedKey | None = None,
    reward_key: NestedKey | None = None,
) -> TransitionDataset | TensorDictBase:
    """The transitions under the keys the fit reads, or an error naming a missing key.

    A :class:`~torchrl_mbmf.data.TransitionDataset` is read with its own keys: a key given
    here must be the dataset's. A TensorDict holding the transitions under other keys is
    returned as a view with ``state``, ``action``, ``("next", "state")`` and
    ``("next", "reward")`` (its done flags kept).

    Args:
        data: the transitions.
        state_key: the state's key, or ``None`` for ``"state"`` (a dataset: its own).
        action_key: the action's key, or ``None`` for ``"action"``.
        reward_key: the reward's key under ``"next"``, or ``None`` for ``"reward"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.world_model.fit import with_transition_keys
        >>> td = TensorDict(observation=torch.zeros(4, 3), action=torch.zeros(4, 1),
        ...                 next=TensorDict(observation=torch.ones(4, 3), reward=torch.ones(4, 1),
        ...                                 batch_size=[4]), batch_size=[4])
        >>> with_transition_keys(td, state_key="observation")["next", "state"].shape
        torch.Size([4, 3])
    """
    given = {"state_key": state_key, "action_key": action_key, "reward_key": reward_key}
    if isinstance(data, TransitionDataset):
        for name, key in given.items():
            if key is not None and key != getattr(data, name):
                raise ValueError(
                    f"{name}={key!r} but the dataset stores {getattr(data, name)!r}: build the "
                    f"dataset with {name}={key!r} (collect_random_transitions(..., "
                    f"{name}={key!r}))"
                )
        return data
    keys = {
        "state": state_key or "state",
        "action": action_key or "action",
        ("next", "state"): ("next", state_key or "state"),
        ("next", "reward"): ("next", reward_key or "reward"),
    }
    present = set(data.keys(True))
    missing = [key for key in keys.values() if key not in present]
    if missing:
        raise KeyError(
            f"the transitions have no {missing[0]!r} entry (state_key={state_key!r}, "
            f"action_key={action_key!r}, reward_key={reward_key!r}); they hold "
            f"{sorted(map(str, data.keys(True, True)))}"
        )
    if all(new == old for new, old in keys.items()):
        return data
    out = data.select(*data.keys(True, True))  # new containers: the caller's data is not changed
    for new, old in keys.items():
        out.set(new, data.get(old))
    return out


def fit_world_model(
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
    bootstrap: bool | None = None,
    state_key: NestedKey | None = None,
    action_key: NestedKey | None = None,
    reward_key: NestedKey | None = None,
) -> FitHistory | EnsembleFitHistory:
    """Fits a world model (one network or an ensemble) with Adam and early stopping.

    The one fitter behind :func:`fit_dynamics` (one network) and
    :func:`~torchrl_mbmf.world_model.ensemble_fit.fit_ensemble` (an ensemble, members on
    bootstrap resamples): the objective follows ``model.ensemble_size``. The best held-out
    weights are restored at the end. Design: ``docs/design/world_model_fit.md``.

    Args:
        model: the world model, trained in place.
        data: a :class:`~torchrl_mbmf.data.TransitionDataset` or a TensorDict of transitions.

    Keyword Args:
        lr: Adam learning rate (ignored when ``optimizer`` is given). Defaults to ``1e-4``.
        batch_size: minibatch size (per member for an ensemble). Defaults to ``512``.
        max_epochs: maximum number of passes over the training split. Defaults to ``200``.
        val_fraction: share of transitions held out for early stopping. Defaults to ``0.1``.
        patience: epochs without held-out improvement before stopping. Defaults to ``10``.
        fit_normalizer: refit the scaling statistics on the training split first.
            Defaults to ``True``.
        seed: seed of the split, the bootstrap indices and the minibatch order. Defaults to
            ``None``.
        progress: show a tqdm bar over epochs. Defaults to ``False``.
        optimizer: optimiser over ``model.parameters()`` to continue with (its state persists
            across refits). Defaults to a new stock Adam (:func:`dynamics_optimizer`).
        multi_step: length ``k`` of the open-loop rollouts of the multi-step term (one
            network only); ``1`` turns it off. Defaults to ``1``.
        multi_step_weight: weight of the multi-step term (``>= 0``; ignored when
            ``multi_step == 1``). Defaults to ``1.0``.
        early_stopping: held-out criterion of early stopping and of the kept weights,
            ``"objective"`` or ``"one_step"`` (the same when ``multi_step == 1``).
            Defaults to ``"objective"``.
        bootstrap: train each member of an ensemble on its own bootstrap resample of the
            training split (``False``: every member on the whole split). Defaults to
            ``None``: ``True`` for an ensemble; one network takes ``None`` or ``False``.
        state_key: key of the state in ``data`` (and, under ``"next"``, of the next state).
            Defaults to ``None``: a dataset's own key, ``"state"`` in a TensorDict.
        action_key: key of the action. Defaults to ``None`` (the dataset's, ``"action"``).
        reward_key: key of the reward under ``"next"``. Defaults to ``None`` (the
            dataset's, ``"reward"``).

    Returns:
        The :class:`FitHistory` (one network) or :class:`EnsembleFitHistory` (ensemble).

    Raises:
        ValueError: on NaN/Inf data, too little data or invalid settings (naming the
            argument), a multi-step term for an ensemble or ``bootstrap`` for one network.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.fit import fit_world_model
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 300, seed=0)
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=2, hidden_sizes=(16,))
        >>> history = fit_world_model(model, data, lr=1e-3, batch_size=64, max_epochs=2, seed=0)
        >>> type(history).__name__, history.num_members
        ('EnsembleFitHistory', 2)
    """
    check_fit_settings(val_fraction, batch_size, max_epochs, patience)
    data = with_transition_keys(data, state_key, action_key, reward_key)
    multi_step = check_multi_step(multi_step)
    multi_step_weight = check_multi_step_weight(multi_step_weight)
    early_stopping = check_early_stopping(early_stopping)
    members = getattr(model, "ensemble_size", 1) > 1
    if members and multi_step != 1:
        raise ValueError(f"multi_step={multi_step}: the multi-step term fits one network only")
    if not members and bootstrap:
        raise ValueError("bootstrap=True resamples per member: it needs an ensemble")
    start = time.perf_counter()
    split = split_for_fit(
        model,
        data,
        val_fraction=val_fraction,
        fit_normalizer=fit_normalizer,
        seed=seed,
        keep_tensors=multi_step > 1,
    )
    if members:
        objective = _Members(model, split, bootstrap=True if bootstrap is None else bootstrap)
    else:
        objective = _OneStep(
            model,
            data,
            split,
            seed=seed,
            multi_step=multi_step,
            weight=multi_step_weight,
            criterion=early_stopping,
        )
    if optimizer is None:
        optimizer = dynamics_optimizer(model, lr=lr)
    _early_stopping_loop(
        objective,
        model,
        optimizer,
        batch_size=batch_size,
        max_epochs=max_epochs,
        patience=patience,
        progress=progress,
    )
    history = objective.history
    history.seconds = time.perf_counter() - start
    _log(history)
    return history


def _log(history: FitHistory | EnsembleFitHistory) -> None:
    if isinstance(history, EnsembleFitHistory):
        logger.info(
            "fit_ensemble: %d members, %d epochs, best val loss %.5f at epoch %d (%.1fs)",
            history.num_members,
            history.epochs,
            history.best_val_loss,
            history.best_epoch,
            history.seconds,
        )
        return
    logger.info(
        "fit_dynamics: %d epochs, best val loss %.5f at epoch %d (%.1fs)",
        history.epochs,
        history.best_val_loss,
        history.best_epoch,
        history.seconds,
    )
    if history.multi_step > 1:
        logger.info(
            "fit_dynamics: %d-step loss (weight %g) on %d windows: train %.5f (last epoch), "
            "val %.5f (kept weights; early stopping on %s)",
            history.multi_step,
            history.multi_step_weight,
            history.num_windows,
            history.train_multi_step_loss[-1],
            history.best_val_multi_step_loss,
            history.early_stopping,
        )


def fit_dynamics_kwargs(world_model: Mapping[str, Any]) -> dict[str, Any]:
    """The keyword arguments of :func:`fit_dynamics` set by a ``world_model`` config node.

    ``multi_step``, ``multi_step_weight`` and ``early_stopping`` default to ``1``, ``1.0``
    and ``"objective"`` (the thesis' one-step fit) when a config predates them.

    Args:
        world_model: the ``world_model`` config (a ``DictConfig`` or a mapping).

    Returns:
        Keyword arguments for :func:`fit_dynamics` (add ``seed``, ``progress``, ``optimizer``).

    Raises:
        ValueError: naming ``world_model.multi_step``, ``world_model.multi_step_weight`` or
            ``world_model.early_stopping`` if it is invalid.

    Examples:
        >>> from torchrl_mbmf.world_model.fit import fit_dynamics_kwargs
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

    The thesis fit (table 7: Adam at lr 1e-4, batch 512, up to 200 epochs, early stopping on a
    held-out split), warm-started from the current weights. ``multi_step = k > 1`` adds the
    ``k``-step open-loop loss of windows of consecutive transitions of the training split;
    ``multi_step=1`` (the default) is bit-identical to the thesis fit. The split, the
    multi-step term and the early-stopping criterion: ``docs/design/world_model_fit.md``.

    Args:
        model: the world model, trained in place.
        data: a :class:`~torchrl_mbmf.data.TransitionDataset` or a TensorDict of transitions
            (``state``, ``action``, ``("next", "state")``, ``("next", "reward")``).

    Keyword Args:
        **kwargs: the settings of
            :func:`~torchrl_mbmf.world_model.fit.fit_world_model` (``lr``,
            ``batch_size``, ``max_epochs``, ``val_fraction``, ``patience``,
            ``fit_normalizer``, ``seed``, ``progress``, ``optimizer``, ``multi_step``,
            ``multi_step_weight``, ``early_stopping``, and the keys ``state_key``,
            ``action_key``, ``reward_key``), the thesis' values by default.

    Returns:
        The :class:`FitHistory`.

    Raises:
        ValueError: on NaN/Inf data, too little data, invalid settings (the message names the
            argument), or, with ``multi_step > 1``, no ``k``-step window in the training split.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model import fit_dynamics
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
            "torchrl_mbmf.world_model.ensemble_fit.fit_ensemble (or fit_world_model)"
        )
    return fit_world_model(model, data, **kwargs)
