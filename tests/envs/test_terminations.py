"""The known termination rules against Gymnasium's own ``terminated`` on real transitions."""

from __future__ import annotations

import warnings

import gymnasium as gym
import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.envs import make_gym_state_env
from torchrl_mbmf.envs.terminations import (
    HopperTermination,
    NeverTerminates,
    termination_rule,
    termination_rule_of_env,
)

X_FIRST = {"exclude_current_positions_from_observation": False}
SEEDS = (0, 1, 2)
STEPS = 700  # per seed: random actions, resets after each termination (falls included)

CASES = [
    ("Hopper-v5", X_FIRST, True),
    ("Hopper-v5", {"exclude_current_positions_from_observation": True}, True),
    ("Walker2d-v5", X_FIRST, True),
    ("Walker2d-v5", {"exclude_current_positions_from_observation": True}, True),
    ("Ant-v5", X_FIRST, True),
    ("Ant-v5", {**X_FIRST, "include_cfrc_ext_in_observation": False}, True),
    ("Humanoid-v5", X_FIRST, True),
    ("InvertedPendulum-v5", {}, True),
    ("InvertedDoublePendulum-v5", {}, True),
    ("HalfCheetah-v5", X_FIRST, False),
    ("Swimmer-v5", X_FIRST, False),
    ("Reacher-v5", {}, False),
    ("Pusher-v5", {}, False),
    ("HumanoidStandup-v5", X_FIRST, False),
    ("Pendulum-v1", {}, False),
]


def _real_transitions(env_id: str, kwargs: dict, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Next observations (float32, as the package's state) and Gymnasium's ``terminated``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = gym.make(env_id, **kwargs)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    states, terminated = [], []
    for _ in range(STEPS):
        obs, _, term, trunc, _ = env.step(env.action_space.sample())
        states.append(torch.as_tensor(obs, dtype=torch.float32))
        terminated.append(bool(term))
        if term or trunc:
            env.reset()
    env.close()
    return torch.stack(states), torch.tensor(terminated)


@pytest.mark.parametrize(("env_id", "kwargs", "terminates"), CASES)
def test_rule_equals_gymnasium_terminated(env_id: str, kwargs: dict, terminates: bool) -> None:
    rule = termination_rule(env_id, **kwargs)
    compared = falls = 0
    for seed in SEEDS:
        states, terminated = _real_transitions(env_id, kwargs, seed)
        predicted = rule(states)  # all transitions of the seed at once: [N, S] -> [N]
        assert predicted.dtype == torch.bool and predicted.shape == terminated.shape
        mismatches = (predicted != terminated).nonzero().flatten().tolist()
        assert not mismatches, f"{env_id} seed {seed}: rule differs at steps {mismatches[:10]}"
        compared += len(terminated)
        falls += int(terminated.sum())
    assert compared == len(SEEDS) * STEPS
    if terminates:  # the comparison covers terminal transitions too, not only healthy ones
        assert falls > 0, f"{env_id}: no termination among {compared} transitions"
    else:
        assert falls == 0


def test_rule_of_the_package_env_reads_its_layout() -> None:
    # the default gymnasium layout drops x; the package's layout keeps it: both read right
    for kwargs in ({"layout": False}, X_FIRST):
        env = make_gym_state_env("Hopper-v5", seed=0, **kwargs)
        rule = termination_rule_of_env(env)
        with set_exploration_type(ExplorationType.RANDOM):
            td = env.rollout(300, break_when_any_done=False)
        terminated = td["next", "terminated"][..., 0]
        assert bool(terminated.any())
        assert torch.equal(rule(td["next", "state"]), terminated)


def test_rule_respects_constructor_arguments() -> None:
    state = torch.zeros(12)
    state[1] = 0.6  # below Hopper's default 0.7
    assert bool(termination_rule("Hopper-v5")(state))
    assert not bool(termination_rule("Hopper-v5", healthy_z_range=(0.5, 2.0))(state))
    assert not bool(termination_rule("Hopper-v5", terminate_when_unhealthy=False)(state))
    assert bool(termination_rule("Hopper-v5", forward_reward_weight=2.0)(state))  # ignored


def test_never_terminating_tasks_and_unknown_task_warns_once() -> None:
    for env_id in ("HalfCheetah-v5", "Swimmer-v4", "Pendulum-v1", "HumanoidStandup-v5"):
        assert isinstance(termination_rule(env_id), NeverTerminates)
    with pytest.warns(UserWarning, match=r"'MyTask-v0'.*termination_fn"):
        rule = termination_rule("MyTask-v0")
    assert isinstance(rule, NeverTerminates)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        termination_rule("MyTask-v0")  # once only


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="healthy_z_range"):
        HopperTermination(healthy_z_range=(1.0, 0.5))
    with pytest.raises(ValueError, match="at least 3 entries"):
        HopperTermination()(torch.zeros(4, 2))
    with pytest.raises(TypeError, match="env_id"):
        termination_rule(3)  # type: ignore[arg-type]
