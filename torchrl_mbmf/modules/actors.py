"""Actor and critic builders with the thesis' network sizes (table 5), sized from the env."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from tensordict.nn import (
    AddStateIndependentNormalScale,
    TensorDictModule,
)
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs import EnvBase
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor, TanhNormal, ValueOperator

from torchrl_mbmf.keys import OBSERVATION_KEY
from torchrl_mbmf.modules.log_std import make_sac_head
from torchrl_mbmf.modules.mlp import check_hidden_sizes

Distribution = Literal["tanh_normal", "normal"]


def _dims(env: EnvBase, observation_key: NestedKey, action_key: NestedKey):
    obs_spec = env.full_observation_spec_unbatched
    if observation_key not in obs_spec.keys(True):
        raise KeyError(
            f"the env has no {observation_key!r} observation; it has "
            f"{sorted(map(str, obs_spec.keys(True, True)))}"
        )
    action_spec = env.full_action_spec_unbatched[action_key]
    return obs_spec[observation_key].shape[-1], action_spec


def _mlp(in_features: int, out_features: int, hidden_sizes, activation) -> MLP:
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden_sizes),
        activation_class=activation,
    )


def _tanh_normal_kwargs(action_spec) -> dict[str, object]:
    return {"low": action_spec.space.low, "high": action_spec.space.high, "tanh_loc": False}


def _actor(net, observation_key, action_key, action_spec, dist_class, dist_kwargs):
    """``net`` writing ``loc`` and ``scale`` from the observation, then the distribution."""
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=[observation_key], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        out_keys=[action_key],
        spec=action_spec,
        distribution_class=dist_class,
        distribution_kwargs=dist_kwargs,
        return_log_prob=True,
    )


class TanhLoc(nn.Module):
    """Squashes a network's output with tanh: the thesis' policy mean (its actor output activation).

    Thesis table 5, "actor output layer activation": ``forward(x) = tanh(net(x))``. A module
    of its own (not ``Sequential(net, Tanh())``) so that the parameter names stay ``net.*``;
    planners unroll it into ``net``'s layers and a tanh
    (:class:`~torchrl_mbmf.modules.planners.ActorSampler`).

    Args:
        net: the network whose output is squashed.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.actors import TanhLoc
        >>> TanhLoc(nn.Linear(2, 1))(torch.zeros(3, 2)).abs().max() < 1
        tensor(True)
    """

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``tanh(net(x))``.

        Args:
            x: the network's input.
        """
        return torch.tanh(self.net(x))


