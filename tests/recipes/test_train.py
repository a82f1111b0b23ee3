"""The training recipe: configs compose, every method smoke-runs, bad configs fail early."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from rl_helpers import TINY_HALF_CHEETAH, build_for_checks
from rl_helpers import TINY_TRAIN as TINY

from torchrl_mbmf.trainers import ConfigError, validate_train_config

ROOT = Path(__file__).resolve().parents[2]
# One torch thread per run: tiny networks gain nothing from two, and on a shared 2-vCPU machine
# two OpenMP threads per process slow small matmuls down several times.
SUBPROCESS_ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
CONFIGS = str(ROOT / "configs")


def _compose(*overrides: str):
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        return compose("train", overrides=list(overrides))


def _run(run_dir: Path, *overrides: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), *overrides, f"run_dir={run_dir}"],
        cwd=run_dir.parent,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=SUBPROCESS_ENV,
    )


@pytest.mark.parametrize(
    "group", ["env", "reward", "world_model", "planner", "logger", "experiment"]
)
def test_every_config_composes(group):
    for path in sorted((ROOT / "configs" / group).glob("*.yaml")):
        cfg = _compose(f"{group}={path.stem}")
        validate_train_config(cfg)


@pytest.mark.parametrize(
    ("method", "extra"),
    [
        ("ppo", []),
        ("ppo", ["ppo.update=stock", "collector=stock"]),
        ("ppo", ["ppo.update=fused_autograd", "eval_episodes=0"]),
        ("sac_mpc", ["device=auto"]),  # the GPU where torch sees one
        ("mpc", []),
        ("ppo_mpc", ["env.num_envs=2", "checkpoint.every_steps=100000", "total_steps=1100"]),
        ("sac", ["sac.update=stock"]),
        ("sac", ["env.num_envs=2", "checkpoint.every_steps=100000"]),
        ("sac_mpc", []),
        ("ppo_mpc", ["planner.terminal_value=true", "planner.refinement=cem"]),
        ("sac_mpc", ["planner.terminal_value=true", "planner.refinement=mppi"]),
        (  # LOOP's acting: MPPI around the actor in an ensemble, min-Q at the horizon
            "sac_mpc",
            [
                "world_model.ensemble_size=3",
                "planner.terminal_value=true",
                "planner.refinement=mppi",
            ],
        ),
        ("mpc", ["world_model.multi_step=3"]),
        (
            "ppo_mpc",
            [
                "world_model.ensemble_size=3",
                "world_model.adaptive_horizon=true",
                "planner.terminal_value=true",
            ],
        ),
    ],
)
def test_method_smoke_run(tmp_path, method, extra):
    run = tmp_path / method
    steps = [] if any(e.startswith("total_steps=") for e in extra) else ["total_steps=900"]
    proc = _run(run, f"method={method}", *steps, *TINY, *extra)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["real_steps"] >= 900
    if "eval_episodes=0" in extra:  # no evaluation: no eval rows, no NaN return
        assert summary["final_eval_return"] is None
        assert not (run / "logs" / "scalars" / "eval" / "return.csv").exists()
    assert set(summary["time_breakdown"]) == {
        "env_s",
        "act_s",
        "update_s",
        "refit_s",
        "rollout_s",
        "other_s",
    }
    if method in ("mpc", "ppo_mpc", "sac_mpc"):
        assert summary["random_steps"] == 300
    if method in ("mpc", "ppo_mpc"):
        assert summary["switch_step"] == 300 + 2 * 192
    assert (run / "config.yaml").exists() and (run / "git_commit.txt").exists()
    scalars = run / "logs" / "scalars"
    assert (scalars / "train" / "episode_return.csv").exists()
    assert (scalars / "eval" / "return.csv").exists() != ("eval_episodes=0" in extra)
    if method != "ppo" and method != "sac":
        assert (scalars / "model" / "val_loss.csv").exists()
    if "world_model.adaptive_horizon=true" in extra:
        threshold = (scalars / "model" / "disagreement_threshold.csv").read_text().split()
        assert threshold and all(float(row.split(",")[1]) > 0 for row in threshold)
        horizon = (scalars / "planner" / "effective_horizon.csv").read_text().split()
        assert all(0 <= float(row.split(",")[1]) <= 10 for row in horizon)
    assert (run / "machine.json").exists() and (run / "policy.pt").exists()
    assert any((run / "checkpoints").iterdir())


def test_half_cheetah_ppo_mpc_tiny(tmp_path):
    run = tmp_path / "hc"
    proc = _run(run, *TINY_HALF_CHEETAH, "total_steps=300")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "summary.json").read_text())["env"] == "HalfCheetah-v5"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["method=dqn"], "method='dqn' is not a method; allowed"),
        (["reward=default", "reward.name=bogus"], "reward.name='bogus'"),
        (["planner.horizon=0"], "planner.horizon must be an integer >= 1"),
        (["planner.num_candidates=0"], "planner.num_candidates must be an integer >= 1"),
        (["total_steps=100000", "planning_updates=200"], "beyond total_steps=100000"),
        (["env.num_envs=3"], "multiple of env.num_envs=3"),
        (["logger.backend=foo"], "logger.backend='foo'"),
        (["method=sac", "sac.update=jit"], "sac.update='jit' is not supported; allowed"),
        (["ppo.update=jit"], "ppo.update='jit' is not supported; allowed"),
        (["collector=multi"], "collector='multi' is not supported; allowed"),
        (["device=gpu"], "device='gpu' is not supported; allowed"),
        (["method=mpc", "world_model.random_steps=0"], "world_model.random_steps must be"),
        (["total_steps=0"], "total_steps must be an integer >= 1, got 0"),
        (["planner.refinement=icem"], "planner.refinement='icem' is not supported; allowed"),
        (["method=mpc", "planner.refinement=cem"], "needs method ppo_mpc or sac_mpc"),
        (["planner.refinement=cem", "planner.num_elites=16"], "planner.num_elites must be"),
        (["planner.refinement=mppi", "planner.temperature=0"], "planner.temperature must be"),
        (["planner.terminal_value=maybe"], "planner.terminal_value must be true or false"),
        (["world_model.ensemble_size=0"], "world_model.ensemble_size must be an integer >= 1"),
        (["world_model.multi_step=0"], "world_model.multi_step"),
        (
            ["world_model.ensemble_size=3", "world_model.multi_step=3"],
            "world_model.multi_step > 1 is implemented for the single model only",
        ),
        (["method=mpc", "world_model.ensemble_size=3"], "needs method ppo_mpc or sac_mpc"),
        (["world_model.adaptive_horizon=true"], "adaptive_horizon needs an ensemble"),
    ],
)
def test_bad_config_fails_before_work(overrides, message, tmp_path):
    cfg = _compose(*overrides)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        build_for_checks(cfg, tmp_path / "run")


def test_variants_get_their_own_run_folders():
    assert _compose().run_name == "HalfCheetah-v5__ppo_mpc__default__h10__seed0"
    cfg = _compose("planner.terminal_value=true", "planner.refinement=cem", "seed=2")
    assert cfg.run_name == "HalfCheetah-v5__ppo_mpc__default__h10__value-cem__seed2"
    cfg = _compose("world_model.ensemble_size=5", "world_model.adaptive_horizon=true")
    assert cfg.run_name == "HalfCheetah-v5__ppo_mpc__default__h10__ens5-adaptive__seed0"


def test_bad_config_subprocess_message(tmp_path):
    proc = _run(tmp_path / "bad", "planner.horizon=0")
    assert proc.returncode != 0
    assert "planner.horizon must be an integer >= 1, got 0" in proc.stderr
    assert not (tmp_path / "bad" / "checkpoints").exists()


@pytest.mark.slow
@pytest.mark.parametrize("method", ["ppo_mpc", "sac_mpc"])
def test_improves_return_on_short_budget(tmp_path, method):
    """The policy alone (deterministic eval) ends better than at its first evaluation."""
    run = tmp_path / method
    proc = _run(
        run,
        f"method={method}",
        "env=pendulum",
        "total_steps=20000",
        "planning_updates=5",
        "world_model.random_steps=2000",
        "world_model.max_epochs=30",
        "eval_every=4000",
        "eval_episodes=3",
        "checkpoint.every_steps=100000",
        "progress=false",
        timeout=3000,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = (run / "logs" / "scalars" / "eval" / "return.csv").read_text().split()
    first = float(rows[0].split(",")[1])
    final = json.loads((run / "summary.json").read_text())["final_eval_return"]
    assert final > first + 100, (first, final)


def test_sac_with_sb3s_scale_trains_and_its_policy_loads_with_that_head(tmp_path):
    """``sac.scale=clamped_log_std`` reaches the actor, and ``load_policy`` rebuilds it."""
    from torchrl_mbmf.modules.log_std import ClampedLogStdExtractor
    from torchrl_mbmf.runs.export import load_policy

    run = tmp_path / "sac"
    proc = _run(run, "method=sac", "total_steps=900", "sac.scale=clamped_log_std", *TINY)
    assert proc.returncode == 0, proc.stderr[-3000:]
    actor, env, info = load_policy(run)
    assert info["config"].sac.scale == "clamped_log_std"
    assert any(isinstance(m, ClampedLogStdExtractor) for m in actor.modules())
    td = actor(env.reset())
    assert (td["scale"] <= torch.tensor(2.0).exp()).all()
