"""The world-model network and the learned termination head of a run, sized from its env."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torchrl.envs import EnvBase

from torchrl_mbmf.checks import check_arguments, settings
from torchrl_mbmf.envs.factory import action_bounds
from torchrl_mbmf.envs.keys import STATE_KEY
from torchrl_mbmf.envs.terminations import (
    NEVER_TERMINATING,
    RULES,
    gym_id_and_kwargs,
    termination_rule,
)
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel, check_hidden_sizes
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel
from torchrl_mbmf.modules.termination import LearnedTermination

__all__ = ["make_termination_head", "make_world_model"]

log = logging.getLogger(__name__)


def make_world_model(
    env: EnvBase,
    *,
    hidden_sizes: Sequence[int],
    ensemble_size: int = 1,
    probabilistic: bool = False,
) -> DeltaDynamicsModel | EnsembleDeltaDynamicsModel:
    """The world-model network of the ``world_model`` group's architecture keys, sized from ``env``.

    Its state and action sizes and its action range are the env's (:func:`action_bounds`).

    Args:
        env: the real env (state and action sizes, action range; a float32 state).

    Keyword Args:
        hidden_sizes: hidden layers (checked by the network's constructor).
        ensemble_size: members; ``1`` builds one :class:`~torchrl_mbmf.modules.DeltaDynamicsModel`
            (the thesis), more an :class:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel`.
            Defaults to ``1``.
        probabilistic: Gaussian outputs (ensemble only). Defaults to ``False``.

    Examples:
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.world_model.networks import make_world_model
        >>> model = make_world_model(make_env("Pendulum-v1"), hidden_sizes=[8])
        >>> type(model).__name__, model.action_low, model.action_high
        ('DeltaDynamicsModel', -2.0, 2.0)

    Raises:
        ValueError: the env's state is not float32, or its action spec has no single range.
    """
    check_arguments(settings(positive_int=("ensemble_size",), flag=("probabilistic",)), locals())
    state_spec = env.full_observation_spec_unbatched[STATE_KEY]
    if state_spec.dtype != torch.float32:
        raise ValueError(
            f"the env's {STATE_KEY!r} is {state_spec.dtype}; the world model works in float32: "
            "add torchrl.envs.DoubleToFloat() to the env (this package's builders do)"
        )
    state_dim = state_spec.shape[-1]
    action_dim = env.full_action_spec_unbatched[env.action_key].shape[-1]
    # the model's action range is the env's (no silent clip: Pendulum's is [-2, 2])
    low, high = action_bounds(env)
    hidden = check_hidden_sizes(hidden_sizes)
    if ensemble_size > 1:
        return EnsembleDeltaDynamicsModel(
            state_dim,
            action_dim,
            num_members=ensemble_size,
            hidden_sizes=hidden,
            probabilistic=probabilistic,
            action_low=low,
            action_high=high,
        )
    return DeltaDynamicsModel(
        state_dim, action_dim, hidden_sizes=hidden, action_low=low, action_high=high
    )


def make_termination_head(env: EnvBase, state_dim: int, device: torch.device) -> LearnedTermination:
    """A :class:`~torchrl_mbmf.modules.LearnedTermination` for ``env``'s state, said in the log.

    With ``world_model.learn_termination`` the head replaces the task's known rule (the user's
    choice): the log says so once, naming the rule it replaces.

    Args:
        env: the real env (its task is named in the log).
        state_dim: size of the state.
        device: device of the head.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.world_model.networks import make_termination_head
        >>> make_termination_head(make_env("Hopper-v5"), 12, torch.device("cpu")).state_dim
        12
    """
    task, kwargs = gym_id_and_kwargs(env) or ("this task", {})
    name = task.split("/")[-1]
    if name.split("-")[0] in NEVER_TERMINATING:
        what = "no terminal states by Gymnasium's rule (the head learns that from the data)"
    elif name.split("-")[0] in RULES and name.endswith("-v5"):
        rule = termination_rule(task, **kwargs)
        what = f"a known termination rule ({type(rule).__name__}), not used"
    else:
        what = "no known termination rule"
    log.info(
        "world_model.learn_termination=true: imagined episodes end where a termination head "
        "fitted on the real terminated flags predicts; %s has %s",
        task,
        what,
    )
    return LearnedTermination(state_dim).to(device)
