"""The world model: one delta+reward MLP of ``ensemble_size`` members (1 = the thesis model)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from torchrl_mbmf.checks import check_number
from torchrl_mbmf.modules.ensemble_layers import EnsembleLinear
from torchrl_mbmf.modules.members import EnsembleMembers
from torchrl_mbmf.modules.mlp import build_mlp, check_hidden_sizes
from torchrl_mbmf.modules.scaling import StandardScaling


def _check_arguments(
    state_dim: int,
    action_dim: int,
    ensemble_size: int,
    probabilistic: bool,
    log_var_bounds: tuple[float, float],
    action_bounds: tuple[float | None, float | None],
) -> tuple[int, float, float]:
    """Checks :class:`DeltaDynamicsModel`'s arguments; returns ``K`` and the action clip."""
    k = check_number(ensemble_size, "ensemble_size", minimum=1, integer=True)
    check_number(state_dim, "state_dim", minimum=1, integer=True)
    check_number(action_dim, "action_dim", minimum=1, integer=True)
    action_low, action_high = action_bounds
    for name, bound in (("action_low", action_low), ("action_high", action_high)):
        number = isinstance(bound, int | float) and not isinstance(bound, bool)
        if bound is not None and not (number and not math.isnan(bound)):
            raise ValueError(f"{name} must be a number or None (no clip), got {bound!r}")
    low = -math.inf if action_low is None else float(action_low)
    high = math.inf if action_high is None else float(action_high)
    if not low < high:
        raise ValueError(f"action_low={action_low} must be < action_high={action_high}")
    min_log_var, max_log_var = log_var_bounds
    if not min_log_var < max_log_var:
        raise ValueError(f"min_log_var={min_log_var} must be < max_log_var={max_log_var}")
    if probabilistic and k == 1:
        raise ValueError(
            "probabilistic=True needs ensemble_size >= 2 (Gaussian members are trained by "
            "fit_ensemble); the one network (ensemble_size=1) is deterministic"
        )
    return k, low, high


def _build_network(
    n_in: int,
    n_out: int,
    hidden_sizes: tuple[int, ...],
    activation: type[nn.Module],
    k: int,
    probabilistic: bool,
) -> nn.Sequential:
    """The one network (``K = 1``, ``nn.Linear`` layers) or ``K`` stacked members."""
    if k == 1:
        return build_mlp(n_in, hidden_sizes, n_out, activation)
    # Drawn and dropped so that a seed gives the members the initial weights it gave when the
    # ensemble was a subclass that first built the one-layer single network.
    nn.Linear(n_in, n_out)
    layer = partial(EnsembleLinear, k)
    out = n_out * (2 if probabilistic else 1)
    return build_mlp(n_in, hidden_sizes, out, activation, layer)


