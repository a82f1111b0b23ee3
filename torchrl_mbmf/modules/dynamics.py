"""The thesis' feed-forward world model: (state, action) -> (state delta, reward)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

_MIN_SCALE = 1e-6


def check_hidden_sizes(hidden_sizes: Sequence[int], name: str = "hidden_sizes") -> tuple[int, ...]:
    """Checks hidden layer widths: a sequence (possibly empty) of integers >= 1.

    A width of 0 builds a layer whose output is always 0; a float or a bool is a typo.

    Args:
        hidden_sizes: the widths.
        name: the argument's name in the error message. Defaults to ``"hidden_sizes"``.

    Returns:
        The widths as a tuple of ints.

    Raises:
        ValueError: naming the argument and the value.

    Examples:
        >>> from torchrl_mbmf.modules.dynamics import check_hidden_sizes
        >>> check_hidden_sizes([64, 64])
        (64, 64)
        >>> try:
        ...     check_hidden_sizes((0,))
        ... except ValueError as err:
        ...     print(err)
        hidden_sizes must be a sequence of integers >= 1, got (0,)
    """
    ok = isinstance(hidden_sizes, Sequence) and not isinstance(hidden_sizes, str)
    if ok:
        ok = all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in hidden_sizes)
    if not ok:
        raise ValueError(f"{name} must be a sequence of integers >= 1, got {hidden_sizes!r}")
    return tuple(int(h) for h in hidden_sizes)


def build_mlp(
    in_features: int,
    hidden_sizes: Sequence[int],
    out_features: int,
    activation: type[nn.Module],
    linear: Callable[[int, int], nn.Module] = nn.Linear,
) -> nn.Sequential:
    """``linear -> activation`` per hidden width, then a last ``linear``: the world model's net.

    Args:
        in_features: input size.
        hidden_sizes: hidden widths (checked by :func:`check_hidden_sizes` by the caller).
        out_features: output size.
        activation: hidden activation class.
        linear: builds a linear layer from ``(in, out)``: :class:`torch.nn.Linear` for one
            model, ``EnsembleLinear`` with a member count for stacked members. Defaults to
            :class:`torch.nn.Linear`.

    Examples:
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.dynamics import build_mlp
        >>> build_mlp(4, (8,), 2, nn.ReLU)
        Sequential(
          (0): Linear(in_features=4, out_features=8, bias=True)
          (1): ReLU()
          (2): Linear(in_features=8, out_features=2, bias=True)
        )
    """
    layers: list[nn.Module] = []
    width = in_features
    for h in hidden_sizes:
        layers += [linear(width, h), activation()]
        width = h
    layers.append(linear(width, out_features))
    return nn.Sequential(*layers)


class DeltaDynamicsModel(nn.Module):
    """Deterministic MLP world model predicting the standard-scaled state delta and reward.

    The thesis model (section 5.2, table 7): inputs are the state and the action, each
    standard-scaled with statistics of the training data; the network (``24 -> 500 -> 500 -> 19``
    for HalfCheetah, ReLU hidden layers, linear output) predicts the scaled delta
    ``s' - s`` and the scaled reward. Actions are clipped to ``[action_low, action_high]``
    before scaling. The scaling statistics are buffers, so they are saved and loaded with the
    weights in ``state_dict``; :meth:`fit_normalizer` sets them from data.

    ``forward(state, action)`` returns the next state and the reward in real units, so the
    module plugs into TorchRL as a :class:`~tensordict.nn.TensorDictModule` (see
    :meth:`as_tensordict_module`); :meth:`predict_scaled` gives the network output the
    training loss compares with :meth:`scale_targets`.

    Args:
        state_dim: size of the state (18 for the thesis' HalfCheetah state).
        action_dim: size of the action (6 for HalfCheetah).

    Keyword Args:
        hidden_sizes: hidden layer widths. Defaults to ``(500, 500)``.
        activation: hidden activation class. Defaults to :class:`torch.nn.ReLU`.
        action_low: lower clip of the action. Defaults to ``-1.0``.
        action_high: upper clip of the action. Defaults to ``1.0``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> model = DeltaDynamicsModel(18, 6, hidden_sizes=(32, 32))
        >>> s, a = torch.randn(100, 18), torch.randn(100, 6)
        >>> model.fit_normalizer(s, a, s + 0.1 * torch.randn(100, 18), torch.randn(100, 1))
        >>> next_state, reward = model(s[:4], a[:4])
        >>> next_state.shape, reward.shape
        (torch.Size([4, 18]), torch.Size([4, 1]))
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        *,
        hidden_sizes: Sequence[int] = (500, 500),
        activation: type[nn.Module] = nn.ReLU,
        action_low: float = -1.0,
        action_high: float = 1.0,
    ) -> None:
        super().__init__()
        if state_dim < 1 or action_dim < 1:
            raise ValueError(
                f"state_dim and action_dim must be >= 1, got state_dim={state_dim}, "
                f"action_dim={action_dim}"
            )
        if action_low >= action_high:
            raise ValueError(f"action_low={action_low} must be < action_high={action_high}")
        self.state_dim = int(state_dim)
        self.action_dim = int(action_dim)
        self.hidden_sizes = check_hidden_sizes(hidden_sizes)
        self.action_low = float(action_low)
        self.action_high = float(action_high)
        self.net = build_mlp(state_dim + action_dim, self.hidden_sizes, state_dim + 1, activation)
        for name, dim in (("state", state_dim), ("action", action_dim), ("delta", state_dim)):
            self.register_buffer(f"{name}_loc", torch.zeros(dim))
            self.register_buffer(f"{name}_scale", torch.ones(dim))
        self.register_buffer("reward_loc", torch.zeros(1))
        self.register_buffer("reward_scale", torch.ones(1))
        self.register_buffer("normalizer_fitted", torch.zeros((), dtype=torch.bool))

    @property
    def config(self) -> dict[str, object]:
        """Constructor arguments, used to check that a checkpoint matches this model."""
        return {
            "state_dim": self.state_dim,
            "action_dim": self.action_dim,
            "hidden_sizes": list(self.hidden_sizes),
            "action_low": self.action_low,
            "action_high": self.action_high,
        }

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
        """Clips the action to ``[action_low, action_high]``."""
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

    def predict_scaled(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Network output ``[..., state_dim + 1]``: scaled delta then scaled reward."""
        return self.net(self.scaled_inputs(state, action))

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

    def forward(
        self, state: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicts the next state ``[..., state_dim]`` and reward ``[..., 1]`` in real units."""
        return self.unscale(state, self.predict_scaled(state, action))

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

    @torch.no_grad()
    def fused_step(self) -> Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]:
        """A faster, inference-only :meth:`forward` with the scaling folded into the weights.

        The input standardisation is folded into the first linear layer and the output
        un-scaling into the last one, removing about ten element-wise operations per call,
        which matters in a planner's small-batch loop. The returned function is a snapshot:
        build a new one after the weights or scaling change (planners do so at every plan).

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
