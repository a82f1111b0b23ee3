"""The member half of the world model: member outputs, disagreement, losses and extraction."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import nn

from torchrl_mbmf.modules.ensemble_layers import FusedEnsembleStep, member_as_single_model

if TYPE_CHECKING:
    from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel


def cyclic_member_index(batch_shape: Sequence[int], num_members: int) -> torch.Tensor:
    """Member of every batch element when candidates are spread over the members.

    Element ``i`` along the last batch dim uses member ``i mod K`` (an unbatched element
    uses member 0).

    Args:
        batch_shape: the batch shape ``[*B]``.
        num_members: ``K``.

    Examples:
        >>> from torchrl_mbmf.modules.members import cyclic_member_index
        >>> cyclic_member_index((2, 4), 3)
        tensor([[0, 1, 2, 0],
                [0, 1, 2, 0]])
    """
    shape = tuple(int(b) for b in batch_shape)
    if not shape:
        return torch.zeros((), dtype=torch.long)
    return (torch.arange(shape[-1]) % num_members).expand(shape)


def check_member_index(
    member_index: torch.Tensor, batch: torch.Size, num_members: int
) -> torch.Tensor:
    """Checks a member of every batch row: integers ``[*B]`` in ``[0, num_members)``.

    Args:
        member_index: the members.
        batch: the batch shape ``[*B]``.
        num_members: ``K``.

    Returns:
        ``member_index`` as a tensor.

    Raises:
        TypeError: for non-integer values.
        ValueError: for a wrong shape or a value outside ``[0, K)``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.members import check_member_index
        >>> check_member_index(torch.tensor([0, 2]), torch.Size([2]), 3)
        tensor([0, 2])
    """
    member_index = torch.as_tensor(member_index)
    if member_index.dtype.is_floating_point or member_index.dtype == torch.bool:
        raise TypeError(f"member_index must hold integers, got dtype {member_index.dtype}")
    if member_index.shape != batch:
        raise ValueError(
            f"member_index has shape {tuple(member_index.shape)}, expected the batch shape "
            f"{tuple(batch)}"
        )
    if member_index.numel() and (
        int(member_index.min()) < 0 or int(member_index.max()) >= num_members
    ):
        raise ValueError(
            f"member_index values must be in [0, {num_members - 1}] "
            f"(num_members={num_members}), got min {int(member_index.min())} and max "
            f"{int(member_index.max())}"
        )
    return member_index


class EnsembleMembers:
    """The methods of :class:`~torchrl_mbmf.modules.DeltaDynamicsModel` that see its members.

    A mixin of the one network ``net`` (member inputs ``[K, N, in]`` to member outputs
    ``[K, N, out]``): member outputs, the members' disagreement, per-member losses and
    single members. Every method works for every ``K`` (``K = 1`` is an ensemble of one).
    Design: ``docs/design/dynamics_model.md``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> model = EnsembleDeltaDynamicsModel(18, 6, num_members=5, hidden_sizes=(32, 32))
        >>> s, a = torch.randn(4, 18), torch.rand(4, 6) * 2 - 1
        >>> next_states, rewards = model.forward_members(s, a)
        >>> next_states.shape, rewards.shape
        (torch.Size([5, 4, 18]), torch.Size([5, 4, 1]))
        >>> model(s, a)[0].shape  # the members' mean
        torch.Size([4, 18])
        >>> own = model(s, a, member_index=torch.tensor([0, 1, 2, 3]))[0]
        >>> torch.allclose(own[2], next_states[2, 2], atol=1e-6)
        True
        >>> model.disagreement(s, a).shape
        torch.Size([4])
    """

    ensemble_size: int
    num_members: int
    state_dim: int
    probabilistic: bool
    min_log_var: float
    max_log_var: float
    net: nn.Module
    delta_scale: torch.Tensor

    # ------------------------------------------------------------------ member outputs
    def _split(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        d = self.state_dim + 1
        if not self.probabilistic:
            return raw, None
        mean, raw_lv = raw[..., :d], raw[..., d:]
        lv = self.max_log_var - nn.functional.softplus(self.max_log_var - raw_lv)
        lv = self.min_log_var + nn.functional.softplus(lv - self.min_log_var)
        # the soft bounds overshoot the upper one by at most log1p(exp(min - max)): make it exact
        return mean, lv.clamp(self.min_log_var, self.max_log_var)

    def members_from_scaled(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Member outputs in scaled units from scaled inputs.

        Args:
            inputs: ``[N, in]`` (shared by all members) or ``[K, N, in]`` (one set per member).

        Returns:
            ``(mean, log_var)``, each ``[K, N, state_dim + 1]`` (scaled delta then scaled
            reward); ``log_var`` is ``None`` for a deterministic ensemble.
        """
        k = self.ensemble_size
        if inputs.dim() == 3 and inputs.shape[0] != k:
            raise ValueError(
                f"member inputs must be [N, in] or [K={k}, N, in], got {tuple(inputs.shape)}"
            )
        if k == 1:  # the one network's nn.Linear layers
            out = self.net(inputs)
            return self._split(out.unsqueeze(0) if inputs.dim() == 2 else out)
        if inputs.dim() == 2:
            inputs = inputs.expand(k, *inputs.shape)
        return self._split(self.net(inputs))

    def predict_scaled_members(
        self, state: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Every member's output in scaled units, for a batch ``[*B]`` shared by all members.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.

        Returns:
            ``(mean, log_var)``, each ``[K, *B, state_dim + 1]`` (scaled delta then scaled
            reward); ``log_var`` is ``None`` for a deterministic ensemble.
        """
        x = self.scaled_inputs(state, action)
        batch = x.shape[:-1]
        mean, lv = self.members_from_scaled(x.reshape(-1, x.shape[-1]))
        shape = (self.num_members, *batch, self.state_dim + 1)
        return mean.reshape(shape), None if lv is None else lv.reshape(shape)

    def forward_members(
        self, state: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Every member's prediction in real units.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.

        Returns:
            ``(next_state [K, *B, state_dim], reward [K, *B, 1])``.
        """
        return self.unscale(state, self.predict_scaled_members(state, action)[0])

    def check_member_index(self, member_index: torch.Tensor, batch: torch.Size) -> torch.Tensor:
        """Checks a member of every batch row (see :func:`check_member_index`).

        Args:
            member_index: the members.
            batch: the batch shape ``[*B]``.
        """
        return check_member_index(member_index, batch, self.num_members)

    def _select(self, members: torch.Tensor, member_index: torch.Tensor | None) -> torch.Tensor:
        """Mean over members (``None``) or member ``member_index[b]`` of every row ``b``."""
        if member_index is None:
            return members.mean(0)
        index = self.check_member_index(member_index, members.shape[1:-1]).to(members.device)
        index = index.unsqueeze(0).unsqueeze(-1).expand(1, *members.shape[1:])
        return members.gather(0, index).squeeze(0)

    def predict_with_disagreement(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        member_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`forward` and :meth:`disagreement` from one pass through the members.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.
            member_index: member of every row ``[*B]``, or ``None`` for the mean. Defaults to
                ``None``.

        Returns:
            ``(next_state [*B, state_dim], reward [*B, 1], disagreement [*B])``.
        """
        mean = self.predict_scaled_members(state, action)[0]
        disagreement = self.disagreement_of_scaled(mean)
        next_state, reward = self.unscale(state, self._select(mean, member_index))
        return next_state, reward, disagreement

    def disagreement_of_scaled(self, members: torch.Tensor) -> torch.Tensor:
        """Disagreement ``[*B]`` of member outputs ``[K, *B, >= state_dim]`` in scaled units.

        ``mean_j std_k(members[k, ..., j])`` over the first ``state_dim`` outputs (the scaled
        delta), with the population std (``correction=0``).

        Args:
            members: member outputs, scaled delta first (as :meth:`predict_scaled_members`).
        """
        return members[..., : self.state_dim].std(0, correction=0).mean(-1)

    def disagreement(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Epistemic disagreement of the members at ``(state, action)``, ``[*B]``.

        The mean over state dimensions of the members' population std of the predicted
        normalised delta ``(s'_k - s - delta_loc) / delta_scale`` (Kurutach et al., 2018).

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.
        """
        return self.disagreement_of_scaled(self.predict_scaled_members(state, action)[0])

    cyclic_member_index = staticmethod(cyclic_member_index)

    # ------------------------------------------------------------------------ training
    def member_loss(self, inputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Training loss of every member ``[K]`` on pre-scaled data.

        The mean over rows and outputs of the squared error, or of the Gaussian negative
        log-likelihood (constant dropped) when ``probabilistic=True``.

        Args:
            inputs: scaled inputs ``[N, in]`` (shared) or ``[K, N, in]`` (per member), as
                ``DynamicsLoss.scaled_pairs`` makes them.
            targets: scaled targets ``[N, state_dim + 1]`` or ``[K, N, state_dim + 1]``.
        """
        mean, lv = self.members_from_scaled(inputs)
        sq = (mean - targets).pow(2)
        if lv is None:
            return sq.mean((-2, -1))
        return (0.5 * (lv + sq * torch.exp(-lv))).mean((-2, -1))

    def member_mse(self, inputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Squared error of every member's mean ``[K]`` on pre-scaled data (the held-out metric).

        Args:
            inputs: scaled inputs ``[N, in]`` or ``[K, N, in]``.
            targets: scaled targets ``[N, state_dim + 1]`` or ``[K, N, state_dim + 1]``.
        """
        mean, _ = self.members_from_scaled(inputs)
        return (mean - targets).pow(2).mean((-2, -1))

    # ------------------------------------------------------------------ single members
    @torch.no_grad()
    def member(self, k: int) -> DeltaDynamicsModel:
        """Member ``k`` as a standalone :class:`~torchrl_mbmf.modules.DeltaDynamicsModel`.

        A copy (no shared memory) with the member's mean head and the scaling statistics.

        Args:
            k: member index in ``[0, K)``.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
            >>> ens = EnsembleDeltaDynamicsModel(3, 1, num_members=2, hidden_sizes=(8,))
            >>> s, a = torch.randn(5, 3), torch.randn(5, 1)
            >>> torch.allclose(ens.member(1)(s, a)[0], ens.forward_members(s, a)[0][1])
            True
        """
        return member_as_single_model(self, k)

    # ------------------------------------------------------------------ fast inference
    def fused_members(self) -> FusedEnsembleStep:
        """An inference-only snapshot of the members with the scaling folded into the weights.

        Returns:
            A :class:`FusedEnsembleStep` (rebuild it after the weights or scaling change).

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
            >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(8,))
            >>> s, a = torch.randn(5, 3), torch.randn(5, 1)
            >>> out = model.fused_members().members(s, a)  # real delta and reward
            >>> torch.allclose(s + out[..., :3], model.forward_members(s, a)[0], atol=1e-5)
            True
        """
        return FusedEnsembleStep(self)


__all__ = ["EnsembleMembers", "check_member_index", "cyclic_member_index"]
