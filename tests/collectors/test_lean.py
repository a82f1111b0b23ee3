import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import RandomPolicy

from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.envs import LearnedDynamicsEnv, make_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    PolicyGuidedMPCPlanner,
    make_ppo_actor_critic,
    make_sac_actor_critic,
)


def _batches(collector, count):
    out = []
    for batch in collector:
        out.append(batch.clone())
        if len(out) == count:
            break
    collector.shutdown()
    return out


def _collect(kind, env_id, reward, policy_kind, lean, frames=40, count=3):
    torch.manual_seed(0)
    env = make_env(env_id, reward=reward, seed=3, max_episode_steps=25)
    if policy_kind == "ppo":
        policy, _ = make_ppo_actor_critic(env, hidden_sizes=(16,))
    elif policy_kind == "ppo_normal":
        policy, _ = make_ppo_actor_critic(env, hidden_sizes=(16,), distribution="normal")
    elif policy_kind == "sac":
        policy, _ = make_sac_actor_critic(env, hidden_sizes=(16,))
    elif policy_kind == "random":
        policy = RandomPolicy(env.full_action_spec)
    else:
        state_dim = env.full_observation_spec_unbatched["state"].shape[-1]
        action_dim = env.full_action_spec_unbatched["action"].shape[-1]
        actor, _ = make_ppo_actor_critic(env, hidden_sizes=(16,))
        model = DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=(32, 32))
        policy = PolicyGuidedMPCPlanner(
            LearnedDynamicsEnv(model, env), actor, num_candidates=4, horizon=3
        )
    env.set_seed(11)
    torch.manual_seed(1)
    if lean:
        collector = LeanCollector(env, policy, frames_per_batch=frames)
    else:
        collector = Collector(
            env,
            policy,
            frames_per_batch=frames,
            total_frames=-1,
            auto_register_policy_transforms=False,
        )
    return _batches(collector, count)


CASES = [
    ("HalfCheetah-v5", "default", "ppo"),
    ("HalfCheetah-v5", "head_pen", "ppo_normal"),
    ("HalfCheetah-v5", "shin_pen", "sac"),
    ("HalfCheetah-v5", "default", "random"),
    ("HalfCheetah-v5", "head_pen", "planner"),
    ("Pendulum-v1", "default", "ppo"),
    ("Pendulum-v1", "default", "random"),
    # tasks that terminate (Gymnasium's health rules) inside the batches
    ("Hopper-v5", "default", "ppo"),
    ("InvertedPendulum-v5", "default", "sac"),
]


@pytest.mark.parametrize(("env_id", "reward", "policy_kind"), CASES)
def test_lean_collector_equals_stock_collector(env_id, reward, policy_kind):
    stock = _collect("stock", env_id, reward, policy_kind, lean=False)
    lean = _collect("lean", env_id, reward, policy_kind, lean=True)
    for s, f in zip(stock, lean, strict=True):
        assert set(s.keys(True, True)) == set(f.keys(True, True))
        for key in s.keys(True, True):
            a, b = s.get(key), f.get(key)
            assert a.dtype == b.dtype and a.shape == b.shape, key
            if key == "action_log_prob":
                # the same distribution's log_prob, over the whole batch instead of one row per
                # step: vectorised and scalar float32 kernels differ in the last bits, which
                # atanh amplifies for actions clamped at the bounds (up to ~5e-3 seen there)
                torch.testing.assert_close(a, b, rtol=1e-3, atol=2e-2, msg=str(key))
                assert (a - b).abs().median() < 1e-5
            else:
                assert torch.equal(a, b), (key, a, b)
    # episodes ended inside the batches
    assert any(bool(b["next", "done"].any()) for b in stock)


@pytest.mark.parametrize("policy_kind", ["ppo_normal", "sac"])
def test_lean_collector_follows_weights_changed_between_batches(policy_kind):
    """Weights changed between batches, in place or by a loss's load_state_dict (which
    bumps no version counter), act in the next batch as they do in the stock collector's."""
    from torchrl.objectives import ClipPPOLoss

    batches = {}
    for lean in (False, True):
        torch.manual_seed(0)
        env = make_env("HalfCheetah-v5", seed=3, max_episode_steps=25)
        if policy_kind == "ppo_normal":
            policy, _ = make_ppo_actor_critic(env, hidden_sizes=(16,), distribution="normal")
        else:
            policy, _ = make_sac_actor_critic(env, hidden_sizes=(16,))
        loss = ClipPPOLoss(policy, make_ppo_actor_critic(env, hidden_sizes=(16,))[1])
        env.set_seed(11)
        torch.manual_seed(1)
        kind = LeanCollector if lean else Collector
        extra = {} if lean else {"total_frames": -1, "auto_register_policy_transforms": False}
        collector = kind(env, policy, frames_per_batch=30, **extra)
        out = []
        for i, batch in enumerate(collector):
            out.append(batch.clone())
            if i == 0:
                with torch.no_grad():
                    for p in policy.parameters():
                        p.mul_(1.5)
            elif i == 1:
                state = loss.state_dict()
                loss.load_state_dict(
                    {k: v - 0.2 if v.is_floating_point() else v for k, v in state.items()}
                )
            else:
                break
        collector.shutdown()
        batches[lean] = out
    for s, f in zip(batches[False], batches[True], strict=True):
        for key in ("action", "loc", "scale", ("next", "state")):
            assert torch.equal(s.get(key), f.get(key)), key


def test_lean_collector_refuses_other_envs():
    from torchrl.envs import GymEnv

    env = GymEnv("Pendulum-v1")
    assert not LeanCollector.supports(env)
    with pytest.raises(ValueError, match=r"use torchrl\.collectors\.Collector"):
        LeanCollector(env, RandomPolicy(env.full_action_spec), frames_per_batch=4)
    with pytest.raises(ValueError, match="frames_per_batch"):
        LeanCollector(
            make_env("Pendulum-v1"), RandomPolicy(env.full_action_spec), frames_per_batch=0
        )


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Pendulum-v1"])
def test_lean_episode_equals_env_rollout_deterministic(env_id):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    env = make_env(env_id, reward="default", seed=0, max_episode_steps=60)
    actor, _ = make_ppo_actor_critic(env, hidden_sizes=(16,))
    results = []
    for lean in (False, True):
        env.set_seed(5)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            if lean:
                td = LeanCollector(
                    env,
                    actor,
                    frames_per_batch=1,
                    exploration_type=ExplorationType.DETERMINISTIC,
                ).episode()
            else:
                td = env.rollout(100_000, actor)
        results.append(td)
    stock, fast = results
    assert stock.shape == fast.shape == torch.Size([60])
    for key in ("action", ("next", "reward"), ("next", "state"), ("next", "episode_reward")):
        assert torch.equal(stock.get(key), fast.get(key)), key
