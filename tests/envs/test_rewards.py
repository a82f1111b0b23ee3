"""Reward transforms checked against gymnasium's own reward and MuJoCo's data."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, StepCounter, TransformedEnv

from torchrl_mbmf.envs import (
    STATE_KEY,
    DefaultReward,
    HeadPenReward,
    ShinPenReward,
    make_half_cheetah_env,
    make_reward,
)
from torchrl_mbmf.envs.physics_info import quiet_mujoco_warnings

STEPS = 1000


def _replay_in_gymnasium(actions: np.ndarray, seed: int):
    """Steps raw gymnasium HalfCheetah-v5 with the given actions; returns per-step physics."""
    with quiet_mujoco_warnings():
        env = gym.make("HalfCheetah-v5", exclude_current_positions_from_observation=False)
    env.reset(seed=seed)  # what TorchRL's set_seed does; the rollout then resets once more
    obs0, _ = env.reset()
    model, data = env.unwrapped.model, env.unwrapped.data
    # Head height in the reference pose, independently: torso body z + head geom z offset.
    head_z0 = model.body("torso").pos[2] + model.geom("head").pos[2]
    out = {"reward": [], "x_velocity": [], "head_drop": [], "front": [], "obs": [obs0]}
    for a in actions:
        obs, reward, _, _, info = env.step(a)
        out["reward"].append(reward)
        out["x_velocity"].append(info["x_velocity"])
        # the head height of the returned state (mj_step leaves geom_xpos one substep behind)
        mujoco.mj_kinematics(model, data)
        out["head_drop"].append(data.geom("head").xpos[2] - head_z0)
        out["front"].append([data.joint(n).qpos[0] for n in ("fthigh", "fshin", "ffoot")])
        out["obs"].append(obs)
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def rollouts():
    """One 1000-step random rollout per reward, and gymnasium's replay of the same actions."""
    result = {}
    for name in ("default", "head_pen", "shin_pen"):
        env = make_half_cheetah_env(name, seed=7)
        td = env.rollout(STEPS, break_when_any_done=False)
        ref = _replay_in_gymnasium(td["action"].double().numpy(), seed=7)
        result[name] = (td, ref)
    return result


def test_default_reward_matches_gymnasium(rollouts):
    td, ref = rollouts["default"]
    assert td.batch_size == (STEPS,)
    # same trajectory as gymnasium's
    np.testing.assert_allclose(td[STATE_KEY][0].numpy(), ref["obs"][0], atol=1e-6)
    np.testing.assert_allclose(td["next", STATE_KEY].numpy(), ref["obs"][1:], atol=1e-4, rtol=1e-5)
    np.testing.assert_allclose(td["next", "reward"][:, 0].numpy(), ref["reward"], atol=1e-5, rtol=0)


def test_head_pen_matches_mujoco(rollouts):
    td, ref = rollouts["head_pen"]
    expected = ref["x_velocity"] - 0.1 * (ref["head_drop"] < -0.2)
    np.testing.assert_allclose(td["next", "reward"][:, 0].numpy(), expected, atol=1e-5, rtol=0)
    np.testing.assert_allclose(
        td["next", "head_height"][:, 0].numpy(), ref["head_drop"], atol=1e-5, rtol=0
    )
    # a threshold that random motion crosses exercises both branches of the penalty
    t = HeadPenReward(threshold=-0.02, penalty_weight=0.5)
    recomputed = t(td.clone())["next", "reward"][:, 0].numpy()
    penalised = ref["head_drop"] < -0.02
    assert 0 < penalised.sum() < STEPS
    np.testing.assert_allclose(recomputed, ref["x_velocity"] - 0.5 * penalised, atol=1e-5, rtol=0)


def test_shin_pen_matches_mujoco(rollouts):
    td, ref = rollouts["shin_pen"]
    front = ref["front"]
    penalty = 0.1 * (front[:, 0] > 0.2) + 0.1 * (front[:, 1] > 0) + 0.1 * (front[:, 2] > 0)
    assert 0 < (penalty > 0).sum() < STEPS
    np.testing.assert_allclose(
        td["next", "reward"][:, 0].numpy(), ref["x_velocity"] - penalty, atol=1e-5, rtol=0
    )


def test_rewards_differ_only_in_penalty(rollouts):
    td, ref = rollouts["default"]
    ctrl = 0.1 * (td["action"].double() ** 2).sum(-1).numpy()
    np.testing.assert_allclose(
        td["next", "reward"][:, 0].numpy() + ctrl, ref["x_velocity"], atol=1e-5, rtol=0
    )


@pytest.mark.parametrize("name", ["default", "head_pen", "shin_pen"])
def test_in_compose_transformed_env_and_batched(name):
    base = make_half_cheetah_env(name, num_envs=2, seed=1)
    # the reward is part of the factory's Compose; also stack another Compose on top
    env = TransformedEnv(base, Compose(StepCounter(step_count_key="outer_count")))
    td = env.rollout(20)
    assert td["next", "reward"].shape == (2, 20, 1)
    nxt = td["next"]
    expected = make_reward(name).compute(td, nxt)
    torch.testing.assert_close(nxt["reward"], expected)
    if name == "default":
        manual = nxt["forward_velocity"] - 0.1 * (td["action"] ** 2).sum(-1, keepdim=True)
    elif name == "head_pen":
        manual = nxt["forward_velocity"] - 0.1 * (nxt["head_height"] < -0.2).float()
    else:
        ang = nxt["joint_angles"]
        thr = torch.tensor([0.2, 0.0, 0.0])
        manual = nxt["forward_velocity"] - 0.1 * (ang[..., 3:] > thr).float().sum(-1, keepdim=True)
    torch.testing.assert_close(nxt["reward"], manual, atol=1e-5, rtol=0)


