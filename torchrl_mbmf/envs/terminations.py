"""Termination rules of Gymnasium tasks as functions of the (predicted) next state.

A learned env cannot ask MuJoCo whether a state is terminal: it applies the task's own rule to
the state its model predicts. The rules here are those of Gymnasium's MuJoCo ``v5`` tasks
(their ``is_healthy`` / ``terminated`` conditions, with each task's constructor parameters),
written for the package's state layout: the Gymnasium observation with the current positions
included (``exclude_current_positions_from_observation=False``: ``x`` first, then ``y`` for Ant
and Humanoid), or, with ``exclude_current_positions_from_observation=True``, without them.

Every rule maps states ``[..., state_dim]`` to a bool tensor ``[...]`` (``True``: terminated).
:func:`termination_rule` looks a rule up by Gymnasium id and constructor arguments,
:func:`termination_rule_of_env` reads both from a TorchRL env built on Gymnasium.

What a rule cannot see:

* Hopper's ``healthy_state_range`` applies to the unclipped joint velocities; the observation
  clips them to ``[-10, 10]``, so a velocity beyond ``healthy_state_range`` (100 by default) is
  seen as 10. Such velocities do not occur in practice.
* InvertedDoublePendulum terminates on the tip height read from MuJoCo's ``site_xpos``, which
  ``mj_step`` leaves at the kinematics of the last Runge-Kutta stage of the step (not exactly
  the returned state); the rule computes the tip height of the returned state from the
  observation's angles (``sin``/``cos``). The two differ by ``O(dt^2)``, so the rule can
  disagree with Gymnasium only for a tip within about ``1e-4`` of the threshold.
* Without positions (``exclude_current_positions_from_observation=True``) Ant's finiteness check
  cannot see ``x`` and ``y``.
* States are float32: a value within float32 rounding of a threshold may compare differently
  than in Gymnasium's float64.
"""

from __future__ import annotations

import inspect
import math
import re
import warnings
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torchrl.envs import EnvBase, TransformedEnv

#: ``rule(states [..., state_dim]) -> terminated [...]`` (bool).
TerminationFn = Callable[[torch.Tensor], torch.Tensor]

#: Gymnasium tasks that never terminate (their ids without the version).
NEVER_TERMINATING = (
    "HalfCheetah",
    "Swimmer",
    "Reacher",
    "Pusher",
    "HumanoidStandup",
    "Pendulum",
)

_warned: set[str] = set()


def _range(name: str, value: object) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in value)  # type: ignore[union-attr]
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a pair (low, high) of numbers, got {value!r}") from err
    if not low < high:
        raise ValueError(f"{name} must have low < high, got {value!r}")
    return low, high


def _check_state(state: torch.Tensor, min_dim: int, name: str) -> None:
    if state.shape[-1] < min_dim:
        raise ValueError(
            f"{name} reads states with at least {min_dim} entries in the last dim, got shape "
            f"{tuple(state.shape)}"
        )


