"""World-model fit records: a snapshot per fit, held-out errors before each refit, no change."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import make_gym_state_env
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.runs.storage import CheckpointIntegrityError
from torchrl_mbmf.trainers import Trainer
from torchrl_mbmf.world_model.snapshots import (
    fit_snapshots,
    heldout_open_loop_errors,
    load_fit_snapshot,
    save_fit_snapshot,
)

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")
TINY_PPO_MPC = [
    "env=pendulum",
    "method=ppo_mpc",
    "progress=false",
    "ppo.frames_per_batch=192",
    "planning_updates=3",
    "total_steps=976",
    "world_model.random_steps=400",
    "world_model.max_epochs=2",
    "world_model.hidden_sizes=[16,16]",
    "world_model.refit_every=1",
    "planner.horizon=3",
    "planner.num_candidates=4",
    "eval_every=100000",
    "checkpoint.every_steps=100000",
]


def _run(run_dir: Path, *overrides: str) -> tuple[Trainer, dict]:
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=[*TINY_PPO_MPC, *overrides])
    trainer = Trainer(cfg, run_dir)
    return trainer, trainer.train()


def _csv(path: Path) -> list[tuple[int, float]]:
    with path.open() as f:
        return [(int(float(r[0])), float(r[1])) for r in csv.reader(f) if r]


def test_each_fit_is_snapshotted_and_each_refit_logs_the_replaced_models_heldout_errors(tmp_path):
    trainer, summary = _run(tmp_path / "on")
    fits = fit_snapshots(tmp_path / "on")
    # the first fit on 400 random steps, refits after updates 1 and 2 (none after the last
    # planning update: nothing plans with that model again)
    assert [n for n, _ in fits] == [400, 592, 784]
    logged = [int(v) for _, v in _csv(tmp_path / "on/logs/scalars/model/transitions.csv")]
    assert logged == [400, 592, 784]
    # the last snapshot is the model the run ended with
    last = load_fit_snapshot(DeltaDynamicsModel(3, 1, hidden_sizes=(16, 16)), fits[-1][1])
    ours, saved = trainer.world.model.state_dict(), last.state_dict()
    assert list(ours) == list(saved)
    assert all(torch.equal(ours[k], saved[k]) for k in ours)
    # held-out errors at the two refits only (the first fit has no predecessor); Pendulum's
    # state has no x position, so only the reward's are recorded
    rows = _csv(tmp_path / "on/logs/scalars/model/heldout_reward_mse_h10.csv")
    assert len(rows) == 2 and all(v >= 0 for _, v in rows)
    assert not (tmp_path / "on/logs/scalars/model/heldout_x_mse_h10.csv").exists()
    # recording changes no training number
    _, off = _run(tmp_path / "off", "world_model.save_fits=false")
    assert off["params_sha256"] == summary["params_sha256"]
    assert fit_snapshots(tmp_path / "off") == []


def test_heldout_errors_match_a_step_by_step_rollout_of_the_unseen_rows():
    data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 600, seed=1)
    torch.manual_seed(0)
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    state = torch.random.get_rng_state()
    # state dim 0 (Pendulum's cos) stands for an x position here
    errors = heldout_open_loop_errors(
        model, data, since=400, horizons=(2, 5), num_starts=None, x_index=0
    )
    assert torch.equal(torch.random.get_rng_state(), state)  # the global generator is untouched
    td = data.tensors()
    s, a = td["state"].float(), td["action"].float()
    ns, r = td["next", "state"].float(), td["next", "reward"].float().reshape(-1)
    # every row from 400 whose next 5 rows lie in the same episode (episodes of 200 steps)
    starts = [i for i in range(400, 600) if (i % 200) + 5 <= 200]
    x_err, r_err = torch.zeros(5), torch.zeros(5)
    with torch.no_grad():
        for i in starts:
            pred = s[i : i + 1]
            for t in range(5):
                pred, rew = model(pred, a[i + t : i + t + 1])
                x_err[t] += (pred[0, 0] - ns[i + t, 0]) ** 2
                r_err[t] += (rew[0, 0] - r[i + t]) ** 2
    x_err, r_err = x_err / len(starts), r_err / len(starts)
    assert errors["model/heldout_starts"] == len(starts)
    assert errors["model/heldout_x_mse_h2"] == pytest.approx(float(x_err[:2].mean()), rel=1e-5)
    assert errors["model/heldout_x_mse_h5"] == pytest.approx(float(x_err.mean()), rel=1e-5)
    assert errors["model/heldout_reward_mse_h5"] == pytest.approx(float(r_err.mean()), rel=1e-5)
    assert heldout_open_loop_errors(model, data, since=600) == {}
    # by default the x index is the task's: Pendulum has none
    default = heldout_open_loop_errors(model, data, since=400, horizons=(2, 5), num_starts=None)
    assert default == {k: v for k, v in errors.items() if "_x_" not in k}


def test_a_damaged_snapshot_is_refused(tmp_path):
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    folder = save_fit_snapshot(model, tmp_path, 10)
    tensor = next((folder / "state").rglob("*.memmap"))
    tensor.write_bytes(tensor.read_bytes()[:-1])
    with pytest.raises(CheckpointIntegrityError):
        load_fit_snapshot(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), folder)
