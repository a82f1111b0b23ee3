"""sac_mbpo: the real/model mix of SAC batches, the branched rollouts, and the method's settings."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_mbmf.checks import ConfigError
from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.data.mixed_replay import MixedReplaySampler
from torchrl_mbmf.envs import make_env
from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
from torchrl_mbmf.trainers.agents import make_agent
from torchrl_mbmf.trainers.settings import TrainConfig
from torchrl_mbmf.world_model.branched_rollouts import BranchedRollouts
from torchrl_mbmf.world_model.ensemble_fit import fit_ensemble

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = str(ROOT / "configs")


def _buffers(real_rows: int = 40, model_rows: int = 30):
    """A real and a model buffer whose rows say where they come from (``source``: 0 / 1)."""
    real = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=1)
    model = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=1)
    for buffer, rows, source in ((real, real_rows, 0.0), (model, model_rows, 1.0)):
        data = TensorDict(
            {"source": torch.full((rows,), source), "row": torch.arange(rows).float()}, [rows]
        )
        buffer.extend(data)
    return real, model


@pytest.mark.parametrize("ratio", [0.0, 0.05, 0.25, 0.5, 1.0])
def test_mixed_batches_have_the_configured_real_share(ratio):
    real, model = _buffers()
    sampler = MixedReplaySampler(real, model, ["source", "row"], batch_size=256, real_ratio=ratio)
    n_real = round(ratio * 256)
    torch.manual_seed(0)
    source, row = sampler()
    assert source.shape == (256,)
    assert source[:n_real].eq(0).all() and source[n_real:].eq(1).all()
    # real rows index the real buffer, model rows the model buffer (uniformly over both)
    assert row[:n_real].lt(40).all() and row[n_real:].lt(30).all()
    td = sampler.sample()
    assert td.batch_size == torch.Size([256])
    assert td["source"][:n_real].eq(0).all() and td["source"][n_real:].eq(1).all()


def test_mixed_sampler_draws_the_rows_each_buffer_would_draw():
    real, model = _buffers()
    sampler = MixedReplaySampler(real, model, ["row"], batch_size=8, real_ratio=0.5)
    torch.manual_seed(3)
    (rows,) = sampler()
    torch.manual_seed(3)
    expected_real = torch.randint(0, 40, (4,)).float()
    expected_model = torch.randint(0, 30, (4,)).float()
    assert torch.equal(rows, torch.cat([expected_real, expected_model]))


def test_mixed_sampler_refuses_bad_values_and_empty_buffers():
    real, model = _buffers()
    with pytest.raises(ValueError, match="real_ratio must be in"):
        MixedReplaySampler(real, model, ["row"], batch_size=8, real_ratio=1.5)
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1"):
        MixedReplaySampler(real, model, ["row"], batch_size=0, real_ratio=0.5)
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=1)
    with pytest.raises(RuntimeError, match="the model replay is empty"):
        MixedReplaySampler(real, empty, ["row"], batch_size=8, real_ratio=0.5)()


def test_sac_agent_updates_on_the_mix():
    """The SAC agent's batches (fused and stock paths) hold the configured real share."""
    env = make_env("Pendulum-v1", seed=0)
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=["method=sac", "sac.batch_size=20"])
    for update in ("fused", "stock"):
        cfg.sac.update = update
        agent = make_agent("sac", env, cfg, torch.device("cpu"))
        agent.observe(env.rollout(50))
        model = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=1)
        imagined = env.rollout(30).select(*agent.loss.in_keys)
        imagined["next", "reward"] = torch.full_like(imagined["next", "reward"], 1e6)
        model.extend(imagined)
        agent.mix_model_replay(model, real_ratio=0.25)
        batch = agent.sample()
        marker = batch["next", "reward"].squeeze(-1).eq(1e6)
        assert marker.tolist() == [False] * 5 + [True] * 15
        if update == "fused":
            reward = agent.sampler()[agent.step.batch_keys.index(("next", "reward"))]
            assert reward.squeeze(-1).eq(1e6).tolist() == [False] * 5 + [True] * 15


def _hopper_terminated(obs: torch.Tensor) -> torch.Tensor:
    """Gymnasium Hopper-v5's termination from its observation (qpos[1:], qvel): not healthy."""
    z, angle, rest = obs[..., 0], obs[..., 1], obs[..., 1:]
    healthy = (z > 0.7) & (angle > -0.2) & (angle < 0.2) & (rest.abs() < 100).all(-1)
    return ~healthy


