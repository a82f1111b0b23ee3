"""The named stages of a shooting plan: expand, score, select, gather, and the plan record."""

from __future__ import annotations

from dataclasses import dataclass

import torch


def expand_candidates(x: torch.Tensor, num_candidates: int) -> torch.Tensor:
    """Repeats a batch of vectors ``[*B, d]`` as ``[*B, m, d]`` candidates (a view, no copy).

    Args:
        x: real states or observations ``[*B, d]``.
        num_candidates: ``m``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import expand_candidates
        >>> expand_candidates(torch.zeros(4, 3), 15).shape
        torch.Size([4, 15, 3])
    """
    return x.unsqueeze(-2).expand(*x.shape[:-1], num_candidates, x.shape[-1])


def discounted_return(
    rewards: torch.Tensor,
    discount: float = 1.0,
    terminal_value: torch.Tensor | None = None,
) -> torch.Tensor:
    """``sum_t discount**t * r_t (+ discount**h * V(s_h))`` over the last dim of ``rewards``.

    Args:
        rewards: imagined rewards ``[*B, m, h]``.
        discount: per-step discount. Defaults to ``1.0`` (the thesis' plain sum).
        terminal_value: value of the last imagined state ``[*B, m]``. Defaults to none.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import discounted_return
        >>> discounted_return(torch.tensor([[1.0, 1.0, 1.0]]), 0.5, torch.tensor([8.0]))
        tensor([2.7500])
    """
    h = rewards.shape[-1]
    if discount == 1.0:
        total = rewards.sum(-1)
    else:
        weights = discount ** torch.arange(h, dtype=rewards.dtype, device=rewards.device)
        total = (rewards * weights).sum(-1)
    if terminal_value is not None:
        total = total + discount**h * terminal_value
    return total


def truncated_return(
    rewards: torch.Tensor,
    trusted_steps: torch.Tensor,
    discount: float = 1.0,
    terminal_value: torch.Tensor | None = None,
) -> torch.Tensor:
    """``sum_{t < T} discount**t * r_t (+ discount**T * V(s_T))`` with ``T = trusted_steps``.

    The score of an adaptive horizon: the rewards from each candidate's first untrusted step
    on are dropped, and the terminal value (of the last trusted state) is discounted by the
    candidate's own ``T``.

    Args:
        rewards: imagined rewards ``[*B, m, h]``.
        trusted_steps: ``T`` of every candidate ``[*B, m]``.
        discount: per-step discount. Defaults to ``1.0``.
        terminal_value: value of every candidate's last trusted state ``[*B, m]``. Defaults
            to none.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import truncated_return
        >>> truncated_return(torch.ones(1, 3), torch.tensor([2]), 0.5, torch.tensor([8.0]))
        tensor([3.5000])
    """
    steps = torch.arange(rewards.shape[-1], device=rewards.device)
    kept = rewards.masked_fill(steps >= trusted_steps.unsqueeze(-1), 0.0)
    total = discounted_return(kept, discount)
    if terminal_value is not None:
        if discount != 1.0:
            power = torch.pow(discount, trusted_steps.to(terminal_value.dtype))
            terminal_value = terminal_value * power
        total = total + terminal_value
    return total


