"""Every task as a real env: state layout, Gymnasium's rewards and episode ends, keys, bounds."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.data import Bounded, Unbounded
from torchrl.envs import Compose, DoubleToFloat, GymEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_mbmf.envs import (
    TASK_LAYOUTS,
    action_bounds,
    env_metadata,
    make_env,
    make_gym_state_env,
    task_layout,
)

#: The tasks of ``configs/env`` (HalfCheetah has its own tests).
CONFIG_TASKS = ["Hopper-v5", "Walker2d-v5", "Ant-v5", "InvertedPendulum-v5", "Pendulum-v1"]


def _gym_env(env_id: str, **kwargs) -> gym.Env:
    """The reference: Gymnasium's env as the layout makes it, with no TorchRL in between."""
    layout = task_layout(env_id)
    return gym.make(env_id, **(layout.make_kwargs(kwargs) if layout else kwargs))


@pytest.mark.parametrize("env_id", sorted(TASK_LAYOUTS))
def test_state_holds_the_positions_the_layout_names(env_id):
    layout = task_layout(env_id)
    env = make_env(env_id, seed=0)
    td = env.rollout(3)
    state, obs = td["next", "state"][-1], td["next", "observation"][-1]
    assert state.dtype == torch.float32
    gym_env = env.base_env._env.unwrapped
    if layout.x_index is not None:  # the root's (or the cart's) x is MuJoCo's qpos[0]
        assert state[layout.x_index].item() == pytest.approx(gym_env.data.qpos[0], abs=1e-6)
    if layout.y_index is not None:
        assert state[layout.y_index].item() == pytest.approx(gym_env.data.qpos[1], abs=1e-6)
    keep = [i for i in range(state.shape[-1]) if i not in layout.hidden_dims]
    assert torch.equal(obs, state[keep])
    # the state is Gymnasium's observation with the positions kept: one more dim per position
    plain = gym.make(env_id).observation_space.shape[-1]
    assert state.shape[-1] == plain + len(layout.hidden_dims) == layout.state_dim


@pytest.mark.parametrize("env_id", sorted(TASK_LAYOUTS))
def test_make_gym_state_env_builds_the_recipes_layout(env_id):
    """The lower-level builder gives the state and observation ``make_env`` (the recipes) gives."""
    layout = task_layout(env_id)
    plain, recipe = make_gym_state_env(env_id, seed=0), make_env(env_id, seed=0)
    for key in ("state", "observation"):
        assert (
            plain.full_observation_spec_unbatched[key]
            == recipe.full_observation_spec_unbatched[key]
        ), key
    torch.manual_seed(0)
    a = plain.rollout(3)
    torch.manual_seed(0)
    b = recipe.rollout(3)
    for key in ("state", "observation", ("next", "state"), ("next", "observation")):
        assert torch.equal(a[key], b[key]), key
    # layout=False: Gymnasium's own observation, all of it shown to the policy
    own = make_gym_state_env(env_id, layout=False).full_observation_spec_unbatched
    assert own["state"].shape[-1] == gym.make(env_id).observation_space.shape[-1]
    assert own["observation"].shape == own["state"].shape
    if layout.gym_kwargs:
        with pytest.raises(ValueError, match="pass layout=False"):
            make_gym_state_env(env_id, exclude_current_positions_from_observation=True)


@pytest.mark.parametrize("env_id", CONFIG_TASKS)
def test_config_tasks_pass_check_env_specs_with_gymnasium_action_bounds(env_id):
    env = make_env(env_id, seed=0)
    check_env_specs(env)
    space = gym.make(env_id).action_space
    assert action_bounds(env) == (float(space.low.min()), float(space.high.max()))


def _step_both(env_id: str, num_envs: int, steps: int, max_episode_steps: int):
    """Steps ``make_env`` and Gymnasium's own env with the same actions; yields both outputs."""
    seed = 5
    env = make_env(env_id, num_envs=num_envs, seed=seed, max_episode_steps=max_episode_steps)
    refs = [_gym_env(env_id, max_episode_steps=max_episode_steps) for _ in range(num_envs)]
    for i, ref in enumerate(refs):
        # copy i is seeded seed + i; TorchRL's set_seed resets once, its first reset draws again
        ref.reset(seed=seed + i)
        ref.reset()
    space = refs[0].action_space
    rng = np.random.default_rng(0)
    td = env.reset()
    batch = td.batch_size
    for _ in range(steps):
        actions = rng.uniform(space.low, space.high, (num_envs, *space.shape)).astype(np.float32)
        td["action"] = torch.from_numpy(actions).reshape(*batch, *space.shape)
        out, td = env.step_and_maybe_reset(td)
        nxt = out["next"].reshape(num_envs)
        ended = []
        for i, ref in enumerate(refs):
            obs, reward, terminated, truncated, _ = ref.step(actions[i])
            yield nxt[i], (obs, reward, terminated, truncated)
            ended.append(terminated or truncated)
            if ended[-1]:
                ref.reset()
        if num_envs > 1 and all(ended):
            # every copy ended at once: on top of the vector env's own auto-reset, TorchRL
            # resets the whole env, so each copy starts from its next draw
            for ref in refs:
                ref.reset()


