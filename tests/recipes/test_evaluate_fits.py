"""recipes/evaluate_fits.py: every recorded fit on the same fresh random episodes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from torchrl_mbmf.analysis.horizon import snapshot_open_loop_errors
from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import make_env
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives.open_loop import multistep_mse
from torchrl_mbmf.world_model.snapshots import save_fit_snapshot

ROOT = Path(__file__).resolve().parents[2]


def _run_folder(tmp_path: Path) -> tuple[Path, list[DeltaDynamicsModel]]:
    run = tmp_path / "run"
    run.mkdir()
    config = {
        "seed": 3,
        "env": {"id": "Pendulum-v1"},
        "reward": {"name": "default", "kwargs": {}},
        "world_model": {"hidden_sizes": [8], "ensemble_size": 1},
    }
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    models = []
    for i, transitions in enumerate((300, 500)):
        torch.manual_seed(i)
        # a Pendulum run's model has the env's action range, [-2, 2]
        model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,), action_low=-2.0, action_high=2.0)
        save_fit_snapshot(model, run, transitions)
        models.append(model)
    return run, models


def test_recipe_scores_each_fit_like_multistep_mse_on_the_same_data(tmp_path):
    run, models = _run_folder(tmp_path)
    script = str(ROOT / "recipes" / "evaluate_fits.py")
    settings = ["eval_steps=400", "horizons=[1,5]", "eval_starts=50", "seed_offset=10"]
    proc = subprocess.run(
        [sys.executable, script, f"run_dir={run}", *settings],
        cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads((run / "world_models" / "open_loop_errors.json").read_text())
    assert out["data"] == {"policy": "uniform random", "steps": 400, "seed": 13}
    assert [f["transitions"] for f in out["fits"]] == [300, 500]
    # the same numbers, recomputed here from the models and the same seeded episodes
    data = collect_random_transitions(make_env("Pendulum-v1", seed=13), 400, seed=13)
    for fit, model in zip(out["fits"], models, strict=True):
        expected = multistep_mse(model, data, horizons=(1, 5), num_starts=50, seed=13)
        # Pendulum's state has no x position
        assert [e["x_mse"] for e in fit["errors"]] == [e.x_mse for e in expected] == [None, None]
        assert [e["reward_mse"] for e in fit["errors"]] == pytest.approx(
            [e.reward_mse for e in expected]
        )


def test_a_run_without_fits_is_a_clear_error(tmp_path):
    run, _ = _run_folder(tmp_path)
    data = collect_random_transitions(make_env("Pendulum-v1", seed=0), 50, seed=0)
    (run / "config.yaml").write_text(yaml.safe_dump({"world_model": {"ensemble_size": 5}}))
    with pytest.raises(ValueError, match="ensemble"):
        snapshot_open_loop_errors(run, data)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "config.yaml").write_text(yaml.safe_dump({"world_model": {"hidden_sizes": [8]}}))
    with pytest.raises(ValueError, match="no world-model fit"):
        snapshot_open_loop_errors(empty, data)