@pytest.mark.parametrize("cls", [DefaultReward, HeadPenReward, ShinPenReward])
def test_on_replay_buffer_samples(cls):
    env = make_half_cheetah_env(cls.name, seed=2)
    td = env.rollout(64)
    stored = td.clone()
    stored["next", "reward"].zero_()
    rb = ReplayBuffer(storage=LazyTensorStorage(64), batch_size=16)
    rb.append_transform(cls())
    rb.extend(stored)
    assert (rb.storage[:]["next", "reward"] == 0).all()  # writing stores data as it is
    sample, info = rb.sample(return_info=True)
    torch.testing.assert_close(sample["next", "reward"], td["next", "reward"][info["index"]])


def test_constructor_arguments_and_keys():
    nxt = TensorDict(
        vel=torch.tensor([[2.0]]),
        angles=torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.5, 0.0]]),
        batch_size=[1],
    )
    td = TensorDict(next=nxt, batch_size=[1])
    t = ShinPenReward(
        thresholds=(0.4,),
        penalty_weights=(1.0,),
        joint_indices=(4,),
        forward_weight=0.5,
        joint_angles_key="angles",
        velocity_key="vel",
        reward_key="r",
    )
    assert t(td)["next", "r"].item() == pytest.approx(0.5 * 2.0 - 1.0)
    with pytest.raises(ValueError, match="same length"):
        ShinPenReward(thresholds=(0.1, 0.2), penalty_weights=(0.1,), joint_indices=(3,))
    with pytest.raises(ValueError, match="valid rewards"):
        make_reward("HeadPen")
    with pytest.raises(KeyError, match="'next'"):
        DefaultReward()(TensorDict(action=torch.zeros(6)))
    assert make_reward("head_pen").parameters_dict() == {
        "name": "head_pen",
        "forward_weight": 1.0,
        "threshold": -0.2,
        "penalty_weight": 0.1,
    }


def test_physics_info_reference_height_matches_model():
    with quiet_mujoco_warnings():
        env = gym.make("HalfCheetah-v5")
    model = env.unwrapped.model
    from torchrl_mbmf.envs import PhysicsInfo

    wrapped = PhysicsInfo(env)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert wrapped.reference_head_height == pytest.approx(data.geom("head").xpos[2])
    assert wrapped.reference_head_height == pytest.approx(0.8)
    with pytest.raises(ValueError, match="joint"):
        PhysicsInfo(env, joints=("nope",))


@pytest.mark.parametrize(
    ("cls", "kwargs", "message"),
    [
        (HeadPenReward, {"threshold": float("nan")}, "threshold must be a finite number, got nan"),
        (HeadPenReward, {"threshold": "low"}, "threshold must be a finite number, got 'low'"),
        (HeadPenReward, {"penalty_weight": -0.1}, "penalty_weight must be a number >= 0"),
        (HeadPenReward, {"forward_weight": float("inf")}, "forward_weight must be a finite"),
        (DefaultReward, {"ctrl_cost_weight": float("nan")}, "ctrl_cost_weight must be a number"),
        (ShinPenReward, {"thresholds": (0.2, float("nan"), 0.0)}, r"thresholds\[1\] must be"),
        (ShinPenReward, {"penalty_weights": (0.1, -1.0, 0.1)}, r"penalty_weights\[1\] must be"),
        (ShinPenReward, {"joint_indices": (3, 4, -1)}, r"joint_indices\[2\] must be"),
    ],
)
def test_reward_constructors_check_their_arguments(cls, kwargs, message):
    with pytest.raises(ValueError, match=message):
        cls(**kwargs)


def _physics(batch, **fields):
    next_td = TensorDict({"forward_velocity": torch.ones(*batch, 1), **fields}, batch_size=batch)
    return TensorDict(action=torch.zeros(*batch, 6), next=next_td, batch_size=batch)


@pytest.mark.parametrize(
    ("reward", "fields", "message"),
    [
        (HeadPenReward(), {"head_height": torch.tensor([[float("nan")], [0.0]])}, "NaN or Inf"),
        (HeadPenReward(), {"head_height": torch.zeros(2, 2)}, r"shape \[2, 1\] or \[2\]"),
        (ShinPenReward(), {"joint_angles": torch.full((2, 6), float("inf"))}, "NaN or Inf"),
        (DefaultReward(), {"forward_velocity": torch.ones(2, 3)}, "got shape \\[2, 3\\]"),
    ],
)
def test_rewards_refuse_non_finite_or_misshaped_physics(reward, fields, message):
    td = _physics((2,), **fields)
    with pytest.raises(ValueError, match=message):
        reward(td)


def test_rewards_accept_physics_without_the_trailing_one():
    td = _physics((3,), head_height=torch.tensor([-0.5, 0.0, 0.1]))
    td["next", "forward_velocity"] = torch.ones(3)
    assert HeadPenReward()(td)["next", "reward"].squeeze(-1).tolist() == pytest.approx(
        [0.9, 1.0, 1.0]
    )
