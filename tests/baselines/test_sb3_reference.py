"""The Stable-Baselines3 reference recipe writes a run folder our analysis reads like ours."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

from torchrl_mbmf.analysis.runs import load_runs
from torchrl_mbmf.baselines.sb3 import make_sb3_model

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
PENDULUM = [
    "env_id=Pendulum-v1",
    "total_steps=600",
    "ppo.frames_per_batch=200",
    "ppo.minibatch_size=100",
    "ppo.epochs=1",
    "ppo.hidden_sizes=[8,8]",
    "eval_every=400",
]


def _run(run_dir: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "sb3_reference.py"),
            *PENDULUM,
            *extra,
            f"run_dir={run_dir}",
        ],
        cwd=run_dir.parent,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_reference_run_folder_is_read_like_ours(tmp_path):
    run_dir = tmp_path / "Pendulum-v1__sb3_ppo__default__seed0"
    proc = _run(run_dir)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["method"] == "sb3_ppo"
    assert summary["real_steps"] == 600  # three 200-step rollouts: every env step counted
    assert summary["grad_steps"] == 3 * 2  # 1 epoch of 2 minibatches per rollout
    (run,) = load_runs(tmp_path)
    assert (run.method, run.seed, run.reward, run.complete) == ("sb3_ppo", 0, "default", True)
    steps, returns = run.scalar("train/episode_return")
    assert steps.tolist() == [200, 400, 600]  # Pendulum's 200-step episodes, at their last step
    means = run.scalar("train/return_last10_mean")[1]
    assert means[-1] == pytest.approx(returns.mean())
    assert run.scalar("eval/return")[0].tolist() == [1, 400]
    assert summary["last10_mean_return"] == pytest.approx(returns.mean())


def test_existing_run_is_never_overwritten_without_restart(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "logs").mkdir(parents=True)
    marker = run_dir / "logs" / "kept.csv"
    marker.write_text("1,2\n")
    proc = _run(run_dir)
    assert proc.returncode != 0
    assert "restart=true" in proc.stderr and str(run_dir) in proc.stderr
    assert marker.exists()
    proc = _run(run_dir, "restart=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert not marker.exists() and (run_dir / "summary.json").exists()


def test_sb3_settings_follow_our_config():
    import gymnasium as gym

    sac = {
        "lr": 1e-3,
        "replay_size": 5000,
        "init_random_frames": 123,
        "batch_size": 64,
        "tau": 0.01,
        "gamma": 0.98,
        "utd_ratio": 2.0,
        "alpha_init": 0.5,
        "hidden_sizes": [16, 16],
    }
    model = make_sb3_model("sac", gym.make("Pendulum-v1"), sac, seed=3)
    assert (model.learning_starts, model.batch_size, model.gradient_steps) == (123, 64, 2)
    assert (model.tau, model.gamma, model.buffer_size) == (0.01, 0.98, 5000)
    assert model.policy.net_arch == [16, 16]
    with pytest.raises(ValueError, match="lack \\['tau'\\]"):
        no_tau = {k: v for k, v in sac.items() if k != "tau"}
        make_sb3_model("sac", gym.make("Pendulum-v1"), no_tau, seed=0)
    with pytest.raises(ValueError, match="algo='td3'"):
        make_sb3_model("td3", gym.make("Pendulum-v1"), sac, seed=0)