@pytest.fixture(scope="module")
def hopper_rollouts():
    torch.manual_seed(0)
    env = make_env("Hopper-v5", seed=0)
    data = collect_random_transitions(make_env("Hopper-v5", seed=1), 600, seed=1)
    model = EnsembleDeltaDynamicsModel(12, 3, num_members=3, hidden_sizes=(32, 32))
    fit_ensemble(model, data, lr=1e-3, batch_size=64, max_epochs=5, seed=0)
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=["method=sac", "env=hopper"])
    agent = make_agent("sac", env, cfg, torch.device("cpu"))
    rollouts = BranchedRollouts(
        model,
        env,
        agent.actor,
        agent.loss.in_keys,
        rollout_every=50,
        rollout_batch_size=200,
        rollout_horizon=15,
        model_replay_size=5000,
        real_ratio=0.05,
        refit_every=50,
    )
    return rollouts, data


def test_branches_start_from_real_states_and_stop_at_the_task_rule(hopper_rollouts):
    rollouts, _ = hopper_rollouts
    # real states with the real env's observations of them
    real = make_env("Hopper-v5", seed=2).rollout(200, break_when_any_done=False)
    starts = real["state"]
    torch.manual_seed(1)
    td, keep = rollouts.imagine(starts)
    assert td.batch_size == torch.Size([200, 15])
    # every branch starts at its real state: the policy saw the real env's observation
    assert torch.equal(td[:, 0]["observation"], real["observation"])
    # consecutive kept steps chain
    chained = keep[:, 1:]
    following, previous = td[:, 1:][chained], td[:, :-1][chained]
    assert torch.equal(following["observation"], previous["next", "observation"])
    # each step's terminated flag is Gymnasium's Hopper rule on the predicted next state
    terminated = td["next", "terminated"].squeeze(-1)
    assert torch.equal(terminated[keep], _hopper_terminated(td["next", "observation"][keep]))
    # a branch keeps its steps up to and including its first termination, none after
    assert terminated.any() and not terminated.all()
    for b in range(200):
        hits = (terminated[b] & keep[b]).nonzero()
        last = int(hits[0]) if len(hits) else 14
        assert keep[b, : last + 1].all() and not keep[b, last + 1 :].any()


def test_generate_fills_the_model_replay_with_kept_transitions(hopper_rollouts):
    rollouts, data = hopper_rollouts
    rollouts.replay.empty()
    torch.manual_seed(2)
    stats = rollouts.generate(data)
    stored = rollouts.replay.storage[: len(rollouts.replay)]
    assert stats["rollout/transitions"] == len(rollouts.replay) > 200
    assert set(stored.keys(True, True)) >= {"observation", "action", ("next", "observation")}
    # a stored transition after a termination is never kept: at most one terminal per branch
    assert int(stored["next", "terminated"].sum()) == stats["rollout/terminated"] <= 200
    assert stats["rollout/mean_length"] == pytest.approx(len(rollouts.replay) / 200)


def test_branched_rollouts_refuse_bad_settings(hopper_rollouts):
    rollouts, _ = hopper_rollouts
    model = rollouts.model_env.dynamics
    kwargs = {
        "rollout_every": 50,
        "rollout_batch_size": 10,
        "rollout_horizon": 1,
        "model_replay_size": 100,
        "real_ratio": 0.05,
        "refit_every": 50,
    }
    for key, bad in (("real_ratio", 1.5), ("rollout_horizon", 0), ("rollout_batch_size", 2.5)):
        with pytest.raises(ValueError, match=key):
            BranchedRollouts(
                model,
                make_env("Hopper-v5"),
                rollouts.actor,
                ["observation"],
                **{**kwargs, key: bad},
            )


def _config(*overrides: str):
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        return compose("train", overrides=["method=sac_mbpo", *overrides])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["mbpo.rollout_every=75"], "mbpo.rollout_every=75 must be a multiple of sac.frames_"),
        (["mbpo.refit_every=120"], "mbpo.refit_every=120 must be a multiple of sac.frames_"),
        (["planner.terminal_value=true"], "planner.terminal_value=true has no effect"),
        (
            ["world_model.ensemble_size=3", "world_model.adaptive_horizon=true"],
            "world_model.adaptive_horizon=true has no effect",
        ),
        (["mbpo.rollout_horizonn=3"], "did you mean 'mbpo.rollout_horizon'"),
    ],
)
def test_sac_mbpo_settings_are_checked(overrides, message):
    cfg = _config(*[("+" if "horizonn" in o else "") + o for o in overrides])
    with pytest.raises(ConfigError, match=message):
        TrainConfig.from_config(cfg)


def test_mbpo_group_values_are_refused_naming_the_key(tmp_path):
    from torchrl_mbmf.trainers import Trainer

    cfg = _config("env=pendulum", "mbpo.real_ratio=1.5", "world_model.ensemble_size=2")
    with pytest.raises(ConfigError, match=r"mbpo\.real_ratio"):
        Trainer(cfg, tmp_path / "run")


