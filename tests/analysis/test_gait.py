from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from torchrl_mbmf.analysis.gait import (
    frame_strip,
    gait_metrics,
    plot_gait,
    record_gait,
    render_states,
)
from torchrl_mbmf.envs import make_half_cheetah_env
from torchrl_mbmf.envs.physics_info import quiet_mujoco_warnings
from torchrl_mbmf.modules import make_ppo_actor_critic


def test_power_matches_mujoco_independently():
    env = make_half_cheetah_env(seed=0)
    actor, _ = make_ppo_actor_critic(env)
    td = record_gait(env, actor, steps=30)
    metrics = gait_metrics(td)
    # Independent reference: replay the same actions in raw gymnasium and read MuJoCo's data.
    with quiet_mujoco_warnings():
        raw = gym.make("HalfCheetah-v5", exclude_current_positions_from_observation=False)
    raw.reset(seed=0)
    raw.reset()
    data = raw.unwrapped.data
    power, heights = [], []
    for a in td["action"].double().numpy():
        raw.step(a)
        power.append(
            [data.actuator_force[i] * data.joint(n).qvel[0] for i, n in enumerate(metrics.joints)]
        )
        heights.append(data.qpos[1])
    np.testing.assert_allclose(metrics.average_power, np.mean(power, 0), atol=1e-3, rtol=1e-4)
    np.testing.assert_allclose(metrics.torso_height, heights, atol=1e-5)
    assert metrics.distance == pytest.approx(
        metrics.x_position[-1] - float(td["state"][0, 0]), abs=1e-6
    )
    assert set(metrics.to_dict()) >= {"average_power", "torso_height", "x_position"}


def test_errors():
    env = make_half_cheetah_env(seed=0)
    with pytest.raises(ValueError, match="steps"):
        record_gait(env, None, steps=0)
    with pytest.raises(ValueError, match=r"\[T\]"):
        gait_metrics(make_half_cheetah_env(num_envs=2).rollout(3))
    with pytest.raises(ValueError, match="frames"):
        frame_strip(np.zeros((3, 4)))


def test_plot_writes_png(tmp_path):
    metrics = gait_metrics(make_half_cheetah_env(seed=1).rollout(10))
    out = tmp_path / "gait.png"
    plot_gait(metrics, str(out), title="random policy")
    assert out.stat().st_size > 1000


def test_render_states_offscreen():
    states = make_half_cheetah_env(seed=0).rollout(3)["next", "state"]
    try:
        frames = render_states(states, width=64, height=48)
    except Exception as err:  # no OpenGL backend on this machine
        pytest.skip(f"offscreen rendering unavailable: {err}")
    assert frames.shape == (3, 48, 64, 3)
    assert frames.dtype == np.uint8
    assert frames.std() > 0  # not a blank image
    assert frame_strip(frames, num=3).shape == (48, 192, 3)
    with pytest.raises(ValueError, match="qpos then qvel"):
        render_states(torch.zeros(2, 17))
