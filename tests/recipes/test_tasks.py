"""Every task of ``configs/env`` from the training recipe, and every method on a terminating one.

Pendulum (every method) and HalfCheetah (PPO-MPC) run in ``test_train.py``; here Hopper runs
every method and Walker2d, Ant and InvertedPendulum run PPO-MPC. Each group is one Hydra
multirun, so the package is imported once per group.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from rl_helpers import TINY_TRAIN, build_for_checks

ROOT = Path(__file__).resolve().parents[2]
SUBPROCESS_ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
#: The tiny settings of the Pendulum smoke runs, on the task the test names.
TINY = [o for o in TINY_TRAIN if not o.startswith("env=")]
METHODS = ("ppo", "mpc", "ppo_mpc", "sac", "sac_mpc")


def _multirun(tmp_path: Path, *overrides: str) -> dict[tuple[str, str], dict]:
    """Runs ``recipes/train.py -m`` in ``tmp_path``; returns the summaries by (env, method)."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), "-m", *overrides, *TINY],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env=SUBPROCESS_ENV,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summaries = [json.loads(p.read_text()) for p in tmp_path.rglob("summary.json")]
    return {(s["env"], s["method"]): s for s in summaries}


def test_every_method_runs_on_hopper(tmp_path):
    runs = _multirun(tmp_path, f"method={','.join(METHODS)}", "env=hopper", "total_steps=900")
    assert sorted(runs) == sorted(("Hopper-v5", m) for m in METHODS)
    for summary in runs.values():
        assert summary["real_steps"] >= 900
        # Hopper's time limit is 1000 steps: every episode that ended was a termination
        assert summary["episodes"] >= 2
        assert summary["final_eval_return"] is not None


def test_every_task_runs_ppo_mpc(tmp_path):
    tasks = {"walker2d": "Walker2d-v5", "ant": "Ant-v5", "inverted_pendulum": "InvertedPendulum-v5"}
    runs = _multirun(
        tmp_path, "method=ppo_mpc", f"env={','.join(tasks)}", "total_steps=700", "eval_every=700"
    )
    assert sorted(runs) == sorted((env_id, "ppo_mpc") for env_id in tasks.values())
    for summary in runs.values():
        assert summary["real_steps"] >= 700
        assert summary["random_steps"] == 300
        assert summary["switch_step"] == 300 + 2 * 192


@pytest.mark.parametrize("reward", ["head_pen", "shin_pen"])
def test_thesis_rewards_are_refused_on_other_tasks(tmp_path, reward):
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=["env=hopper", f"reward={reward}"])
    with pytest.raises(ValueError, match=f"reward='{reward}'.*defined for HalfCheetah-v5 only"):
        build_for_checks(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