def counted_steps(
    terminated: torch.Tensor, trusted_steps: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps counted in each candidate's score and whether it ended at a terminal state.

    A candidate's score counts its steps up to and including its first terminal step (and no
    more than its ``trusted_steps``); it *ended* when that terminal step is among the counted
    ones (then no terminal value is added).

    Args:
        terminated: whether each imagined step reached a terminal state ``[*B, m, h]``.
        trusted_steps: each candidate's trusted steps ``[*B, m]``, or ``None`` for all ``h``.
            Defaults to ``None``.

    Returns:
        ``(steps [*B, m], ended [*B, m])``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import counted_steps
        >>> done = torch.tensor([[False, True, False], [False, False, False]])
        >>> counted_steps(done)
        (tensor([2, 3]), tensor([ True, False]))
        >>> counted_steps(done, torch.tensor([1, 2]))
        (tensor([1, 2]), tensor([False, False]))
    """
    h = terminated.shape[-1]
    ever = terminated.any(-1)
    first = terminated.to(torch.int8).argmax(-1)  # the first True (0 when none)
    steps = torch.where(ever, first + 1, torch.full_like(first, h))
    if trusted_steps is None:
        return steps, ever
    ended = ever & (first < trusted_steps)
    return torch.minimum(steps, trusted_steps.to(steps.dtype)), ended


def terminated_return(
    rewards: torch.Tensor,
    terminated: torch.Tensor,
    discount: float = 1.0,
    terminal_value: torch.Tensor | None = None,
    trusted_steps: torch.Tensor | None = None,
) -> torch.Tensor:
    """The score of candidates that may reach terminal states.

    ``sum_{t <= k} discount**t * r_t`` for a candidate whose first terminal step is ``k``
    (that step's reward counted, nothing after it, no terminal value); a candidate that
    does not terminate scores as :func:`truncated_return` (``trusted_steps``, or the whole
    horizon, plus the discounted terminal value).

    Args:
        rewards: imagined rewards ``[*B, m, h]``.
        terminated: whether each imagined step reached a terminal state ``[*B, m, h]``.
        discount: per-step discount. Defaults to ``1.0``.
        terminal_value: value of every candidate's last (trusted) state ``[*B, m]``.
            Defaults to none.
        trusted_steps: each candidate's trusted steps ``[*B, m]``. Defaults to all ``h``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import terminated_return
        >>> rewards = torch.ones(2, 4)
        >>> done = torch.tensor([[True, False, False, False], [False] * 4])
        >>> terminated_return(rewards, done, terminal_value=torch.tensor([100.0, 100.0]))
        tensor([  1., 104.])
    """
    steps, ended = counted_steps(terminated, trusted_steps)
    if terminal_value is not None:
        terminal_value = terminal_value.masked_fill(ended, 0.0)
    return truncated_return(rewards, steps, discount, terminal_value)


def select_best(returns: torch.Tensor) -> torch.Tensor:
    """Index of the highest-scoring candidate along the last dim (first one on ties).

    Args:
        returns: candidate scores ``[*B, m]``.

    Returns:
        ``[*B]`` indices.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import select_best
        >>> select_best(torch.tensor([[1.0, 3.0, 3.0]]))
        tensor([1])
    """
    return returns.argmax(-1)


def gather_candidate(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Picks candidate ``index[b]`` of every batch element: ``[*B, m, d]`` -> ``[*B, d]``.

    Args:
        x: per-candidate vectors ``[*B, m, d]``.
        index: ``[*B]`` candidate indices.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import gather_candidate
        >>> gather_candidate(torch.arange(6.0).reshape(1, 3, 2), torch.tensor([2]))
        tensor([[4., 5.]])
    """
    idx = index[..., None, None].expand(*index.shape, 1, x.shape[-1])
    return x.gather(-2, idx).squeeze(-2)


@dataclass
class Plan:
    """The outcome of one planning call, with the statistics it writes.

    Attributes:
        first_actions: first action of every candidate ``[*B, m, action_dim]``.
        returns: score of every candidate ``[*B, m]``.
        best: index of the chosen candidate ``[*B]``.
        trusted_steps: imagined steps counted in every candidate's score ``[*B, m]``, or
            ``None`` when every candidate counts the whole horizon (no adaptive horizon).
        disagreement: the members' disagreement at every candidate's imagined ``(s, a)``
            ``[*B, m, h]``, or ``None`` when it was not computed.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import Plan
        >>> plan = Plan(torch.zeros(2, 3, 1), torch.tensor([[0., 2., 1.], [3., 0., 0.]]),
        ...             torch.tensor([1, 0]))
        >>> plan.action.shape
        torch.Size([2, 1])
        >>> plan.statistics()["best_return"]
        tensor([[2.],
                [3.]])
    """

    first_actions: torch.Tensor
    returns: torch.Tensor
    best: torch.Tensor
    trusted_steps: torch.Tensor | None = None
    disagreement: torch.Tensor | None = None

    @property
    def action(self) -> torch.Tensor:
        """First action of the best candidate ``[*B, action_dim]``."""
        return gather_candidate(self.first_actions, self.best)

    @property
    def effective_horizon(self) -> torch.Tensor:
        """Trusted steps of the chosen candidate ``[*B]`` (needs ``trusted_steps``)."""
        if self.trusted_steps is None:
            raise ValueError("this plan has no trusted_steps (it used the whole horizon)")
        return self.trusted_steps.gather(-1, self.best.unsqueeze(-1)).squeeze(-1)

    def statistics(self) -> dict[str, torch.Tensor]:
        """The plan's statistics, each ``[*B, 1]``.

        ``best_return`` and ``mean_return`` of the candidates; with ``trusted_steps`` also
        ``effective_horizon`` (the chosen candidate's trusted steps) and, with
        ``disagreement``, its mean over all candidates and imagined steps.
        """
        returns = self.returns
        stats = {
            "best_return": returns.amax(-1, keepdim=True),
            "mean_return": returns.mean(-1, keepdim=True),
        }
        if self.trusted_steps is not None:
            horizon = self.effective_horizon.to(returns.dtype).unsqueeze(-1)
            stats["effective_horizon"] = horizon
        if self.disagreement is not None:
            mean = self.disagreement.mean((-2, -1)).unsqueeze(-1)
            stats["disagreement"] = mean.to(returns.dtype)
        return stats


__all__ = [
    "Plan",
    "counted_steps",
    "discounted_return",
    "expand_candidates",
    "gather_candidate",
    "select_best",
    "terminated_return",
    "truncated_return",
]