def test_the_mbpo_run_name_names_its_variant():
    cfg = _config("experiment=hybrid_mbpo")
    assert "__sac_mbpo__hybrid_mbpo__" in cfg.run_name and "__mbpo-H1-" in cfg.run_name
    assert "__mbpo-H3-" in _config("experiment=hybrid_mbpo", "mbpo.rollout_horizon=3").run_name
    assert "__mbpo" not in _config("method=sac").run_name


SMOKE = [
    "method=sac_mbpo",
    "total_steps=400",
    "world_model.random_steps=200",
    "world_model.ensemble_size=2",
    "world_model.hidden_sizes=[16,16]",
    "world_model.max_epochs=2",
    "sac.init_random_frames=200",
    "sac.hidden_sizes=[16,16]",
    "sac.batch_size=32",
    "sac.utd_ratio=2",
    "mbpo.rollout_every=100",
    "mbpo.rollout_batch_size=64",
    "mbpo.rollout_horizon=3",
    "mbpo.refit_every=100",
    "eval_every=400",
    "eval_episodes=1",
    "checkpoint.every_steps=200",
    "progress=false",
]


@pytest.mark.parametrize("env", ["half_cheetah", "hopper"])
def test_train_recipe_runs_sac_mbpo(tmp_path, env):
    run = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "train.py"),
            *SMOKE,
            f"env={env}",
            f"run_dir={run}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["method"] == "sac_mbpo"
    assert summary["real_steps"] == 400 and summary["random_steps"] == 200
    assert summary["time_breakdown"]["rollout_s"] > 0
    assert summary["final_eval_return"] is not None
    # a round at the first learning batch and every 100 real steps after it
    steps = (run / "logs" / "scalars" / "rollout" / "transitions.csv").read_text().split()
    assert [int(row.split(",")[0]) for row in steps] == [250, 350]
    # refits: after the random data and every 100 real steps
    fits = (run / "logs" / "scalars" / "model" / "train_loss.csv").read_text().split()
    assert [int(row.split(",")[0]) for row in fits] == [200, 300, 400]
    latest = sorted((run / "checkpoints").glob("checkpoint-*"))[-1]
    names = {p.name.split("-", 1)[1] for p in (latest / "components").iterdir()}
    assert {"replay", "model_replay", "dataset", "world_model"} <= names


def test_runs_written_before_the_mbpo_group_resume_unchanged():
    from torchrl_mbmf.runs.resume import resume_changes

    mbpo = {"mbpo.real_ratio": 0.05, "mbpo.rollout_horizon": 1}
    # a sac run written before the group existed: its keys are no change
    old = {"method": "sac", "sac.lr": 3e-4}
    assert resume_changes(old, {**old, **mbpo}) == ({}, {})
    # a sac_mbpo run compares them like any setting
    saved = {"method": "sac_mbpo", **mbpo}
    refused, _ = resume_changes(saved, {**saved, "mbpo.real_ratio": 0.5})
    assert refused == {"mbpo.real_ratio": (0.05, 0.5)}


@pytest.mark.parametrize("probabilistic", [False, True])
def test_random_member_env_steps_a_random_member(probabilistic):
    from torchrl_mbmf.world_model.branched_rollouts import RandomMemberEnv

    torch.manual_seed(0)
    real = make_env("Pendulum-v1", seed=0)
    model = EnsembleDeltaDynamicsModel(
        3, 1, num_members=3, hidden_sizes=(16,), probabilistic=probabilistic
    )
    env = RandomMemberEnv(model, real)
    start = real.reset().expand(2000).clone()
    start["action"] = torch.rand(2000, 1) * 4 - 2
    torch.manual_seed(1)
    out = env.step(start.clone())["next"]
    torch.manual_seed(1)
    members = torch.randint(0, 3, (2000,))
    # the reference: each member's own prediction (real units), by the model's forward
    each = [model(start["state"], start["action"], torch.full((2000,), k)) for k in range(3)]
    expected = torch.stack([each[k][0] for k in range(3)])[members, torch.arange(2000)]
    if not probabilistic:
        assert torch.allclose(out["state"], expected, atol=1e-6)
        assert members.unique().numel() == 3
    else:
        # sampled around the member's mean: not equal, but centred on it
        noise = out["state"] - expected
        assert not torch.allclose(out["state"], expected)
        assert noise.mean(0).abs().lt(5 * noise.std(0) / 2000**0.5).all()
    assert torch.equal(
        out["disagreement"].squeeze(-1), model.disagreement(start["state"], start["action"])
    )