class DeltaDynamicsModel(StandardScaling, EnsembleMembers, nn.Module):
    """MLP world model of ``K`` members predicting the standard-scaled state delta and reward.

    ``ensemble_size=1`` (the default) is the thesis model (section 5.2, table 7): one MLP on
    the standard-scaled ``(state, action)``. ``K >= 2`` stacks ``K`` members evaluated in one
    batched op per layer; ``forward`` then gives their mean, or one member per row with
    ``member_index``, and ``probabilistic=True`` adds a bounded log-variance per output (PETS,
    Chua et al., 2018). ``forward`` works in real units; the scaling statistics are buffers
    set by :meth:`fit_normalizer`. Design: ``docs/design/dynamics_model.md``.

    Args:
        state_dim: size of the state (18 for the thesis' HalfCheetah state).
        action_dim: size of the action (6 for HalfCheetah).

    Keyword Args:
        ensemble_size: number of members ``K``. Defaults to ``1`` (the thesis model).
        hidden_sizes: hidden layer widths (of every member). Defaults to ``(500, 500)``.
        activation: hidden activation class. Defaults to :class:`torch.nn.ReLU`.
        probabilistic: members output a mean and a bounded log-variance (needs ``K >= 2``).
            Defaults to ``False``.
        min_log_var: lower soft bound of the log-variance (scaled units). Defaults to
            ``-10.0``.
        max_log_var: upper soft bound of the log-variance (scaled units). Defaults to ``0.5``.
        action_low: lower clip of the action, or ``None`` for none. Defaults to ``None``
            (set from the env's action spec by ``LearnedDynamicsEnv``).
        action_high: upper clip of the action, or ``None`` for none. Defaults to ``None``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> model = DeltaDynamicsModel(18, 6, hidden_sizes=(32, 32))
        >>> s, a = torch.randn(100, 18), torch.randn(100, 6)
        >>> model.fit_normalizer(s, a, s + 0.1 * torch.randn(100, 18), torch.randn(100, 1))
        >>> next_state, reward = model(s[:4], a[:4])
        >>> next_state.shape, reward.shape
        (torch.Size([4, 18]), torch.Size([4, 1]))
        >>> model.net[0].weight.shape  # the thesis layout: nn.Linear [out, in]
        torch.Size([32, 24])
        >>> ensemble = DeltaDynamicsModel(18, 6, ensemble_size=3, hidden_sizes=(32, 32))
        >>> ensemble.net[0].weight.shape, ensemble.forward_members(s, a)[0].shape
        (torch.Size([3, 24, 32]), torch.Size([3, 100, 18]))
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        *,
        ensemble_size: int = 1,
        hidden_sizes: Sequence[int] = (500, 500),
        activation: type[nn.Module] = nn.ReLU,
        probabilistic: bool = False,
        min_log_var: float = -10.0,
        max_log_var: float = 0.5,
        action_low: float | None = None,
        action_high: float | None = None,
    ) -> None:
        super().__init__()
        k, low, high = _check_arguments(
            state_dim,
            action_dim,
            ensemble_size,
            probabilistic,
            (min_log_var, max_log_var),
            (action_low, action_high),
        )
        self.state_dim = int(state_dim)
        self.action_dim = int(action_dim)
        self.hidden_sizes = check_hidden_sizes(hidden_sizes)
        #: the action clip (``-inf``/``inf`` when there is none)
        self.action_low = low
        self.action_high = high
        self.ensemble_size = k
        self.probabilistic = bool(probabilistic)
        self.min_log_var = float(min_log_var)
        self.max_log_var = float(max_log_var)
        n_in, n_out = state_dim + action_dim, state_dim + 1
        self.net = _build_network(n_in, n_out, self.hidden_sizes, activation, k, probabilistic)
        self._register_scaling_buffers()

    @property
    def action_bounds(self) -> tuple[float, float] | None:
        """The action clip ``(low, high)``, or ``None`` when the model clips nothing."""
        if math.isinf(self.action_low) and math.isinf(self.action_high):
            return None
        return self.action_low, self.action_high

    def set_action_bounds(self, low: float, high: float) -> None:
        """Sets the action clip (a learned env adopts its env's action spec with it).

        Args:
            low: lower bound.
            high: upper bound.
        """
        low, high = float(low), float(high)
        if not low < high:
            raise ValueError(f"action bounds must have low < high, got [{low}, {high}]")
        self.action_low, self.action_high = low, high

    @property
    def num_members(self) -> int:
        """The ensemble size ``K`` (``1`` for the thesis model)."""
        return self.ensemble_size

    @property
    def config(self) -> dict[str, object]:
        """Constructor arguments, used to check that a checkpoint matches this model."""
        config: dict[str, object] = {
            "state_dim": self.state_dim,
            "action_dim": self.action_dim,
            "hidden_sizes": list(self.hidden_sizes),
            "action_low": self.action_low,
            "action_high": self.action_high,
        }
        if self.ensemble_size == 1:
            return config
        return {
            **config,
            "num_members": self.ensemble_size,
            "probabilistic": self.probabilistic,
            "min_log_var": self.min_log_var,
            "max_log_var": self.max_log_var,
        }

    def predict_scaled(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Network output ``[..., state_dim + 1]``: scaled delta then scaled reward.

        The members' mean for ``K >= 2``.

        Args:
            state: states ``[..., state_dim]``.
            action: actions ``[..., action_dim]``.
        """
        if self.ensemble_size > 1:
            return self.predict_scaled_members(state, action)[0].mean(0)
        return self.net(self.scaled_inputs(state, action))

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
                ``member_index[b]``. Defaults to ``None``: the mean over members.
        """
        if self.ensemble_size > 1:
            return self.predict_with_disagreement(state, action, member_index)[:2]
        if member_index is not None:
            self.check_member_index(member_index, state.shape[:-1])
        return self.unscale(state, self.predict_scaled(state, action))

    @torch.no_grad()
    def fused_step(self) -> Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]:
        """A faster, inference-only :meth:`forward` with the scaling folded into the weights.

        The input standardisation is folded into the first linear layer and the output
        un-scaling into the last one, removing about ten element-wise operations per call,
        which matters in a planner's small-batch loop. The returned function is a snapshot:
        build a new one after the weights or scaling change (planners do so at every plan).
        For ``K >= 2`` it is :meth:`fused_members` (called, the members' mean).

        Returns:
            ``step(state, action) -> (next_state, reward)``, equal to ``forward`` up to
            float rounding.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
            >>> s, a = torch.randn(5, 3), torch.randn(5, 1)
            >>> torch.allclose(model.fused_step()(s, a)[0], model(s, a)[0], atol=1e-5)
            True
        """
        if self.ensemble_size > 1:
            return self.fused_members()  # the members' mean when called
        layers = list(self.net)
        first, last = layers[0], layers[-1]
        if not (isinstance(first, nn.Linear) and isinstance(last, nn.Linear)):
            return self.forward
        if len(layers) == 1:
            (w1,), (b1,) = self.fold_scaling([first.weight], [first.bias])
            middle: list[nn.Module] = []
            wl, bl = None, None
        else:
            (w1, wl), (b1, bl) = self.fold_scaling(
                [first.weight, last.weight], [first.bias, last.bias]
            )
            middle = layers[1:-1]
        low, high, d = self.action_low, self.action_high, self.state_dim

        def step(state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
            x = torch.cat([state, action.clamp(low, high)], -1)
            x = nn.functional.linear(x, w1, b1)
            for layer in middle:
                x = layer(x)
            if wl is not None:
                x = nn.functional.linear(x, wl, bl)
            return state + x[..., :d], x[..., d:]

        return step

    def as_tensordict_module(
        self,
        *,
        state_key: NestedKey = "state",
        action_key: NestedKey = "action",
        reward_key: NestedKey = "reward",
        next_state_key: NestedKey | None = None,
    ) -> TensorDictModule:
        """Wraps the model in a :class:`~tensordict.nn.TensorDictModule`.

        Keyword Args:
            state_key: input state key. Defaults to ``"state"``.
            action_key: input action key. Defaults to ``"action"``.
            reward_key: output reward key. Defaults to ``"reward"``.
            next_state_key: output next-state key. Defaults to ``state_key`` (overwritten in
                place, the :class:`~torchrl.envs.model_based.ModelBasedEnvBase` convention).

        Returns:
            The module, sharing this model's parameters.

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> module = DeltaDynamicsModel(3, 1, hidden_sizes=(8,)).as_tensordict_module()
            >>> td = module(TensorDict(state=torch.zeros(5, 3), action=torch.zeros(5, 1),
            ...                        batch_size=[5]))
            >>> td["reward"].shape
            torch.Size([5, 1])
        """
        return TensorDictModule(
            self,
            in_keys=[state_key, action_key],
            out_keys=[next_state_key if next_state_key is not None else state_key, reward_key],
        )


__all__ = ["DeltaDynamicsModel", "build_mlp", "check_hidden_sizes"]
