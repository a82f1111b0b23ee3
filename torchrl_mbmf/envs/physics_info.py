"""Gymnasium wrapper exposing the MuJoCo quantities the thesis' rewards and gait analysis need."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Sequence
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from torchrl_mbmf.envs.keys import (
    ACTUATOR_TORQUES_KEY,
    FORWARD_VELOCITY_KEY,
    HEAD_HEIGHT_KEY,
    JOINT_ANGLES_KEY,
    JOINT_VELOCITIES_KEY,
)

logger = logging.getLogger(__name__)

#: The six actuated joints of HalfCheetah, in action order.
HALF_CHEETAH_JOINTS: tuple[str, ...] = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")


@contextlib.contextmanager
def quiet_mujoco_warnings() -> Iterator[None]:
    """Routes MuJoCo's compiler warnings to :mod:`logging` while the block runs.

    MuJoCo's default warning handler prints to stderr and appends to ``MUJOCO_LOG.TXT`` in the
    working directory (HalfCheetah's XML triggers a ``settotalmass`` deprecation warning on every
    load). Inside this block the warnings go to this module's logger at DEBUG level instead; the
    previous handler is restored on exit, so no global state outlives the call. A handler the
    user installed is left alone.

    Examples:
        >>> import gymnasium as gym
        >>> from torchrl_mbmf.envs.physics_info import quiet_mujoco_warnings
        >>> with quiet_mujoco_warnings():
        ...     env = gym.make("HalfCheetah-v5")
        >>> env.close()
    """
    previous = mujoco.get_mju_user_warning()
    if previous is not None:
        yield
        return
    mujoco.set_mju_user_warning(lambda msg: logger.debug("MuJoCo: %s", msg))
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(None)


class PhysicsInfo(gym.Wrapper):
    """Adds torso velocity, head height and joint quantities of a MuJoCo env to its ``info``.

    The thesis' HeadPen and ShinPen rewards and its gait analysis need physics that the
    observation does not carry (the head is a geom of the torso, its height is not observed).
    This wrapper reads them from ``env.unwrapped.data`` after every ``reset`` and ``step`` and
    writes float64 arrays into ``info``, all of them of the state the call returns (after a
    step, MuJoCo's kinematics are recomputed first: ``mj_step`` leaves them at the pose before
    its last substep):

    - ``forward_velocity`` (1,): the env's own ``info["x_velocity"]`` (0 at reset);
    - ``head_height`` (1,): world z of the ``head`` geom minus its z in the model's reference
      pose (``qpos0``), so -0.2 means the head dropped 20 cm below where it starts;
    - ``joint_angles`` / ``joint_velocities`` (n,): ``qpos`` / ``qvel`` of the actuated joints;
    - ``actuator_torques`` (n,): ``data.actuator_force`` (torque applied at this step).

    Args:
        env: a gymnasium MuJoCo env (HalfCheetah by default names).

    Keyword Args:
        joints: names of the joints to report, in order. Defaults to HalfCheetah's six actuated
            joints.
        head_geom: name of the geom whose height is reported, or ``None`` to skip it.
            Defaults to ``"head"``.

    Examples:
        >>> import gymnasium as gym
        >>> from torchrl_mbmf.envs.physics_info import PhysicsInfo, quiet_mujoco_warnings
        >>> with quiet_mujoco_warnings():
        ...     env = PhysicsInfo(gym.make("HalfCheetah-v5"))
        >>> _, info = env.reset(seed=0)
        >>> sorted(info)[:3]
        ['actuator_torques', 'forward_velocity', 'head_height']
        >>> abs(float(info["head_height"][0])) < 0.05
        True
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        joints: Sequence[str] = HALF_CHEETAH_JOINTS,
        head_geom: str | None = "head",
    ) -> None:
        super().__init__(env)
        model = self.unwrapped.model
        try:
            self._qpos_idx = np.array([model.jnt_qposadr[model.joint(j).id] for j in joints])
            self._qvel_idx = np.array([model.jnt_dofadr[model.joint(j).id] for j in joints])
        except KeyError as err:
            raise ValueError(
                f"joints={tuple(joints)!r} names a joint the MuJoCo model does not have ({err})"
            ) from err
        self._head_id: int | None = None
        self._head_z0 = 0.0
        if head_geom is not None:
            self._head_id = model.geom(head_geom).id
            data0 = mujoco.MjData(model)
            mujoco.mj_forward(model, data0)
            self._head_z0 = float(data0.geom_xpos[self._head_id, 2])

    @property
    def reference_head_height(self) -> float:
        """World z of the head geom in the model's reference pose (m)."""
        return self._head_z0

    def _physics(self, info: dict[str, Any], *, stepped: bool = False) -> dict[str, Any]:
        data = self.unwrapped.data
        info[FORWARD_VELOCITY_KEY] = np.array([float(info.get("x_velocity", 0.0))])
        if self._head_id is not None:
            if stepped:
                # After mj_step, geom_xpos still holds the pose before the last integration
                # substep; recompute the kinematics (positions only: cheap, and mj_step redoes
                # them from qpos anyway, so the dynamics are unchanged).
                mujoco.mj_kinematics(self.unwrapped.model, data)
            info[HEAD_HEIGHT_KEY] = np.array([data.geom_xpos[self._head_id, 2] - self._head_z0])
        info[JOINT_ANGLES_KEY] = data.qpos[self._qpos_idx].copy()
        info[JOINT_VELOCITIES_KEY] = data.qvel[self._qvel_idx].copy()
        info[ACTUATOR_TORQUES_KEY] = data.actuator_force.copy()
        return info

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        """Resets the wrapped env and adds the physics entries to ``info``."""
        obs, info = self.env.reset(**kwargs)
        return obs, self._physics(dict(info))

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Steps the wrapped env and adds the physics entries to ``info``."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, self._physics(dict(info), stepped=True)
