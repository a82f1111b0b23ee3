"""The ``ppo.update`` and ``sac.update`` settings pick the update path the trainer runs."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from torchrl_mbmf.objectives.fused_ppo import FusedPPOUpdate
from torchrl_mbmf.objectives.fused_sac import FusedSACUpdate
from torchrl_mbmf.trainers import Trainer

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")


def _trainer(tmp_path: Path, *overrides: str) -> Trainer:
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=["env=pendulum", "progress=false", *overrides])
    return Trainer(cfg, tmp_path / "run")


@pytest.mark.parametrize(
    ("update", "gradients"), [(None, "manual"), ("fused_autograd", "autograd"), ("stock", None)]
)
def test_ppo_update_setting(tmp_path, update, gradients):
    extra = [] if update is None else [f"ppo.update={update}"]
    trainer = _trainer(tmp_path, "method=ppo", *extra)
    if gradients is None:
        assert trainer.agent.fused is None
    else:
        assert isinstance(trainer.agent.fused, FusedPPOUpdate)
        assert trainer.agent.fused.gradients == gradients


@pytest.mark.parametrize("update", [None, "stock"])
def test_sac_update_setting(tmp_path, update):
    extra = [] if update is None else [f"sac.update={update}"]
    trainer = _trainer(tmp_path, "method=sac", *extra)
    fused = update is None  # the default is the fused update
    assert isinstance(trainer.agent.step, FusedSACUpdate) == fused
    assert (trainer.agent.sampler is not None) == fused
    assert bool(trainer.agent.optim.defaults.get("fused")) == fused
