"""The world model's standard scaling: its statistics, the (un)scaling, and the one fold."""

from __future__ import annotations

from collections.abc import Sequence

import torch

_MIN_SCALE = 1e-6


class StandardScaling:
    """The scaling half of :class:`~torchrl_mbmf.modules.DeltaDynamicsModel`, in one place.

    Inputs are ``(s - state_loc) / state_scale`` and ``(clip(a) - action_loc) /
    action_scale``, targets ``(s' - s - delta_loc) / delta_scale`` and ``(r - reward_loc) /
    reward_scale``; the statistics are buffers of the model (shared by all its members) set by
    :meth:`fit_normalizer`. :meth:`fold_scaling` folds them into a chain of linear layers: the
    one fold every fast path (fused steps, cached planner steps, fused ensemble members) uses.
    A mixin: the model defines ``state_dim``, ``action_dim``, ``action_low``, ``action_high``
    and registers the buffers with ``_register_scaling_buffers``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,), action_low=-1.0, action_high=1.0)
        >>> s, a = torch.zeros(2, 3), torch.full((2, 1), 5.0)
        >>> model.scaled_inputs(s, a)[0, -1]  # the action is clipped to 1 first
        tensor(1.)
    """

    state_dim: int
    action_dim: int
    action_low: float
    action_high: float
    state_loc: torch.Tensor
    state_scale: torch.Tensor
    action_loc: torch.Tensor
    action_scale: torch.Tensor
    delta_loc: torch.Tensor
    delta_scale: torch.Tensor
    reward_loc: torch.Tensor
    reward_scale: torch.Tensor
    normalizer_fitted: torch.Tensor

    def _register_scaling_buffers(self) -> None:
        """Registers the statistics as buffers (identity scaling until fitted)."""
        register = self.register_buffer  # type: ignore[attr-defined]  # an nn.Module's
        dims = (("state", self.state_dim), ("action", self.action_dim), ("delta", self.state_dim))
        for name, dim in dims:
            register(f"{name}_loc", torch.zeros(dim))
            register(f"{name}_scale", torch.ones(dim))
        register("reward_loc", torch.zeros(1))
        register("reward_scale", torch.ones(1))
        register("normalizer_fitted", torch.zeros((), dtype=torch.bool))

    def _check(self, state: torch.Tensor, action: torch.Tensor) -> None:
        if state.shape[-1] != self.state_dim:
            raise ValueError(
                f"state has last dim {state.shape[-1]}, expected state_dim={self.state_dim}"
            )
        if action.shape[-1] != self.action_dim:
            raise ValueError(
                f"action has last dim {action.shape[-1]}, expected action_dim={self.action_dim}"
            )
        if state.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"state batch {tuple(state.shape[:-1])} and action batch "
                f"{tuple(action.shape[:-1])} differ"
            )
        model = self.state_loc.dtype
        for name, value in (("state", state), ("action", action)):
            if torch.promote_types(value.dtype, model) != model:
                raise ValueError(
                    f"{name} is {value.dtype}, the model is {model}: convert the inputs (a "
                    "float64 env: torchrl's DoubleToFloat transform) or the model"
                )

    @torch.no_grad()
    def fit_normalizer(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        next_state: torch.Tensor,
        reward: torch.Tensor,
    ) -> None:
        """Sets the standard-scaling statistics from transitions (thesis section 4.2).

        Args:
            state: states ``[N, state_dim]``.
            action: actions ``[N, action_dim]`` (clipped before the statistics are taken).
            next_state: next states ``[N, state_dim]``.
            reward: rewards ``[N]`` or ``[N, 1]``.

        Raises:
            ValueError: on wrong sizes, fewer than 2 transitions, or non-finite values.
        """
        self._check(state, action)
        if next_state.shape != state.shape or reward.numel() != state[..., 0].numel():
            raise ValueError(
                f"next_state {tuple(next_state.shape)} must have the state's shape "
                f"{tuple(state.shape)} and reward {tuple(reward.shape)} one value per transition"
            )
        reward = reward.reshape(*state.shape[:-1], 1)
        state = state.reshape(-1, self.state_dim)
        if state.shape[0] < 2:
            raise ValueError(f"need at least 2 transitions to fit the scaler, got {state.shape[0]}")
        action = self.clip_action(action.reshape(-1, self.action_dim))
        delta = next_state.reshape(-1, self.state_dim) - state
        reward = reward.reshape(-1, 1)
        for name, value in (
            ("state", state),
            ("action", action),
            ("delta", delta),
            ("reward", reward),
        ):
            if not torch.isfinite(value).all():
                raise ValueError(f"{name} contains NaN or Inf; refusing to fit the scaler")
            loc = value.mean(0)
            scale = value.std(0).clamp_min(_MIN_SCALE)
            getattr(self, f"{name}_loc").copy_(loc)
            getattr(self, f"{name}_scale").copy_(scale)
        self.normalizer_fitted.fill_(True)

    def clip_action(self, action: torch.Tensor) -> torch.Tensor:
        """Clips the action to ``[action_low, action_high]`` (unchanged without bounds)."""
        return action.clamp(self.action_low, self.action_high)

    def scaled_inputs(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Standard-scaled network inputs ``[..., state_dim + action_dim]`` (action clipped).

        Args:
            state: states ``[..., state_dim]``.
            action: actions ``[..., action_dim]``.
        """
        self._check(state, action)
        return torch.cat(
            [
                (state - self.state_loc) / self.state_scale,
                (self.clip_action(action) - self.action_loc) / self.action_scale,
            ],
            -1,
        )

    def scale_targets(
        self, state: torch.Tensor, next_state: torch.Tensor, reward: torch.Tensor
    ) -> torch.Tensor:
        """Training targets ``[..., state_dim + 1]`` in the network's scaled units."""
        delta = (next_state - state - self.delta_loc) / self.delta_scale
        reward = reward.reshape(*state.shape[:-1], 1)
        return torch.cat([delta, (reward - self.reward_loc) / self.reward_scale], -1)

    def unscale(
        self, state: torch.Tensor, output: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Maps a network output to (next state, reward) in real units."""
        delta = output[..., : self.state_dim] * self.delta_scale + self.delta_loc
        reward = output[..., self.state_dim :] * self.reward_scale + self.reward_loc
        return state + delta, reward

    @torch.no_grad()
    def fold_scaling(
        self, weights: Sequence[torch.Tensor], biases: Sequence[torch.Tensor]
    ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Folds the scaling into a chain of linear layers: the one fold of every fast path.

        The input standardisation goes into the first layer (it then reads the raw
        ``[state, clipped action]``) and the output un-scaling into the last one (it then
        writes the real ``[delta, reward]``); the layers in between are unchanged. Works on
        ``nn.Linear`` weights ``[out, in]`` and on stacked member weights ``[K, in, out]``.

        Args:
            weights: the linear layers' weights, first to last (one entry: first is last).
            biases: their biases, ``[out]`` or ``[K, out]``.

        Returns:
            New ``(weights, biases)`` lists; the given tensors are not modified.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> model = DeltaDynamicsModel(3, 1, hidden_sizes=())
            >>> model.state_scale.fill_(2.0)
            tensor([2., 2., 2.])
            >>> (w,), (b,) = model.fold_scaling([model.net[0].weight], [model.net[0].bias])
            >>> s, a = torch.randn(5, 3), torch.rand(5, 1) * 2 - 1
            >>> delta = torch.nn.functional.linear(torch.cat([s, a], -1), w, b)[:, :3]
            >>> torch.allclose(s + delta, model(s, a)[0], atol=1e-6)
            True
        """
        weights, biases = list(weights), list(biases)
        in_loc = torch.cat([self.state_loc, self.action_loc])
        in_scale = torch.cat([self.state_scale, self.action_scale])
        out_loc = torch.cat([self.delta_loc, self.reward_loc])
        out_scale = torch.cat([self.delta_scale, self.reward_scale])
        if weights[0].dim() == 3:  # stacked members [K, in, out]
            weights[0] = weights[0] / in_scale[:, None]
            biases[0] = biases[0] - torch.einsum("i,kio->ko", in_loc, weights[0])
            weights[-1] = weights[-1] * out_scale
        else:
            weights[0] = weights[0] / in_scale
            biases[0] = biases[0] - weights[0] @ in_loc
            weights[-1] = weights[-1] * out_scale[:, None]
        biases[-1] = biases[-1] * out_scale + out_loc
        return weights, biases


__all__ = ["StandardScaling"]
