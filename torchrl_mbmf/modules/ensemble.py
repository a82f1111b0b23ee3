"""An ensemble of the thesis' world model, with all members in one batched tensor op."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import torch
from torch import nn

from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel, build_mlp, check_hidden_sizes
from torchrl_mbmf.modules.ensemble_layers import (
    EnsembleLinear,
    FusedEnsembleStep,
    member_as_single_model,
)


class EnsembleDeltaDynamicsModel(DeltaDynamicsModel):
    """``K`` independently initialised thesis world models evaluated as one batched network.

    Each member has the architecture of :class:`~torchrl_mbmf.modules.DeltaDynamicsModel`
    (``state_dim + action_dim -> hidden_sizes -> state_dim + 1``, ReLU hidden layers, linear
    output) and predicts the standard-scaled state delta and reward. The members' weights are
    stacked tensors ``[K, in, out]`` (:class:`EnsembleLinear`), so all members run in one
    ``torch.baddbmm`` per layer, never a Python loop over members. The standard-scaling buffers
    are shared by all members and set from data exactly as the single model's
    (:meth:`~torchrl_mbmf.modules.DeltaDynamicsModel.fit_normalizer`, inherited): inputs are
    ``(s - state_loc) / state_scale`` and ``(clip(a) - action_loc) / action_scale``, targets
    ``(s' - s - delta_loc) / delta_scale`` and ``(r - reward_loc) / reward_scale``.

    With ``probabilistic=True`` each member also outputs a log-variance per output (in scaled
    units), bounded to ``[min_log_var, max_log_var]`` (soft bounds as in PETS,
    ``lv = max - softplus(max - raw)`` then ``lv = min + softplus(lv - min)``, then a clamp that
    only removes the second softplus' tiny overshoot of ``max``), and
    :meth:`member_loss` is the Gaussian negative log-likelihood; by default the members are
    deterministic and trained with the MSE. Predictions in real units always use the members'
    means.

    **Disagreement.** :meth:`disagreement` of ``(s, a)`` is the mean over the ``state_dim``
    state dimensions of the standard deviation across the ``K`` members (population std,
    ``correction=0``) of the predicted *normalised* delta, ``(s'_k - s - delta_loc) /
    delta_scale``: ``mean_j std_k(delta_kj) / delta_scale_j``. It is 0 when all members agree
    (always for ``K = 1``) and unitless, so one threshold fits every state dimension. The reward
    is not part of it.

    **As a single model.** The class subclasses ``DeltaDynamicsModel``: ``forward(state,
    action)`` (and :meth:`predict_scaled`, :meth:`fused_step`, ``as_tensordict_module``) give
    the mean over members, or one member per batch row with ``member_index``, so the ensemble is
    accepted wherever a ``DeltaDynamicsModel`` makes a prediction, including
    :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` (which then steps the members' mean) and
    ``DynamicsLoss.forward`` (the mean's error). ``net`` is the stacked network, which maps
    ``[K, N, in]`` to ``[K, N, out]``; fit the ensemble with
    :func:`~torchrl_mbmf.trainers.ensemble_fit.fit_ensemble` (bootstrapped members), not with
    ``fit_dynamics``, which trains one network. :meth:`member` extracts one member as a plain
    ``DeltaDynamicsModel``. To roll each batch element in its own member and read the
    disagreement from the env, use :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv`.

    References: Chua et al., "Deep Reinforcement Learning in a Handful of Trials using
    Probabilistic Dynamics Models" (PETS), NeurIPS 2018; Kurutach et al., "Model-Ensemble
    Trust-Region Policy Optimization", ICLR 2018.

    Args:
        state_dim: size of the state (18 for the thesis' HalfCheetah state).
        action_dim: size of the action (6 for HalfCheetah).

    Keyword Args:
        num_members: ensemble size ``K``. Defaults to ``5``.
        hidden_sizes: hidden layer widths of every member. Defaults to ``(500, 500)``.
        activation: hidden activation class. Defaults to :class:`torch.nn.ReLU`.
        probabilistic: members output a mean and a bounded log-variance and train with the
            Gaussian NLL. Defaults to ``False`` (deterministic members, MSE).
        min_log_var: lower soft bound of the log-variance (scaled units). Defaults to
            ``-10.0``.
        max_log_var: upper soft bound of the log-variance (scaled units). Defaults to ``0.5``.
        action_low: lower clip of the action. Defaults to ``-1.0``.
        action_high: upper clip of the action. Defaults to ``1.0``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> model = EnsembleDeltaDynamicsModel(18, 6, num_members=5, hidden_sizes=(32, 32))
        >>> s, a = torch.randn(4, 18), torch.rand(4, 6) * 2 - 1
        >>> next_states, rewards = model.forward_members(s, a)
        >>> next_states.shape, rewards.shape
        (torch.Size([5, 4, 18]), torch.Size([5, 4, 1]))
        >>> model(s, a)[0].shape  # the members' mean, as a DeltaDynamicsModel
        torch.Size([4, 18])
        >>> own = model(s, a, member_index=torch.tensor([0, 1, 2, 3]))[0]
        >>> torch.allclose(own[2], next_states[2, 2], atol=1e-6)
        True
        >>> model.disagreement(s, a).shape
        torch.Size([4])
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        *,
        num_members: int = 5,
        hidden_sizes: Sequence[int] = (500, 500),
        activation: type[nn.Module] = nn.ReLU,
        probabilistic: bool = False,
        min_log_var: float = -10.0,
        max_log_var: float = 0.5,
        action_low: float = -1.0,
        action_high: float = 1.0,
    ) -> None:
        if isinstance(num_members, bool) or not isinstance(num_members, int) or num_members < 1:
            raise ValueError(f"num_members must be an integer >= 1, got {num_members!r}")
        hidden = check_hidden_sizes(hidden_sizes)
        if not min_log_var < max_log_var:
            raise ValueError(f"min_log_var={min_log_var} must be < max_log_var={max_log_var}")
        # The parent builds the scaling buffers; its single MLP is replaced by the stacked
        # members below (built with no hidden layer so no large layer is allocated for nothing).
        super().__init__(
            state_dim,
            action_dim,
            hidden_sizes=(),
            activation=activation,
            action_low=action_low,
            action_high=action_high,
        )
        self.hidden_sizes = hidden
        self.num_members = num_members
        self.probabilistic = bool(probabilistic)
        self.min_log_var = float(min_log_var)
        self.max_log_var = float(max_log_var)
        out = (state_dim + 1) * (2 if self.probabilistic else 1)
        self.net = build_mlp(
            state_dim + action_dim, hidden, out, activation, partial(EnsembleLinear, num_members)
        )

    @property
    def config(self) -> dict[str, object]:
        """Constructor arguments, used to check that a checkpoint matches this model."""
        return {
            **super().config,
            "num_members": self.num_members,
            "probabilistic": self.probabilistic,
            "min_log_var": self.min_log_var,
            "max_log_var": self.max_log_var,
        }

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
        if inputs.dim() == 2:
            inputs = inputs.expand(self.num_members, *inputs.shape)
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

    def predict_scaled(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Mean over members of the network output ``[..., state_dim + 1]`` (scaled units).

        Args:
            state: states ``[..., state_dim]``.
            action: actions ``[..., action_dim]``.
        """
        return self.predict_scaled_members(state, action)[0].mean(0)

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

    def _member_index(self, member_index: torch.Tensor, batch: torch.Size) -> torch.Tensor:
        member_index = torch.as_tensor(member_index)
        if member_index.dtype.is_floating_point or member_index.dtype == torch.bool:
            raise TypeError(f"member_index must hold integers, got dtype {member_index.dtype}")
        if member_index.shape != batch:
            raise ValueError(
                f"member_index has shape {tuple(member_index.shape)}, expected the batch shape "
                f"{tuple(batch)}"
            )
        if member_index.numel() and (
            int(member_index.min()) < 0 or int(member_index.max()) >= self.num_members
        ):
            raise ValueError(
                f"member_index values must be in [0, {self.num_members - 1}] "
                f"(num_members={self.num_members}), got min {int(member_index.min())} and max "
                f"{int(member_index.max())}"
            )
        return member_index

    def _select(self, members: torch.Tensor, member_index: torch.Tensor | None) -> torch.Tensor:
        """Mean over members (``None``) or member ``member_index[b]`` of every row ``b``."""
        if member_index is None:
            return members.mean(0)
        index = self._member_index(member_index, members.shape[1:-1]).to(members.device)
        index = index.unsqueeze(0).unsqueeze(-1).expand(1, *members.shape[1:])
        return members.gather(0, index).squeeze(0)

    def forward(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        member_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicts the next state ``[*B, state_dim]`` and reward ``[*B, 1]`` in real units.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.
            member_index: integers ``[*B]`` in ``[0, K)``: row ``b`` uses member
                ``member_index[b]``. Defaults to ``None``: the mean over members. All members
                are evaluated either way (one batched op), then the rows are picked.
        """
        return self.predict_with_disagreement(state, action, member_index)[:2]

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

        The mean over state dimensions of the standard deviation across members (population
        std) of the predicted normalised delta ``(s'_k - s - delta_loc) / delta_scale``; see
        the class docstring.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.
        """
        return self.disagreement_of_scaled(self.predict_scaled_members(state, action)[0])

    @staticmethod
    def cyclic_member_index(batch_shape: Sequence[int], num_members: int) -> torch.Tensor:
        """Member of every batch element when candidates are spread over the members.

        Element ``i`` along the last batch dim uses member ``i mod K`` (an unbatched element
        uses member 0): the convention of the ensemble planner and of
        :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv`.

        Args:
            batch_shape: the batch shape ``[*B]``.
            num_members: ``K``.

        Examples:
            >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
            >>> EnsembleDeltaDynamicsModel.cyclic_member_index((2, 4), 3)
            tensor([[0, 1, 2, 0],
                    [0, 1, 2, 0]])
        """
        shape = tuple(int(b) for b in batch_shape)
        if not shape:
            return torch.zeros((), dtype=torch.long)
        return (torch.arange(shape[-1]) % num_members).expand(shape)

    # ------------------------------------------------------------------------ training
    def member_loss(self, inputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Training loss of every member ``[K]`` on pre-scaled data.

        The mean over rows and outputs of the squared error (deterministic) or of the Gaussian
        negative log-likelihood ``0.5 * (log_var + (y - mean)^2 / exp(log_var))`` (constant
        dropped; ``probabilistic=True``). Summing it over members gives every member exactly
        the gradient of its own loss.

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

        The copy has the member's weights (its mean head) and the shared scaling statistics;
        it does not share memory with the ensemble.

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

    def fused_step(self) -> Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]:
        """A faster, inference-only ``forward`` (members' mean) with the scaling folded in.

        Returns:
            ``step(state, action) -> (next_state, reward)``, a snapshot of the current weights.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
            >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(8,))
            >>> s, a = torch.randn(5, 3), torch.randn(5, 1)
            >>> torch.allclose(model.fused_step()(s, a)[0], model(s, a)[0], atol=1e-5)
            True
        """
        return self.fused_members()


__all__ = ["EnsembleDeltaDynamicsModel", "EnsembleLinear", "FusedEnsembleStep"]
