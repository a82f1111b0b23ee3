"""What every world-model fit shares: its data, its train/held-out split and its best weights."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from torchrl_mbmf.data.transitions import TransitionDataset, consecutive_windows, episode_ends
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.dynamics_loss import DynamicsLoss

__all__ = [
    "FitSplit",
    "MultiStepWindows",
    "StateSnapshot",
    "check_fit_settings",
    "seeded_generator",
    "split_for_fit",
    "transition_tensors",
    "transition_windows",
]


def transition_tensors(
    data: TransitionDataset | TensorDictBase,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``(state, action, next_state, reward)`` rows a world model is fitted on (float32).

    Args:
        data: a :class:`~torchrl_mbmf.data.TransitionDataset` or a TensorDict of transitions
            (``state``, ``action``, ``("next", "state")``, ``("next", "reward")``), any batch
            shape (flattened).

    Returns:
        ``state [N, S]``, ``action [N, A]``, ``next_state [N, S]`` and ``reward [N, 1]``.

    Raises:
        ValueError: naming the entry and the number of transitions with NaN or Inf.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.world_model.fit_data import transition_tensors
        >>> td = TensorDict(state=torch.zeros(4, 3), action=torch.zeros(4, 1),
        ...                 next=TensorDict(state=torch.ones(4, 3), reward=torch.ones(4),
        ...                                 batch_size=[4]), batch_size=[4])
        >>> [tuple(t.shape) for t in transition_tensors(td)]
        [(4, 3), (4, 1), (4, 3), (4, 1)]
    """
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


def seeded_generator(seed: int | None) -> torch.Generator:
    """A CPU generator seeded with ``seed`` (from system entropy when ``None``).

    Args:
        seed: the seed, or ``None``.

    Examples:
        >>> from torchrl_mbmf.world_model.fit_data import seeded_generator
        >>> seeded_generator(0).initial_seed()
        0
    """
    generator = torch.Generator()
    if seed is not None:
        generator.manual_seed(seed)
    else:
        generator.seed()
    return generator


@dataclass
class FitSplit:
    """The prologue of every fit: the split, the fitted scaler and the scaled pairs.

    Attributes:
        train_idx: rows of the training split.
        val_idx: rows of the held-out split.
        train_x: scaled inputs of the training split.
        train_y: scaled targets of the training split.
        val_x: scaled inputs of the held-out split.
        val_y: scaled targets of the held-out split.
        tensors: the raw ``(state, action, next_state, reward)`` on the model's device
            (kept only when asked for: multi-step rollouts rescale at every step).
        generator: the fit's generator, after the split was drawn.
        device: the model's device.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.world_model.fit_data import FitSplit
        >>> x = torch.zeros(4, 2)
        >>> FitSplit(torch.arange(3), torch.arange(3, 4), x[:3], x[:3], x[3:], x[3:], None,
        ...          torch.Generator(), torch.device("cpu")).val_x.shape
        torch.Size([1, 2])
    """

    train_idx: torch.Tensor
    val_idx: torch.Tensor
    train_x: torch.Tensor
    train_y: torch.Tensor
    val_x: torch.Tensor
    val_y: torch.Tensor
    tensors: list[torch.Tensor] | None
    generator: torch.Generator
    device: torch.device


