from __future__ import annotations

import os

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from torchrl_mbmf.envs import (
    FORWARD_VELOCITY_KEY,
    HEAD_HEIGHT_KEY,
    JOINT_ANGLES_KEY,
    OBSERVATION_KEY,
    STATE_KEY,
    make_env,
    make_gym_state_env,
    make_half_cheetah_env,
)


@pytest.mark.parametrize("reward", ["default", "head_pen", "shin_pen"])
def test_keys_shapes_and_specs(reward):
    env = make_half_cheetah_env(reward, seed=0)
    check_env_specs(env)
    td = env.rollout(4)
    assert td["next", STATE_KEY].shape == (4, 18)
    assert td["next", OBSERVATION_KEY].shape == (4, 17)
    assert td["next", STATE_KEY].dtype == torch.float32
    assert td["next", "reward"].shape == (4, 1)
    torch.testing.assert_close(td["next", OBSERVATION_KEY], td["next", STATE_KEY][..., 1:])
    torch.testing.assert_close(td[OBSERVATION_KEY], td[STATE_KEY][..., 1:])
    # episode return and step count are tracked
    torch.testing.assert_close(td["next", "episode_reward"][-1], td["next", "reward"].sum(0))
    assert td["next", "step_count"][-1].item() == 4
    for key in (FORWARD_VELOCITY_KEY, HEAD_HEIGHT_KEY, JOINT_ANGLES_KEY):
        assert key in td["next"]


def test_batched_env_same_keys():
    env = make_half_cheetah_env("shin_pen", num_envs=3, seed=0)
    assert env.batch_size == (3,)
    check_env_specs(env)
    td = env.rollout(5)
    assert td.batch_size == (3, 5)
    assert td["next", STATE_KEY].shape == (3, 5, 18)
    assert td["next", OBSERVATION_KEY].shape == (3, 5, 17)
    assert td["next", JOINT_ANGLES_KEY].shape == (3, 5, 6)
    # copies are seeded differently
    assert not torch.equal(td[STATE_KEY][0, 0], td[STATE_KEY][1, 0])


def test_state_starts_with_x_position():
    env = make_half_cheetah_env(seed=0)
    td = env.rollout(50)
    x = td["next", STATE_KEY][:, 0]
    dx = torch.diff(torch.cat([td[STATE_KEY][:1, 0], x]))
    # x velocity from MuJoCo equals the finite difference of the state's first entry
    torch.testing.assert_close(dx / 0.05, td["next", FORWARD_VELOCITY_KEY][:, 0], atol=2e-3, rtol=0)


def test_seed_reproducible():
    a = make_half_cheetah_env(seed=3).reset()[STATE_KEY]
    b = make_half_cheetah_env(seed=3).reset()[STATE_KEY]
    c = make_half_cheetah_env(seed=4).reset()[STATE_KEY]
    torch.testing.assert_close(a, b)
    assert not torch.equal(a, c)


def test_unknown_reward_lists_valid_names():
    with pytest.raises(ValueError, match=r"'nope'.*\['default', 'head_pen', 'shin_pen'\]"):
        make_half_cheetah_env("nope")
    with pytest.raises(ValueError, match="num_envs"):
        make_half_cheetah_env(num_envs=0)
    with pytest.raises(ValueError, match="exclude_current_positions"):
        make_half_cheetah_env(exclude_current_positions_from_observation=True)


def test_no_mujoco_log_in_working_dir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    make_half_cheetah_env().rollout(2)
    assert not os.path.exists(tmp_path / "MUJOCO_LOG.TXT")


def test_make_env_dispatch():
    assert make_env("HalfCheetah-v5", reward="head_pen").observation_spec[STATE_KEY].shape == (18,)
    pendulum = make_env("Pendulum-v1", seed=0)
    check_env_specs(pendulum)
    assert pendulum.observation_spec[STATE_KEY].shape == (3,)
    with pytest.raises(ValueError, match="HalfCheetah-v5 only"):
        make_env("Pendulum-v1", reward="shin_pen")
    with pytest.raises(ValueError, match="valid rewards"):
        make_env("Pendulum-v1", reward="bad")


def test_gym_state_env_batched_pendulum():
    env = make_gym_state_env("Pendulum-v1", num_envs=2, seed=0, drop_state_dims=(2,))
    check_env_specs(env)
    td = env.rollout(3)
    assert td["next", OBSERVATION_KEY].shape == (2, 3, 2)
    torch.testing.assert_close(td["next", OBSERVATION_KEY], td["next", STATE_KEY][..., :2])
