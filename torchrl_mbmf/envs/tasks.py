"""Where each known Gymnasium task keeps its positions in the model state.

The world model predicts the whole state, so forward progress must be in it: for the MuJoCo
locomotion tasks the state is Gymnasium's observation built with
``exclude_current_positions_from_observation=False`` (the root's x, and y where the task moves in
a plane, first). Policies and critics must not see those unbounded positions: the policy
observation is the state without them. :func:`task_layout` gives that description per task;
:func:`~torchrl_mbmf.envs.make_env` builds every task from it, and the analysis reads the x index
from it instead of assuming HalfCheetah's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

__all__ = ["TASK_LAYOUTS", "TaskLayout", "task_layout"]

_WITH_POSITIONS: Mapping[str, bool] = MappingProxyType(
    {"exclude_current_positions_from_observation": False}
)


@dataclass(frozen=True)
class TaskLayout:
    """The state layout of one Gymnasium task, as the real envs of this package build it.

    Attributes:
        env_id: the Gymnasium id.
        state_dim: size of the state built with ``gym_kwargs`` (and the task's other defaults).
        x_index: state index of the x position (forward progress, or a cart's position), or
            ``None`` when the state has none.
        y_index: state index of the y position, or ``None``.
        hidden_dims: state dims left out of the policy observation (the unbounded root
            positions).
        gym_kwargs: ``gym.make`` arguments that put the positions into the observation.
        terminates: whether the task ends episodes on its own (``terminated``), not only by its
            time limit.

    Examples:
        >>> from torchrl_mbmf.envs.tasks import task_layout
        >>> layout = task_layout("Ant-v5")
        >>> layout.state_dim, layout.x_index, layout.y_index, layout.hidden_dims
        (107, 0, 1, (0, 1))
    """

    env_id: str
    state_dim: int
    x_index: int | None
    y_index: int | None = None
    hidden_dims: tuple[int, ...] = ()
    gym_kwargs: Mapping[str, object] = field(default_factory=dict)
    terminates: bool = False

    def make_kwargs(self, gym_kwargs: Mapping[str, object]) -> dict[str, object]:
        """``gym_kwargs`` with this layout's own ``gym.make`` arguments added.

        Args:
            gym_kwargs: the caller's ``gym.make`` arguments.

        Returns:
            The merged arguments.

        Raises:
            ValueError: the caller sets one of the layout's arguments to another value (for
                example ``exclude_current_positions_from_observation=True``, which would take
                the positions out of the model state).

        Examples:
            >>> from torchrl_mbmf.envs.tasks import task_layout
            >>> task_layout("Hopper-v5").make_kwargs({"max_episode_steps": 10})
            {'max_episode_steps': 10, 'exclude_current_positions_from_observation': False}
        """
        merged = dict(gym_kwargs)
        for key, value in self.gym_kwargs.items():
            if merged.setdefault(key, value) != value:
                raise ValueError(
                    f"{key}={merged[key]!r} is not supported for {self.env_id}: its model state "
                    f"needs {key}={value!r} (the positions first, so forward progress is in "
                    "the state; the policy observation leaves them out)"
                )
        return merged


def _planar(env_id: str, state_dim: int, *, terminates: bool = False) -> TaskLayout:
    """A task moving in the plane: x and y first, both hidden from the policy."""
    return TaskLayout(env_id, state_dim, 0, 1, (0, 1), _WITH_POSITIONS, terminates)


def _forward(env_id: str, state_dim: int, *, terminates: bool = False) -> TaskLayout:
    """A task moving along x: x first, hidden from the policy."""
    return TaskLayout(env_id, state_dim, 0, None, (0,), _WITH_POSITIONS, terminates)


#: The layout of every task whose state this package knows (Gymnasium 1.x ids). The carts of
#: the inverted pendulums move on a bounded rail: their x is part of Gymnasium's own observation
#: and stays visible to the policy.
TASK_LAYOUTS: Mapping[str, TaskLayout] = MappingProxyType(
    {
        layout.env_id: layout
        for layout in (
            _planar("Ant-v5", 107, terminates=True),  # with the contact forces (v5 default)
            _forward("HalfCheetah-v5", 18),
            _forward("Hopper-v5", 12, terminates=True),
            _planar("Humanoid-v5", 350, terminates=True),
            _planar("HumanoidStandup-v5", 350),
            TaskLayout("InvertedDoublePendulum-v5", 9, 0, terminates=True),
            TaskLayout("InvertedPendulum-v5", 4, 0, terminates=True),
            TaskLayout("Pusher-v5", 23, None),
            TaskLayout("Reacher-v5", 10, None),
            _planar("Swimmer-v5", 10),
            _forward("Walker2d-v5", 18, terminates=True),
            TaskLayout("Pendulum-v1", 3, None),
        )
    }
)


def task_layout(env_id: str) -> TaskLayout | None:
    """The layout of a known task, or ``None`` for any other id.

    Args:
        env_id: a Gymnasium id, for example ``"Hopper-v5"``.

    Returns:
        Its :class:`TaskLayout` from :data:`TASK_LAYOUTS`, or ``None`` (an unknown task: its
        state is its observation, nothing is hidden, and where its x lies is not known).

    Examples:
        >>> from torchrl_mbmf.envs.tasks import task_layout
        >>> task_layout("Hopper-v5").x_index, task_layout("Pendulum-v1").x_index
        (0, None)
        >>> task_layout("MyTask-v0") is None
        True
    """
    return TASK_LAYOUTS.get(env_id)
