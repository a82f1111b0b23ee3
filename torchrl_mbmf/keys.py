"""Tensordict keys shared by the real and the learned environments, the modules and the trainers."""

from __future__ import annotations

#: Full thesis state: the x position of the torso followed by the 17 standard observations
#: (18 dims for HalfCheetah). The world model predicts the delta of this vector.
STATE_KEY: str = "state"

#: What policies and critics see: the state without the absolute x position (17 dims for
#: HalfCheetah). The learned environment keeps it in sync with :data:`STATE_KEY`.
OBSERVATION_KEY: str = "observation"

#: Forward velocity of the torso (m/s), read from MuJoCo by the physics info reader.
FORWARD_VELOCITY_KEY: str = "forward_velocity"

#: Height of the head relative to its height in the model's initial pose (m).
HEAD_HEIGHT_KEY: str = "head_height"

#: Angles (rad) of the six actuated joints: bthigh, bshin, bfoot, fthigh, fshin, ffoot.
JOINT_ANGLES_KEY: str = "joint_angles"

#: Angular velocities (rad/s) of the six actuated joints, same order as :data:`JOINT_ANGLES_KEY`.
JOINT_VELOCITIES_KEY: str = "joint_velocities"

#: Torques (N m) applied by the six actuators at this step, same order as the action.
ACTUATOR_TORQUES_KEY: str = "actuator_torques"

__all__ = [
    "ACTUATOR_TORQUES_KEY",
    "FORWARD_VELOCITY_KEY",
    "HEAD_HEIGHT_KEY",
    "JOINT_ANGLES_KEY",
    "JOINT_VELOCITIES_KEY",
    "OBSERVATION_KEY",
    "STATE_KEY",
]
