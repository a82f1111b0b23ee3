"""Experiment presets, budgets and launchers: every swept run composes and validates, and a
multirun through the local and Ray launchers trains each job into its own run folder."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from torchrl_mbmf.trainers import validate_train_config

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = str(ROOT / "configs")
PRESETS = sorted(p.stem for p in (ROOT / "configs" / "experiment").glob("*.yaml"))


def _compose(*overrides: str, hydra_cfg: bool = False):
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        return compose("train", overrides=list(overrides), return_hydra_config=hydra_cfg)


def _swept_runs(preset: str) -> list[list[str]]:
    """Every override list the preset's sweep expands to (one list per run)."""
    cfg = _compose(f"experiment={preset}", hydra_cfg=True)
    params = cfg.hydra.sweeper.params or {}
    keys = list(params)
    values = [str(params[k]).split(",") for k in keys]
    return [
        [f"{k}={v}" for k, v in zip(keys, combo, strict=True)]
        for combo in itertools.product(*values)
    ]


@pytest.mark.parametrize("budget", ["thesis", "short"])
@pytest.mark.parametrize("preset", PRESETS)
def test_every_swept_run_composes_and_validates(preset, budget):
    runs = _swept_runs(preset)
    names = set()
    for overrides in runs:
        cfg = _compose(f"experiment={preset}", f"budget={budget}", *overrides)
        validate_train_config(cfg)
        assert cfg.run_dir.startswith(f"outputs/{budget}/")
        names.add(cfg.run_name)
    # One run folder per swept job: no two jobs of a sweep write into the same folder.
    assert len(names) == len(runs)


def test_thesis_budgets_of_the_presets():
    exp1 = _compose("experiment=exp1_horizon", "planner.horizon=25")
    assert exp1.method == "ppo_mpc" and exp1.planner.horizon == 25
    # 10,000 random-data steps + 200 planning updates of 2,048 steps.
    assert exp1.total_steps == 10_000 + 200 * 2048 == 419_600
    budgets = {
        m: _compose("experiment=exp2_planning", f"method={m}").total_steps
        for m in ("ppo", "mpc", "ppo_mpc")
    }
    assert budgets == {"ppo": 1_000_000, "mpc": 419_600, "ppo_mpc": 1_000_000}
    assert _compose("experiment=exp4_sac").method == "sac_mpc"


def test_short_budget_overrides_every_preset():
    for preset in PRESETS:
        cfg = _compose(f"experiment={preset}", "budget=short")
        assert cfg.total_steps == 102_160 and cfg.planning_updates == 45
        assert cfg.budget.name == "short"


@pytest.mark.parametrize(
    ("launcher", "target"),
    [
        ("local", "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"),
        ("ray_local", "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher"),
        ("ray_cluster", "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher"),
        ("slurm", "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"),
    ],
)
def test_launcher_configs_compose(launcher, target):
    cfg = _compose(f"hydra/launcher={launcher}", hydra_cfg=True)
    assert cfg.hydra.launcher._target_ == target


@pytest.mark.parametrize("launcher", ["local", "ray_local"])
def test_multirun_trains_each_job_into_its_own_folder(tmp_path, launcher):
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "train.py"),
            "-m",
            f"hydra/launcher={launcher}",
            "method=ppo",
            "env=pendulum",
            "total_steps=320",
            "ppo.frames_per_batch=160",
            "eval_every=320",
            "progress=false",
            "threads=1",
            "seed=0,1",
            f"run_dir={tmp_path}/runs/${{run_name}}",
            f"hydra.sweep.dir={tmp_path}/sweep",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=400,
        env={**os.environ, "OMP_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summaries = {
        p.parent.name: json.loads(p.read_text())
        for p in sorted((tmp_path / "runs").glob("*/summary.json"))
    }
    assert sorted(summaries) == [
        "Pendulum-v1__ppo__default__h10__seed0",
        "Pendulum-v1__ppo__default__h10__seed1",
    ]
    assert all(s["real_steps"] == 320 for s in summaries.values())
    # Different seeds train different policies.
    assert len({s["params_sha256"] for s in summaries.values()}) == 2
