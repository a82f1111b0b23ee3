"""A learned termination head: a classifier of terminal states for tasks without a known rule."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from torchrl_mbmf.modules.mlp import build_mlp, check_hidden_sizes


@dataclass
class TerminationFit:
    """What :meth:`LearnedTermination.fit` measured on its held-out split.

    Attributes:
        epochs: epochs run.
        val_accuracy: share of held-out states classified right.
        val_balanced_accuracy: mean of the held-out recall of terminal and of other states.
        val_terminal: held-out terminal states.
        val_size: held-out states.

    Examples:
        >>> from torchrl_mbmf.modules.termination import TerminationFit
        >>> TerminationFit(10, 0.98, 0.95, 12, 500).val_accuracy
        0.98
    """

    epochs: int
    val_accuracy: float
    val_balanced_accuracy: float
    val_terminal: int
    val_size: int


def classification_scores(predicted: torch.Tensor, target: torch.Tensor) -> dict[str, float]:
    """Accuracy, balanced accuracy, precision and recall of bool predictions.

    Args:
        predicted: predicted terminal flags ``[N]``.
        target: true terminal flags ``[N]``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.termination import classification_scores
        >>> scores = classification_scores(torch.tensor([True, False, False, False]),
        ...                                torch.tensor([True, True, False, False]))
        >>> scores["accuracy"], scores["recall"], scores["precision"]
        (0.75, 0.5, 1.0)
    """
    predicted, target = predicted.bool().flatten(), target.bool().flatten()
    tp = int((predicted & target).sum())
    tn = int((~predicted & ~target).sum())
    positives, negatives = int(target.sum()), int((~target).sum())
    recall = tp / positives if positives else 1.0
    specificity = tn / negatives if negatives else 1.0
    predicted_pos = int(predicted.sum())
    return {
        "accuracy": (tp + tn) / max(1, target.numel()),
        "balanced_accuracy": (recall + specificity) / 2,
        "precision": tp / predicted_pos if predicted_pos else 1.0,
        "recall": recall,
    }


class LearnedTermination(nn.Module):
    """``termination_fn`` learned from real transitions: ``p(terminated | s')`` > ``threshold``.

    For a task whose termination rule is not known, a small MLP on the standard-scaled next
    state is fitted to the real env's ``terminated`` flags (binary cross-entropy, terminal
    states up-weighted by the inverse of their share); called on states ``[..., state_dim]`` it
    returns the bool ``[...]`` a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` takes as its
    ``termination_fn``. Its scaling statistics are buffers, saved with its weights.

    Args:
        state_dim: size of the state.

    Keyword Args:
        hidden_sizes: hidden layer widths. Defaults to ``(64, 64)``.
        threshold: probability above which a state is terminal. Defaults to ``0.5``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.termination import LearnedTermination
        >>> states = torch.randn(2000, 3)
        >>> terminated = states[:, 0] > 1.0  # the rule to learn
        >>> head = LearnedTermination(3, hidden_sizes=(32,))
        >>> fit = head.fit(states, terminated, epochs=60, seed=0)
        >>> fit.val_accuracy > 0.9
        True
        >>> head(torch.tensor([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0]]))
        tensor([ True, False])
    """

    def __init__(
        self,
        state_dim: int,
        *,
        hidden_sizes: Sequence[int] = (64, 64),
        threshold: float = 0.5,
    ) -> None:
        super().__init__()
        if isinstance(state_dim, bool) or not isinstance(state_dim, int) or state_dim < 1:
            raise ValueError(f"state_dim must be an integer >= 1, got {state_dim!r}")
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"threshold must be in (0, 1), got {threshold!r}")
        self.state_dim = state_dim
        self.threshold = float(threshold)
        self.net = build_mlp(state_dim, check_hidden_sizes(hidden_sizes), 1, nn.ReLU)
        self.register_buffer("state_loc", torch.zeros(state_dim))
        self.register_buffer("state_scale", torch.ones(state_dim))

    def logits(self, state: torch.Tensor) -> torch.Tensor:
        """Logit of ``p(terminated)`` ``[...]`` of states ``[..., state_dim]``."""
        if state.shape[-1] != self.state_dim:
            raise ValueError(
                f"state has last dim {state.shape[-1]}, expected state_dim={self.state_dim}"
            )
        x = (state - self.state_loc) / self.state_scale
        return self.net(x)[..., 0]

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """Terminal flags ``[...]`` (bool) of states ``[..., state_dim]``."""
        with torch.no_grad():
            return torch.sigmoid(self.logits(state)) > self.threshold

    def fit(
        self,
        states: torch.Tensor,
        terminated: torch.Tensor,
        *,
        epochs: int = 100,
        lr: float = 1e-3,
        batch_size: int = 256,
        val_fraction: float = 0.1,
        seed: int = 0,
    ) -> TerminationFit:
        """Fits the head on next states and their ``terminated`` flags (a random split held out).

        Args:
            states: next states ``[N, state_dim]``.
            terminated: their terminal flags ``[N]`` (or ``[N, 1]``).

        Keyword Args:
            epochs: passes over the training split. Defaults to ``100``.
            lr: Adam learning rate. Defaults to ``1e-3``.
            batch_size: minibatch size. Defaults to ``256``.
            val_fraction: held-out share. Defaults to ``0.1``.
            seed: seed of the split and the minibatch order. Defaults to ``0``.

        Each call continues from the head's current weights (a refit on more data warm-starts)
        with a new Adam optimiser; the scaling statistics are those of the new training split.

        Returns:
            The held-out scores (:class:`TerminationFit`).

        Raises:
            ValueError: flags and states of different counts, fewer than two states, or a
                ``val_fraction`` outside (0, 1).
        """
        device = self.state_loc.device
        states = states.reshape(-1, self.state_dim).to(device, torch.float32)
        target = terminated.reshape(-1).to(device, torch.float32)
        if target.numel() != states.shape[0]:
            raise ValueError(f"terminated has {target.numel()} flags for {states.shape[0]} states")
        if not 0.0 < val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction!r}")
        g = torch.Generator().manual_seed(seed)  # on the CPU: the same split on any device
        order = torch.randperm(states.shape[0], generator=g).to(device)
        n_val = max(1, round(val_fraction * states.shape[0]))
        if states.shape[0] <= n_val:
            raise ValueError(
                f"fitting needs at least 2 states (one held out), got {states.shape[0]}"
            )
        val, train = order[:n_val], order[n_val:]
        with torch.no_grad():
            self.state_loc.copy_(states[train].mean(0))
            self.state_scale.copy_(states[train].std(0).clamp_min(1e-6))
        share = float(target[train].mean())
        pos_weight = torch.tensor((1 - share) / share if 0 < share < 1 else 1.0, device=device)
        loss_fn = nn.BCEWithLogitsLoss(pos_weight=pos_weight)
        opt = torch.optim.Adam(self.net.parameters(), lr=lr)
        for _ in range(epochs):
            perm = train[torch.randperm(train.numel(), generator=g).to(device)]
            for i in range(0, perm.numel(), batch_size):
                idx = perm[i : i + batch_size]
                loss = loss_fn(self.logits(states[idx]), target[idx])
                opt.zero_grad()
                loss.backward()
                opt.step()
        scores = classification_scores(self(states[val]), target[val].bool())
        return TerminationFit(
            epochs=epochs,
            val_accuracy=scores["accuracy"],
            val_balanced_accuracy=scores["balanced_accuracy"],
            val_terminal=int(target[val].sum()),
            val_size=int(n_val),
        )


__all__ = ["LearnedTermination", "TerminationFit", "classification_scores"]
