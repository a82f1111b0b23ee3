"""PhysicsInfo reports the physics of the state the step returns, not of the substep before."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np

from torchrl_mbmf.envs.physics_info import PhysicsInfo, quiet_mujoco_warnings


def test_head_height_is_that_of_the_returned_state():
    with quiet_mujoco_warnings():
        env = PhysicsInfo(
            gym.make("HalfCheetah-v5", exclude_current_positions_from_observation=False)
        )
    model = env.unwrapped.model
    head = model.geom("head").id
    fresh = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    obs, info = env.reset(seed=0)
    checked = 0
    for _ in range(400):
        obs, _, terminated, truncated, info = env.step(rng.uniform(-1, 1, size=6))
        # Independent: the 18-dim state is qpos (9) then qvel (9); pose a fresh MjData there.
        fresh.qpos[:] = obs[:9]
        fresh.qvel[:] = obs[9:]
        mujoco.mj_kinematics(model, fresh)
        expected = fresh.geom_xpos[head, 2] - env.reference_head_height
        np.testing.assert_allclose(info["head_height"][0], expected, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(info["joint_angles"], obs[3:9])
        checked += 1
        if terminated or truncated:
            obs, info = env.reset()
    assert checked == 400
    env.close()