def _inside(x: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """``low < x < high`` (open interval, as Gymnasium's ``is_healthy``)."""
    return (x > low) & (x < high)


class TerminationRule:
    """Base of the known termination rules: a callable ``states [..., S] -> bool [...]``.

    Subclasses implement :meth:`terminated`; ``__call__`` checks the state's size first.
    ``min_state_dim`` is the smallest state the rule can read.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import NeverTerminates
        >>> NeverTerminates()(torch.zeros(4, 3))
        tensor([False, False, False, False])
    """

    min_state_dim = 0

    def __call__(self, state: torch.Tensor) -> torch.Tensor:
        """Terminated ``[...]`` of the states ``[..., state_dim]``."""
        _check_state(state, self.min_state_dim, type(self).__name__)
        return self.terminated(state)

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """The rule itself (the state's size already checked)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in vars(self).items())
        return f"{type(self).__name__}({params})"


class NeverTerminates(TerminationRule):
    """The rule of tasks without terminal states: always ``False``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import NeverTerminates
        >>> NeverTerminates()(torch.zeros(2, 5, 18)).shape
        torch.Size([2, 5])
    """

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """All ``False``."""
        return torch.zeros(state.shape[:-1], dtype=torch.bool, device=state.device)


class _PlanarWalkerRule(TerminationRule):
    """Hopper and Walker2d: root height and torso angle (qpos[1:3])."""

    def __init__(
        self,
        *,
        healthy_z_range: tuple[float, float],
        healthy_angle_range: tuple[float, float],
        terminate_when_unhealthy: bool,
        exclude_current_positions_from_observation: bool,
    ) -> None:
        self.healthy_z_range = _range("healthy_z_range", healthy_z_range)
        self.healthy_angle_range = _range("healthy_angle_range", healthy_angle_range)
        self.terminate_when_unhealthy = bool(terminate_when_unhealthy)
        self.exclude_current_positions_from_observation = bool(
            exclude_current_positions_from_observation
        )

    @property
    def _z_index(self) -> int:
        return 0 if self.exclude_current_positions_from_observation else 1

    def healthy(self, state: torch.Tensor) -> torch.Tensor:
        """Whether each state is healthy ``[...]``."""
        i = self._z_index
        return _inside(state[..., i], *self.healthy_z_range) & _inside(
            state[..., i + 1], *self.healthy_angle_range
        )

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """Unhealthy (when ``terminate_when_unhealthy``)."""
        if not self.terminate_when_unhealthy:
            return NeverTerminates.terminated(self, state)  # type: ignore[arg-type]
        return ~self.healthy(state)


class HopperTermination(_PlanarWalkerRule):
    """Hopper-v5's termination: unhealthy height, torso angle or state magnitude.

    Healthy when ``healthy_z_range[0] < z < healthy_z_range[1]``, ``healthy_angle_range[0] <
    angle < healthy_angle_range[1]`` and every entry after them (the other joint angles and
    the velocities) lies strictly inside ``healthy_state_range``. With positions included the
    state is ``[x, z, angle, ...]`` (12 entries), without them ``[z, angle, ...]`` (11).

    Keyword Args:
        healthy_state_range: Defaults to ``(-100.0, 100.0)``.
        healthy_z_range: Defaults to ``(0.7, inf)``.
        healthy_angle_range: Defaults to ``(-0.2, 0.2)``.
        terminate_when_unhealthy: Defaults to ``True``.
        exclude_current_positions_from_observation: the state has no ``x``. Defaults to
            ``False`` (the package's layout).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import HopperTermination
        >>> state = torch.zeros(2, 12)
        >>> state[:, 1] = torch.tensor([1.25, 0.5])  # standing, then fallen
        >>> HopperTermination()(state)
        tensor([False,  True])
    """

    min_state_dim = 3

    def __init__(
        self,
        *,
        healthy_state_range: tuple[float, float] = (-100.0, 100.0),
        healthy_z_range: tuple[float, float] = (0.7, math.inf),
        healthy_angle_range: tuple[float, float] = (-0.2, 0.2),
        terminate_when_unhealthy: bool = True,
        exclude_current_positions_from_observation: bool = False,
    ) -> None:
        super().__init__(
            healthy_z_range=healthy_z_range,
            healthy_angle_range=healthy_angle_range,
            terminate_when_unhealthy=terminate_when_unhealthy,
            exclude_current_positions_from_observation=exclude_current_positions_from_observation,
        )
        self.healthy_state_range = _range("healthy_state_range", healthy_state_range)

    def healthy(self, state: torch.Tensor) -> torch.Tensor:
        """Whether each state is healthy ``[...]``."""
        rest = state[..., self._z_index + 1 :]  # qpos[2:] and the velocities
        ok = _inside(rest, *self.healthy_state_range).all(-1)
        return super().healthy(state) & ok


class Walker2dTermination(_PlanarWalkerRule):
    """Walker2d-v5's termination: unhealthy root height or torso angle.

    Healthy when ``healthy_z_range[0] < z < healthy_z_range[1]`` and ``healthy_angle_range[0]
    < angle < healthy_angle_range[1]``; the state is ``[x, z, angle, ...]`` (18 entries) with
    positions, ``[z, angle, ...]`` (17) without.

    Keyword Args:
        healthy_z_range: Defaults to ``(0.8, 2.0)``.
        healthy_angle_range: Defaults to ``(-1.0, 1.0)``.
        terminate_when_unhealthy: Defaults to ``True``.
        exclude_current_positions_from_observation: the state has no ``x``. Defaults to
            ``False``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import Walker2dTermination
        >>> state = torch.zeros(3, 18)
        >>> state[:, 1] = torch.tensor([1.25, 0.5, 2.5])
        >>> Walker2dTermination()(state)
        tensor([False,  True,  True])
    """

    min_state_dim = 3

    def __init__(
        self,
        *,
        healthy_z_range: tuple[float, float] = (0.8, 2.0),
        healthy_angle_range: tuple[float, float] = (-1.0, 1.0),
        terminate_when_unhealthy: bool = True,
        exclude_current_positions_from_observation: bool = False,
    ) -> None:
        super().__init__(
            healthy_z_range=healthy_z_range,
            healthy_angle_range=healthy_angle_range,
            terminate_when_unhealthy=terminate_when_unhealthy,
            exclude_current_positions_from_observation=exclude_current_positions_from_observation,
        )


class _TorsoHeightRule(TerminationRule):
    """Ant and Humanoid: the torso's height qpos[2] (index 2 with x, y, else 0)."""

    closed = False
    #: qpos + qvel sizes, for the finiteness check (Ant).
    finite_dims: int | None = None

    def __init__(
        self,
        *,
        healthy_z_range: tuple[float, float],
        terminate_when_unhealthy: bool,
        exclude_current_positions_from_observation: bool,
    ) -> None:
        self.healthy_z_range = _range("healthy_z_range", healthy_z_range)
        self.terminate_when_unhealthy = bool(terminate_when_unhealthy)
        self.exclude_current_positions_from_observation = bool(
            exclude_current_positions_from_observation
        )

    @property
    def min_state_dim(self) -> int:  # type: ignore[override]
        return 1 if self.exclude_current_positions_from_observation else 3

    def healthy(self, state: torch.Tensor) -> torch.Tensor:
        """Whether each state is healthy ``[...]``."""
        z = state[..., 0 if self.exclude_current_positions_from_observation else 2]
        low, high = self.healthy_z_range
        ok = (z >= low) & (z <= high) if self.closed else _inside(z, low, high)
        if self.finite_dims is not None:
            n = self.finite_dims - (2 if self.exclude_current_positions_from_observation else 0)
            ok = ok & torch.isfinite(state[..., :n]).all(-1)
        return ok

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """Unhealthy (when ``terminate_when_unhealthy``)."""
        if not self.terminate_when_unhealthy:
            return NeverTerminates.terminated(self, state)  # type: ignore[arg-type]
        return ~self.healthy(state)


class AntTermination(_TorsoHeightRule):
    """Ant-v5's termination: torso height outside ``healthy_z_range`` or a non-finite state.

    Healthy when ``healthy_z_range[0] <= z <= healthy_z_range[1]`` (closed, as in Gymnasium)
    and the joint positions and velocities (the state's first 29 entries with ``x, y``, 27
    without) are finite. The contact forces that follow by default
    (``include_cfrc_ext_in_observation=True``) are not read.

    Keyword Args:
        healthy_z_range: Defaults to ``(0.2, 1.0)``.
        terminate_when_unhealthy: Defaults to ``True``.
        exclude_current_positions_from_observation: the state has no ``x, y``. Defaults to
            ``False``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import AntTermination
        >>> state = torch.zeros(3, 29)
        >>> state[:, 2] = torch.tensor([0.55, 1.2, 0.1])
        >>> AntTermination()(state)
        tensor([False,  True,  True])
    """

    closed = True
    finite_dims = 29

    def __init__(
        self,
        *,
        healthy_z_range: tuple[float, float] = (0.2, 1.0),
        terminate_when_unhealthy: bool = True,
        exclude_current_positions_from_observation: bool = False,
    ) -> None:
        super().__init__(
            healthy_z_range=healthy_z_range,
            terminate_when_unhealthy=terminate_when_unhealthy,
            exclude_current_positions_from_observation=exclude_current_positions_from_observation,
        )

    @property
    def min_state_dim(self) -> int:  # type: ignore[override]
        """The joint positions and velocities the finiteness check reads."""
        return 27 if self.exclude_current_positions_from_observation else 29


class HumanoidTermination(_TorsoHeightRule):
    """Humanoid-v5's termination: torso height outside ``(healthy_z_range)`` (open interval).

    Keyword Args:
        healthy_z_range: Defaults to ``(1.0, 2.0)``.
        terminate_when_unhealthy: Defaults to ``True``.
        exclude_current_positions_from_observation: the state has no ``x, y``. Defaults to
            ``False``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import HumanoidTermination
        >>> state = torch.zeros(2, 50)
        >>> state[:, 2] = torch.tensor([1.4, 0.9])
        >>> HumanoidTermination()(state)
        tensor([False,  True])
    """

    def __init__(
        self,
        *,
        healthy_z_range: tuple[float, float] = (1.0, 2.0),
        terminate_when_unhealthy: bool = True,
        exclude_current_positions_from_observation: bool = False,
    ) -> None:
        super().__init__(
            healthy_z_range=healthy_z_range,
            terminate_when_unhealthy=terminate_when_unhealthy,
            exclude_current_positions_from_observation=exclude_current_positions_from_observation,
        )


class InvertedPendulumTermination(TerminationRule):
    """InvertedPendulum-v5's termination: pole angle ``|state[1]| > 0.2`` or a non-finite state.

    The state is ``[cart x, pole angle, cart velocity, pole angular velocity]``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import InvertedPendulumTermination
        >>> InvertedPendulumTermination()(torch.tensor([[0.0, 0.1, 0, 0], [0.0, -0.3, 0, 0]]))
        tensor([False,  True])
    """

    min_state_dim = 4

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """Pole beyond 0.2 rad or a non-finite entry."""
        return ~torch.isfinite(state).all(-1) | (state[..., 1].abs() > 0.2)


class InvertedDoublePendulumTermination(TerminationRule):
    """InvertedDoublePendulum-v5's termination: the tip's height ``y <= 1``.

    The state is ``[x, sin q1, sin q2, cos q1, cos q2, velocities (3), constraint force]``;
    both poles are 0.6 long on a cart at height 0, so the tip is at
    ``y = 0.6 cos q1 + 0.6 cos(q1 + q2)`` (upright: 1.2). Gymnasium reads the tip's height
    from MuJoCo's ``site_xpos``, which lags the returned state by a fraction of a step (see
    the module docstring).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import InvertedDoublePendulumTermination
        >>> upright = torch.tensor([0.0, 0, 0, 1, 1, 0, 0, 0, 0])
        >>> bent = torch.tensor([0.0, 1, 0, 0, 1, 0, 0, 0, 0])  # q1 = pi / 2
        >>> InvertedDoublePendulumTermination()(torch.stack([upright, bent]))
        tensor([False,  True])
    """

    min_state_dim = 5

    def tip_height(self, state: torch.Tensor) -> torch.Tensor:
        """Height of the tip ``[...]``."""
        s1, s2, c1, c2 = state[..., 1], state[..., 2], state[..., 3], state[..., 4]
        return 0.6 * c1 + 0.6 * (c1 * c2 - s1 * s2)

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """Tip at or below 1."""
        return self.tip_height(state) <= 1.0


#: Gymnasium name (without version) -> the rule class of its ``v5`` task.
RULES: dict[str, type[TerminationRule]] = {
    "Hopper": HopperTermination,
    "Walker2d": Walker2dTermination,
    "Ant": AntTermination,
    "Humanoid": HumanoidTermination,
    "InvertedPendulum": InvertedPendulumTermination,
    "InvertedDoublePendulum": InvertedDoublePendulumTermination,
}


_RULE_PARAMETERS = frozenset(
    name
    for cls in RULES.values()
    for name in inspect.signature(cls.__init__).parameters
    if name != "self"
)


def _rule_kwargs(cls: type[TerminationRule], env_kwargs: Mapping[str, Any]) -> dict[str, Any]:
    params = inspect.signature(cls.__init__).parameters
    return {k: v for k, v in env_kwargs.items() if k in params and k != "self"}


def termination_rule(env_id: str, **env_kwargs: Any) -> TerminationFn:
    """The termination rule of a Gymnasium task, for the package's state layout.

    Gymnasium's MuJoCo ``v5`` tasks with terminations (Hopper, Walker2d, Ant, Humanoid,
    InvertedPendulum, InvertedDoublePendulum) get their rule, with the constructor arguments
    in ``env_kwargs`` that change it (``healthy_z_range``, ``terminate_when_unhealthy``,
    ``exclude_current_positions_from_observation``...; others are ignored). Unlike
    ``gym.make``, ``exclude_current_positions_from_observation`` defaults to ``False`` here,
    the package's layout (:func:`termination_rule_of_env` reads the env's own value). Tasks without
    terminations (HalfCheetah, Swimmer, Reacher, Pusher, HumanoidStandup of any version,
    Pendulum) never terminate. Any other id warns once, naming the task and the
    ``termination_fn`` argument of :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`, and never
    terminates.

    Args:
        env_id: Gymnasium id, for example ``"Hopper-v5"``.
        **env_kwargs: the task's constructor arguments (those of ``gym.make``).

    Returns:
        ``rule(states [..., state_dim]) -> bool [...]``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs.terminations import termination_rule
        >>> type(termination_rule("Hopper-v5")).__name__
        'HopperTermination'
        >>> termination_rule("Hopper-v5", healthy_z_range=(0.5, 3.0)).healthy_z_range
        (0.5, 3.0)
        >>> termination_rule("HalfCheetah-v5")(torch.zeros(18))
        tensor(False)
    """
    if not isinstance(env_id, str):
        raise TypeError(f"env_id must be a Gymnasium id string, got {env_id!r}")
    match = re.fullmatch(r"(?:.+/)?([A-Za-z0-9]+)-(v\d+)", env_id)
    name, version = (match.group(1), match.group(2)) if match else (env_id, "")
    if name in NEVER_TERMINATING:
        return NeverTerminates()
    if name in RULES and version == "v5":
        cls = RULES[name]
        return cls(**_rule_kwargs(cls, env_kwargs))
    if env_id not in _warned:
        _warned.add(env_id)
        warnings.warn(
            f"no known termination rule for {env_id!r}: its learned env never terminates; pass "
            "termination_fn=<callable on the predicted next state> to LearnedDynamicsEnv for a "
            "task with terminal states",
            UserWarning,
            stacklevel=2,
        )
    return NeverTerminates()


def gym_id_and_kwargs(env: EnvBase) -> tuple[str, dict[str, Any]] | None:
    """The Gymnasium id and ``gym.make`` arguments of a TorchRL env built on Gymnasium.

    Looks through :class:`~torchrl.envs.TransformedEnv` layers for the wrapped Gymnasium env
    (the first copy of a vector env); ``None`` when there is none. The arguments are those of
    ``gym.make`` completed with the task's own values of the termination rules' parameters
    (so a default such as ``exclude_current_positions_from_observation=True`` is seen).

    Args:
        env: a TorchRL env.

    Examples:
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.envs.terminations import gym_id_and_kwargs
        >>> gym_id_and_kwargs(make_gym_state_env("Pendulum-v1"))[0]
        'Pendulum-v1'
    """
    node: EnvBase = env
    while isinstance(node, TransformedEnv):
        node = node.base_env
    gym_env = getattr(node, "_env", None)
    if gym_env is not None and hasattr(gym_env, "envs"):
        gym_env = gym_env.envs[0]
    spec = getattr(gym_env, "spec", None)
    if spec is None or not isinstance(getattr(spec, "id", None), str):
        return None
    kwargs = dict(spec.kwargs or {})
    # the constructed task's own settings (its defaults included), as MuJoCo envs keep them
    unwrapped = getattr(gym_env, "unwrapped", None)
    for name, value in vars(unwrapped).items() if unwrapped is not None else ():
        if name.startswith("_") and not name.startswith("__") and name[1:] in _RULE_PARAMETERS:
            kwargs[name[1:]] = value
    return spec.id, kwargs


def termination_rule_of_env(env: EnvBase) -> TerminationFn:
    """:func:`termination_rule` of the Gymnasium task a TorchRL env runs.

    An env not built on Gymnasium warns once (naming its class and the ``termination_fn``
    argument) and never terminates.

    Args:
        env: a TorchRL env (for example from :func:`~torchrl_mbmf.envs.make_env`).

    Examples:
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.envs.terminations import termination_rule_of_env
        >>> termination_rule_of_env(make_gym_state_env("Pendulum-v1"))
        NeverTerminates()
    """
    found = gym_id_and_kwargs(env)
    if found is None:
        return termination_rule(type(env).__name__)
    env_id, kwargs = found
    return termination_rule(env_id, **kwargs)


__all__ = [
    "NEVER_TERMINATING",
    "RULES",
    "AntTermination",
    "HopperTermination",
    "HumanoidTermination",
    "InvertedDoublePendulumTermination",
    "InvertedPendulumTermination",
    "NeverTerminates",
    "TerminationFn",
    "TerminationRule",
    "Walker2dTermination",
    "gym_id_and_kwargs",
    "termination_rule",
    "termination_rule_of_env",
]
