from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# Tiny models: one thread is faster, and robust to other processes holding a core.
ENV = {**os.environ, "MUJOCO_GL": "egl", "OMP_NUM_THREADS": "1"}


def _run(tmp_path: Path, *overrides: str) -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    out = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "fit_world_model.py"),
            *overrides,
            f"hydra.run.dir={out}",
            "progress=false",
        ],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.mark.parametrize(
    "overrides",
    [
        ("env=pendulum", "world_model.random_steps=400", "eval_steps=300"),
        ("reward=shin_pen", "world_model.random_steps=300", "eval_steps=100", "horizons=[2,5]"),
    ],
)
def test_recipe_writes_outputs(tmp_path, overrides):
    out = _run(tmp_path, *overrides, "world_model.max_epochs=2", "world_model.hidden_sizes=[16,16]")
    for name in (
        "world_model.pt",
        "fit_history.json",
        "horizon_mse.json",
        "horizon_mse.md",
        "horizon_reward.png",
        "summary.json",
        "dataset/metadata.json",
    ):
        assert (out / name).exists(), name
    # the x plot where the task's state has an x position (HalfCheetah's; Pendulum has none)
    assert (out / "horizon_x.png").exists() == ("env=pendulum" not in overrides)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["real_steps"] == summary["random_steps"] + summary["eval_steps"]
    errors = json.loads((out / "horizon_mse.json").read_text())
    assert [e["horizon"] for e in errors] == (
        [5, 10, 25] if "env=pendulum" in overrides else [2, 5]
    )
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_recipe_reuses_dataset_and_refuses_other_reward(tmp_path):
    first = _run(
        tmp_path,
        "world_model.random_steps=100",
        "eval_steps=50",
        "horizons=[2]",
        "world_model.max_epochs=1",
        "world_model.hidden_sizes=[8]",
    )
    dataset = first / "dataset"
    _run(
        tmp_path / "again",
        f"dataset={dataset}",
        "eval_steps=50",
        "horizons=[2]",
        "world_model.max_epochs=1",
        "world_model.hidden_sizes=[8]",
    )
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "fit_world_model.py"),
            "reward=head_pen",
            f"dataset={dataset}",
            f"hydra.run.dir={tmp_path / 'bad'}",
            "progress=false",
        ],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode != 0
    assert "head_pen" in proc.stderr and "collect new data" in proc.stderr