@pytest.mark.parametrize(
    ("env_id", "num_envs", "time_limit"),
    [
        ("Hopper-v5", 1, 40),
        ("Hopper-v5", 2, 40),
        ("Walker2d-v5", 1, 40),
        ("InvertedPendulum-v5", 1, 6),  # random actions topple it in a few steps
    ],
)
def test_rewards_and_episode_ends_are_gymnasium_own(env_id, num_envs, time_limit):
    """Terminated when the task says so, truncated at its time limit, as Gymnasium reports."""
    ends = {"terminated": 0, "truncated": 0}
    for nxt, (obs, reward, terminated, truncated) in _step_both(env_id, num_envs, 150, time_limit):
        np.testing.assert_allclose(nxt["state"].numpy(), obs, rtol=1e-5, atol=1e-5)
        # the task's own reward, healthy reward included
        assert nxt["reward"].item() == pytest.approx(reward, rel=1e-5, abs=1e-5)
        assert bool(nxt["terminated"]) == terminated
        assert bool(nxt["truncated"]) == truncated
        assert bool(nxt["done"]) == (terminated or truncated)
        ends["terminated"] += terminated
        ends["truncated"] += truncated
    assert ends["terminated"] > 0 and ends["truncated"] > 0, ends


@pytest.mark.parametrize("reward", ["head_pen", "shin_pen"])
@pytest.mark.parametrize("env_id", ["Hopper-v5", "Pendulum-v1"])
def test_thesis_rewards_are_refused_on_other_tasks(env_id, reward):
    with pytest.raises(ValueError, match=f"reward='{reward}'.*HalfCheetah-v5 only"):
        make_env(env_id, reward=reward)


def test_positions_cannot_be_left_out_of_a_known_task_state():
    with pytest.raises(ValueError, match="exclude_current_positions_from_observation=True"):
        make_env("Walker2d-v5", exclude_current_positions_from_observation=True)
    with pytest.raises(ValueError, match="exclude_current_positions_from_observation=True"):
        make_env("HalfCheetah-v5", exclude_current_positions_from_observation=True)


def test_unknown_task_keeps_its_observation_as_the_state():
    assert task_layout("MountainCarContinuous-v0") is None
    td = make_env("MountainCarContinuous-v0", seed=0).rollout(2)
    assert torch.equal(td["state"], td["observation"])


@pytest.mark.parametrize("env_id", ["Hopper-v5", "HalfCheetah-v5"])
def test_state_and_observation_keys_are_configurable(env_id):
    env = make_env(env_id, seed=0, state_key="full_state", observation_key="policy_obs")
    check_env_specs(env)
    td = env.rollout(2)
    assert "state" not in td and "observation" not in td
    assert torch.equal(td["policy_obs"], td["full_state"][..., 1:])


def test_one_key_for_state_and_observation_is_refused():
    with pytest.raises(ValueError, match="state_key and observation_key must differ"):
        make_gym_state_env("Pendulum-v1", state_key="observation", observation_key="observation")


@pytest.mark.parametrize(
    "wrap",
    [
        lambda base: TransformedEnv(base, DoubleToFloat()),  # a single transform
        lambda base: TransformedEnv(base, Compose(DoubleToFloat(), Compose(StepCounter()))),
        lambda base: TransformedEnv(TransformedEnv(base, DoubleToFloat()), StepCounter()),
        lambda base: base,
    ],
)
def test_env_metadata_accepts_any_transform(wrap):
    assert env_metadata(wrap(GymEnv("Hopper-v5"))) == {
        "env_id": "Hopper-v5",
        "reward": {"name": "default"},
    }


def test_env_metadata_keeps_the_thesis_reward_behind_other_transforms():
    env = TransformedEnv(make_env("HalfCheetah-v5", reward="shin_pen"), StepCounter())
    assert env_metadata(env)["reward"]["name"] == "shin_pen"
    assert env_metadata(make_env("Hopper-v5", num_envs=2))["env_id"] == "Hopper-v5"


def test_env_metadata_names_what_it_expects():
    from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv

    with pytest.raises(ValueError, match=r"cannot find the Gymnasium id of .*GymEnv, GymWrapper"):
        env_metadata(ContinuousActionVecMockEnv())


def test_action_bounds_need_one_bounded_range():
    env = GymEnv("Hopper-v5")
    env.action_spec = Bounded(torch.tensor([-1.0, -2.0, -1.0]), torch.ones(3), (3,))
    with pytest.raises(ValueError, match="per-dimension bounds"):
        action_bounds(env)
    env.action_spec = Unbounded((3,))
    with pytest.raises(ValueError, match="needs a Bounded action spec"):
        action_bounds(env)


@pytest.mark.parametrize(
    ("env_id", "bounds"),
    [("Pendulum-v1", (-2.0, 2.0)), ("InvertedPendulum-v5", (-3.0, 3.0)), ("Hopper-v5", (-1, 1))],
)
@pytest.mark.parametrize("ensemble_size", [1, 2])
def test_recipe_world_model_takes_the_env_action_range(env_id, bounds, ensemble_size):
    from torchrl_mbmf.world_model.networks import make_world_model

    env = make_env(env_id)
    model = make_world_model(env, hidden_sizes=[8], ensemble_size=ensemble_size)
    assert (model.action_low, model.action_high) == bounds
    # the largest action and half of it are different inputs to the model: nothing clips them
    state = env.reset()["state"][None]
    high = torch.full((1, *env.action_spec.shape), bounds[1])
    assert not torch.equal(model(state, high)[0], model(state, high / 2)[0])


def test_recipe_world_model_refuses_a_float64_state_naming_double_to_float():
    from torchrl.envs import RenameTransform

    from torchrl_mbmf.world_model.networks import make_world_model

    env = TransformedEnv(GymEnv("Hopper-v5"), RenameTransform(["observation"], ["state"]))
    with pytest.raises(ValueError, match=r"'state' is torch.float64.*DoubleToFloat\(\)"):
        make_world_model(env, hidden_sizes=[8])
