"""The shooting planners' scoring stage: discounted return, terminal value, terminations."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_mbmf.modules.planners.stages import (
    counted_steps,
    discounted_return,
    terminated_return,
    truncated_return,
)


class CandidateScoring:
    """The scoring hooks of :class:`~torchrl_mbmf.modules.planners.ShootingPlanner`.

    A mixin: the planner sets ``value_module``, ``value_key``, ``discount``, ``state_key``
    and ``env``. :meth:`score_candidates` is the replaceable hook; the rest adapts what an
    overriding hook is called with. Why terminations cut the score is in
    ``docs/design/planners.md``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners.scoring import CandidateScoring
        >>> scoring = CandidateScoring()
        >>> scoring.value_module, scoring.discount = None, 0.5
        >>> scoring.score_candidates(torch.ones(1, 2, 3), None)
        tensor([[1.7500, 1.7500]])
    """

    # set by the planner (no class defaults: an nn.Module's submodule must not be shadowed)
    value_module: TensorDictModuleBase | None
    value_key: NestedKey
    discount: float

    def score_candidates(
        self,
        rewards: torch.Tensor,
        final: TensorDictBase | None,
        trusted_steps: torch.Tensor | None = None,
        terminated: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Candidate scores ``[*B, m]``: discounted return plus the optional terminal value.

        A candidate that reaches a terminal state scores the rewards up to and including
        that step, nothing after it and no terminal value
        (:func:`~torchrl_mbmf.modules.planners.terminated_return`). An overriding hook is
        called with the rewards after each candidate's terminal step zeroed (and, with an
        adaptive horizon, the steps counted up to that terminal step as ``trusted_steps``).

        Args:
            rewards: imagined rewards ``[*B, m, h]``.
            final: the learned env's observation entries at the last (trusted) imagined
                state, batch ``[*B, m]`` (``None`` when no score reads it).
            trusted_steps: each candidate's trusted steps ``[*B, m]``, or ``None`` for the
                whole horizon. Defaults to ``None``.
            terminated: whether each imagined step reached a terminal state ``[*B, m, h]``,
                or ``None`` when the env never terminates. Defaults to ``None``.
        """
        value = self.terminal_value(final) if self.value_module is not None else None
        if terminated is not None:
            return terminated_return(rewards, terminated, self.discount, value, trusted_steps)
        if trusted_steps is None:
            return discounted_return(rewards, self.discount, value)
        return truncated_return(rewards, trusted_steps, self.discount, value)

    def terminal_value(self, final: TensorDictBase) -> torch.Tensor:
        """``value_module``'s value ``[*B, m]`` at the last imagined state.

        Args:
            final: the learned env's observation entries there.
        """
        return self.value_module(final.copy()).get(self.value_key)[..., 0]

    def _final_entries(self, state: torch.Tensor) -> TensorDictBase:
        entries = {self.state_key: state}
        if self.env.observation_key is not None:
            entries[self.env.observation_key] = self.env.observation(state)
        return TensorDict(entries, batch_size=state.shape[:-1])

    def _reads_final(self) -> bool:
        # the stock score reads the last imagined state only for a terminal value
        stock = type(self).score_candidates is CandidateScoring.score_candidates
        return self.value_module is not None or not stock

    def _score(
        self,
        rewards: torch.Tensor,
        final: TensorDictBase | None,
        trusted_steps: torch.Tensor | None,
        terminated: torch.Tensor | None,
    ) -> torch.Tensor:
        if terminated is not None:
            if type(self).score_candidates is CandidateScoring.score_candidates:
                return self.score_candidates(rewards, final, trusted_steps, terminated)
            # an overridden hook sees the rewards after each candidate's terminal step zeroed
            # (and, when it is given trusted steps, the counted steps as those)
            counted, _ = counted_steps(terminated, trusted_steps)
            steps = torch.arange(rewards.shape[-1], device=rewards.device)
            rewards = rewards.masked_fill(steps >= counted.unsqueeze(-1), 0.0)
            if trusted_steps is not None:
                trusted_steps = counted
        if trusted_steps is None:  # the two-argument hook of planners that override it
            return self.score_candidates(rewards, final)
        return self.score_candidates(rewards, final, trusted_steps)


__all__ = ["CandidateScoring"]