def check_fit_settings(
    val_fraction: float, batch_size: int, max_epochs: int, patience: int
) -> None:
    """Raises a ``ValueError`` naming the first invalid fit setting.

    Args:
        val_fraction: held-out share, in ``(0, 1)``.
        batch_size: minibatch size, ``>= 1``.
        max_epochs: epoch cap, ``>= 1``.
        patience: early-stopping patience, ``>= 1``.

    Examples:
        >>> from torchrl_mbmf.world_model.fit_data import check_fit_settings
        >>> try:
        ...     check_fit_settings(1.5, 64, 10, 3)
        ... except ValueError as err:
        ...     print(err)
        val_fraction must be in (0, 1), got 1.5
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    if batch_size < 1 or max_epochs < 1 or patience < 1:
        raise ValueError(
            f"batch_size, max_epochs and patience must be >= 1, got {batch_size}, "
            f"{max_epochs}, {patience}"
        )


def split_for_fit(
    model: DeltaDynamicsModel,
    data: TransitionDataset | TensorDictBase,
    *,
    val_fraction: float,
    fit_normalizer: bool,
    seed: int | None,
    keep_tensors: bool = False,
) -> FitSplit:
    """Splits the transitions, fits the scaler on the training split and scales every row once.

    The split is the first ``torch.randperm`` of the fit's generator (``seed``): the first
    ``round(N * val_fraction)`` (at least 1) rows are held out.

    Args:
        model: the world model (single or ensemble).
        data: the transitions (see :func:`transition_tensors`).

    Keyword Args:
        val_fraction: held-out share.
        fit_normalizer: refit the scaling statistics on the training split.
        seed: seed of the fit's generator, or ``None``.
        keep_tensors: keep the raw tensors in :attr:`FitSplit.tensors`. Defaults to ``False``.

    Returns:
        The :class:`FitSplit`.

    Raises:
        ValueError: with too few transitions, or NaN/Inf in them.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.fit_data import split_for_fit
        >>> td = TensorDict(state=torch.randn(20, 3), action=torch.rand(20, 1),
        ...                 next=TensorDict(state=torch.randn(20, 3), reward=torch.randn(20),
        ...                                 batch_size=[20]), batch_size=[20])
        >>> split = split_for_fit(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), td,
        ...                       val_fraction=0.1, fit_normalizer=True, seed=0)
        >>> split.train_x.shape, split.val_y.shape
        (torch.Size([18, 4]), torch.Size([2, 4]))
    """
    state, action, next_state, reward = transition_tensors(data)
    n = state.shape[0]
    n_val = max(1, round(n * val_fraction))
    if n - n_val < 2:
        raise ValueError(f"need at least {n_val + 2} transitions to fit, got {n}")
    device = next(model.parameters()).device
    generator = seeded_generator(seed)
    perm = torch.randperm(n, generator=generator)
    val_idx, train_idx = perm[:n_val], perm[n_val:]
    tensors = [t.to(device) for t in (state, action, next_state, reward)]
    if fit_normalizer:
        model.fit_normalizer(*(t[train_idx] for t in tensors))
    # The scaler is fixed during the fit: scale everything once, then train on index slices.
    with torch.no_grad():
        inputs, targets = DynamicsLoss(model).scaled_pairs(*tensors)
    return FitSplit(
        train_idx,
        val_idx,
        inputs[train_idx],
        targets[train_idx],
        inputs[val_idx],
        targets[val_idx],
        tensors if keep_tensors else None,
        generator,
        device,
    )


class StateSnapshot:
    """A copy of a model's ``state_dict`` kept in preallocated tensors (the best epoch's).

    Args:
        model: the model whose state is kept (copied once at construction).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.world_model.fit_data import StateSnapshot
        >>> layer = torch.nn.Linear(2, 2)
        >>> snapshot = StateSnapshot(layer)
        >>> with torch.no_grad():
        ...     _ = layer.weight.add_(1.0)
        >>> snapshot.restore()
        >>> torch.equal(layer.weight, snapshot.saved["weight"])
        True
    """

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


def transition_windows(data: TransitionDataset | TensorDictBase, length: int) -> torch.Tensor:
    """``[W, length]`` row indices (rows of :func:`transition_tensors`) of episode windows.

    Args:
        data: a :class:`~torchrl_mbmf.data.TransitionDataset`, or a TensorDict ``[..., T]``
            whose last batch dim is time, with ``("next", "done")`` flags.
        length: window length ``k``.

    Raises:
        ValueError: when a TensorDict has no done flags.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.world_model.fit_data import transition_windows
        >>> s = torch.arange(4.0).unsqueeze(-1)
        >>> td = TensorDict(state=s, next=TensorDict(state=s + 1, done=torch.zeros(4, 1,
        ...                 dtype=torch.bool), batch_size=[4]), batch_size=[4]).unsqueeze(0)
        >>> transition_windows(td, 3)
        tensor([[0, 1, 2],
                [1, 2, 3]])
    """
    if isinstance(data, TransitionDataset):
        return data.windows(length)
    # A TensorDict [..., T]: time is its last batch dimension; episodes end at done steps.
    try:
        done = episode_ends(data)
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


class MultiStepWindows:
    """Windows of ``k`` consecutive transitions for the multi-step term of one fit.

    Windows wholly inside the training split are trained on; the others (holding at least one
    held-out transition) score the held-out multi-step loss.

    Args:
        data: the fitted transitions.
        length: window length ``k``.
        tensors: the raw ``(state, action, next_state, reward)`` rows.
        train_idx: rows of the training split.
        device: where the window indices live.

    Raises:
        ValueError: when no window lies in the training split.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.world_model.fit_data import MultiStepWindows, transition_tensors
        >>> s = torch.randn(10, 2)
        >>> td = TensorDict(state=s[:-1], action=torch.zeros(9, 1), next=TensorDict(
        ...     state=s[1:], reward=torch.zeros(9), done=torch.zeros(9, 1, dtype=torch.bool),
        ...     batch_size=[9]), batch_size=[9]).unsqueeze(0)
        >>> w = MultiStepWindows(td, 3, list(transition_tensors(td)), torch.arange(9), "cpu")
        >>> w.num_train, w.num_val
        (7, 0)
    """

    def __init__(
        self,
        data: TransitionDataset | TensorDictBase,
        length: int,
        tensors: list[torch.Tensor],
        train_idx: torch.Tensor,
        device: torch.device | str,
    ) -> None:
        self.state, self.action, self.next_state, self.reward = tensors
        windows = transition_windows(data, length)
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
