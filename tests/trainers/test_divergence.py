"""A run whose losses or returns become NaN/Inf stops, naming the step and the quantity."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

import torchrl_mbmf.trainers.agents as agents
from torchrl_mbmf.trainers import Trainer, TrainingDivergedError

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")
TINY = [
    "method=ppo",
    "env=pendulum",
    "total_steps=480",
    "ppo.frames_per_batch=160",
    "eval_every=100000",
    "checkpoint.every_steps=100000",
    "progress=false",
    "logger.backend=csv",
]


def _trainer(tmp_path: Path, *overrides: str) -> Trainer:
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=[*TINY, *overrides])
    return Trainer(cfg, tmp_path / "run")


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_log_refuses_non_finite_scalars(tmp_path, value):
    trainer = _trainer(tmp_path)
    trainer.log({"loss/loss_objective": 0.5})
    with pytest.raises(TrainingDivergedError, match=r"loss/loss_critic=.* at real step 0"):
        trainer.log({"loss/loss_critic": value})
    # nothing non-finite reaches the logs
    rows = (tmp_path / "run" / "logs" / "scalars" / "loss").glob("*.csv")
    assert all("nan" not in p.read_text() and "inf" not in p.read_text() for p in rows)


def test_diverged_update_stops_the_run(tmp_path, monkeypatch):
    real = agents.ppo_update
    calls = []

    def diverging(*args, **kwargs):
        stats = real(*args, **kwargs)
        calls.append(1)
        if len(calls) == 2:
            stats["loss_objective"] = float("nan")
        return stats

    monkeypatch.setattr(agents, "ppo_update", diverging)
    trainer = _trainer(tmp_path, "ppo.update=stock")  # the path that calls ppo_update
    with pytest.raises(TrainingDivergedError, match=r"loss/loss_objective=nan at real step 320"):
        trainer.train()
    assert not (tmp_path / "run" / "summary.json").exists()


def test_non_finite_evaluation_stops_the_run(tmp_path, monkeypatch):
    trainer = _trainer(tmp_path, "collector=stock")  # the path that calls eval_env.rollout
    monkeypatch.setattr(trainer.eval_env, "rollout", lambda *a, **k: _nan_rollout())
    with pytest.raises(TrainingDivergedError, match=r"eval/return=nan at real step 0"):
        trainer.evaluate()


def _nan_rollout():
    import torch
    from tensordict import TensorDict

    return TensorDict({"next": {"reward": torch.full((3, 1), float("nan"))}}, [3])
