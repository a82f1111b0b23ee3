"""On a terminating task the recipe's agents bootstrap through truncations, never terminations.

Hopper's real env ends episodes with ``terminated`` (a fall) or ``truncated`` (the time limit);
PPO's GAE and SAC's targets must stop the return at the first and bootstrap at the second.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from torchrl.envs.utils import RandomPolicy

from torchrl_mbmf.envs import make_env
from torchrl_mbmf.trainers.agents import make_agent

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _agent_and_batch(method: str, update: str) -> tuple[object, TensorDictBase]:
    env = make_env("Hopper-v5", seed=0, max_episode_steps=25)
    algo = OmegaConf.load(CONFIGS / "algo" / f"{method}.yaml")
    algo.update = update
    torch.manual_seed(0)
    agent = make_agent(method, env, OmegaConf.create({method: algo}), torch.device("cpu"))
    # random actions: Hopper falls within its 25-step limit in some episodes, not in others
    batch = env.rollout(150, RandomPolicy(env.full_action_spec), break_when_any_done=False)
    nxt = batch["next"]
    assert nxt["terminated"].any() and (nxt["truncated"] & ~nxt["terminated"]).any()
    return agent, batch


def _reference_gae(batch, critic, gamma: float, lmbda: float, *, terminal_key: str):
    """GAE written out: bootstrap unless ``terminal_key``, restart the recursion at ``done``."""
    with torch.no_grad():
        value = critic(batch.clone())["state_value"][:, 0]
        next_value = critic(batch["next"].clone())["state_value"][:, 0]
    nxt = batch["next"]
    reward = nxt["reward"][:, 0]
    stop = nxt[terminal_key][:, 0].float()
    done = nxt["done"][:, 0].float()
    delta = reward + gamma * (1 - stop) * next_value - value
    advantage = torch.zeros_like(delta)
    running = torch.zeros(())
    for t in reversed(range(delta.shape[0])):
        running = delta[t] + gamma * lmbda * (1 - done[t]) * running
        advantage[t] = running
    return advantage


@pytest.mark.parametrize("update", ["fused", "stock"])
def test_ppo_advantage_stops_at_terminations_and_bootstraps_at_truncations(update):
    agent, batch = _agent_and_batch("ppo", update)
    gamma, lmbda = float(agent.gae.gamma), float(agent.gae.lmbda)
    expected = _reference_gae(batch, agent.critic, gamma, lmbda, terminal_key="terminated")
    if agent.fused is not None:
        advantage, _ = agent.fused.advantage(batch.clone())
    else:
        advantage = agent.gae(batch.clone())["advantage"]
    torch.testing.assert_close(advantage.reshape(-1), expected, rtol=1e-4, atol=1e-4)
    # the reference tells the two apart: treating every episode end as a termination differs
    wrong = _reference_gae(batch, agent.critic, gamma, lmbda, terminal_key="done")
    assert not torch.allclose(advantage.reshape(-1), wrong, rtol=1e-4, atol=1e-4)


def _q_loss(agent, batch: TensorDictBase, update: str) -> torch.Tensor:
    torch.manual_seed(1)  # the same next actions for every call
    if update == "stock":
        return agent.loss(batch.clone())["loss_qvalue"]
    keys = agent.step.batch_keys
    obs, action, reward, next_obs, terminated = (batch.get(k) for k in keys)
    return agent.step.losses(obs, action, reward[:, 0], next_obs, terminated[:, 0])[1]


@pytest.mark.parametrize("update", ["fused", "stock"])
def test_sac_target_ignores_the_next_state_after_a_termination_only(update):
    agent, batch = _agent_and_batch("sac", update)
    nxt = batch["next"]
    for rows, bootstraps in (
        (nxt["terminated"][:, 0], False),
        (nxt["truncated"][:, 0] & ~nxt["terminated"][:, 0], True),
    ):
        part = batch[rows]
        moved = part.clone()
        moved["next", "observation"] = moved["next", "observation"] + 5.0
        with torch.no_grad():
            same = torch.equal(_q_loss(agent, part, update), _q_loss(agent, moved, update))
        assert same != bootstraps