def make_ppo_actor_critic(
    env: EnvBase,
    *,
    hidden_sizes: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ReLU,
    distribution: Distribution = "tanh_normal",
    init_log_std: float = 0.0,
    observation_key: NestedKey = OBSERVATION_KEY,
    action_key: NestedKey = "action",
) -> tuple[ProbabilisticActor, ValueOperator]:
    """Builds the PPO actor (Gaussian, state-independent log-std) and state-value critic.

    Both are MLPs of ``hidden_sizes`` with ``activation`` (thesis table 5: 2x64, ReLU) reading the
    policy ``observation``. The actor writes ``loc`` and ``scale``, samples ``action`` and its
    ``action_log_prob`` (the key ``ClipPPOLoss`` reads in torchrl 0.14); the scale is one
    trainable parameter per action dim (``log std`` = its log). The critic writes
    ``state_value``.

    Args:
        env: the real env; observation and action sizes are read from its specs.

    Keyword Args:
        hidden_sizes: hidden widths of both networks. Defaults to ``(64, 64)``.
        activation: hidden activation. Defaults to :class:`torch.nn.ReLU`.
        distribution: ``"tanh_normal"`` (a TanhNormal: actions inside the bounds, exact
            log-prob of what runs while the pre-tanh sample stays below float32's tanh
            saturation) or ``"normal"`` (the thesis' Gaussian with a tanh-squashed mean; the
            env clips actions; what ``configs/algo/ppo.yaml`` and so the recipes use). Defaults
            to ``"tanh_normal"``.
        init_log_std: initial log std of the policy. Defaults to ``0.0``.
        observation_key: input key. Defaults to ``"observation"``.
        action_key: action key. Defaults to ``"action"``.

    Returns:
        ``(actor, critic)``.

    Examples:
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> env = make_gym_state_env("Pendulum-v1")
        >>> actor, critic = make_ppo_actor_critic(env)
        >>> td = critic(actor(env.reset()))
        >>> [k in td.keys() for k in ("action", "action_log_prob", "loc", "scale", "state_value")]
        [True, True, True, True, True]
    """
    hidden_sizes = check_hidden_sizes(hidden_sizes)
    obs_dim, action_spec = _dims(env, observation_key, action_key)
    action_dim = action_spec.shape[-1]
    net = _mlp(obs_dim, action_dim, hidden_sizes, activation)
    if distribution == "normal":
        net = TanhLoc(net)
        dist_class, dist_kwargs = IndependentNormal, {}
    elif distribution == "tanh_normal":
        dist_class, dist_kwargs = TanhNormal, _tanh_normal_kwargs(action_spec)
    else:
        raise ValueError(
            f"unknown distribution {distribution!r}; expected 'tanh_normal' or 'normal'"
        )
    policy_net = nn.Sequential(
        net, AddStateIndependentNormalScale(action_dim, init_value=init_log_std)
    )
    actor = _actor(policy_net, observation_key, action_key, action_spec, dist_class, dist_kwargs)
    critic = ValueOperator(_mlp(obs_dim, 1, hidden_sizes, activation), in_keys=[observation_key])
    return actor, critic


def make_sac_actor_critic(
    env: EnvBase,
    *,
    hidden_sizes: Sequence[int] = (256, 256),
    activation: type[nn.Module] = nn.ReLU,
    observation_key: NestedKey = OBSERVATION_KEY,
    action_key: NestedKey = "action",
    scale: str = "biased_softplus",
) -> tuple[ProbabilisticActor, ValueOperator]:
    """Builds the SAC actor (TanhNormal, state-dependent scale) and one Q-network.

    ``torchrl.objectives.SACLoss`` copies the Q-network into its ensemble
    (``num_qvalue_nets``), so one is enough.

    Args:
        env: the real env; observation and action sizes are read from its specs.

    Keyword Args:
        hidden_sizes: hidden widths of both networks. Defaults to ``(256, 256)``.
        activation: hidden activation. Defaults to :class:`torch.nn.ReLU`.
        observation_key: input key. Defaults to ``"observation"``.
        action_key: action key. Defaults to ``"action"``.
        scale: how the actor's network gives the scale
            (:func:`~torchrl_mbmf.modules.log_std.make_sac_head`): ``"biased_softplus"``
            (torchrl's default) or ``"clamped_log_std"`` (SAC's reference code,
            Stable-Baselines3). Defaults to ``"biased_softplus"``.

    Returns:
        ``(actor, qvalue)``; the Q-network reads ``(observation, action)`` and writes
        ``state_action_value``.

    Examples:
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import make_sac_actor_critic
        >>> env = make_gym_state_env("Pendulum-v1")
        >>> actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(32, 32))
        >>> qvalue(actor(env.reset()))["state_action_value"].shape
        torch.Size([1])
    """
    hidden_sizes = check_hidden_sizes(hidden_sizes)
    obs_dim, action_spec = _dims(env, observation_key, action_key)
    action_dim = action_spec.shape[-1]
    net = nn.Sequential(
        _mlp(obs_dim, 2 * action_dim, hidden_sizes, activation),
        make_sac_head(scale),
    )
    kwargs = _tanh_normal_kwargs(action_spec)
    actor = _actor(net, observation_key, action_key, action_spec, TanhNormal, kwargs)
    qvalue = ValueOperator(
        _mlp(obs_dim + action_dim, 1, hidden_sizes, activation),
        in_keys=[observation_key, action_key],
    )
    return actor, qvalue
