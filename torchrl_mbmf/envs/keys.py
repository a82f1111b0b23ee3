"""Tensordict keys of the real and the learned environments (see :mod:`torchrl_mbmf.keys`)."""

from __future__ import annotations

from torchrl_mbmf.keys import (
    ACTUATOR_TORQUES_KEY,
    FORWARD_VELOCITY_KEY,
    HEAD_HEIGHT_KEY,
    JOINT_ANGLES_KEY,
    JOINT_VELOCITIES_KEY,
    OBSERVATION_KEY,
    STATE_KEY,
)

__all__ = [
    "ACTUATOR_TORQUES_KEY",
    "FORWARD_VELOCITY_KEY",
    "HEAD_HEIGHT_KEY",
    "JOINT_ANGLES_KEY",
    "JOINT_VELOCITIES_KEY",
    "OBSERVATION_KEY",
    "STATE_KEY",
]
