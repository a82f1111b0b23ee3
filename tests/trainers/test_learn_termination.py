"""``world_model.learn_termination``: a termination head fitted with the model replaces the rule."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from rl_helpers import TINY_TRAIN, build_for_checks

from torchrl_mbmf.checks import ConfigError
from torchrl_mbmf.envs import make_env
from torchrl_mbmf.envs.terminations import HopperTermination
from torchrl_mbmf.modules import LearnedTermination

ROOT = Path(__file__).resolve().parents[2]
TINY = [o for o in TINY_TRAIN if not o.startswith("env=")]


def _cfg(*overrides: str):
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose("train", overrides=[*TINY, *overrides])


def _trainer(tmp_path: Path, *overrides: str):
    from torchrl_mbmf.trainers import Trainer

    cfg = _cfg(
        "env=hopper", "method=mpc", "planner.num_candidates=8", "planner.horizon=4", *overrides
    )
    return Trainer(cfg, tmp_path / "run")


def test_the_head_is_fitted_with_the_model_and_ends_the_planners_candidates(tmp_path, caplog):
    with caplog.at_level(logging.INFO, logger="torchrl_mbmf.world_model.networks"):
        trainer = _trainer(tmp_path, "world_model.learn_termination=true")
    said = [r.getMessage() for r in caplog.records if "learn_termination" in r.getMessage()]
    assert len(said) == 1 and "HopperTermination" in said[0] and "not used" in said[0]
    world = trainer.world
    head = world.termination
    assert isinstance(head, LearnedTermination)
    assert world.planner.env.termination_fn is head
    assert "termination_head" in world.checkpoint_components()
    logged = {}
    trainer.log = logged.update  # the scalars of the fit
    trainer.collect_random()  # the random steps, then the first fit: model and head
    data = world.dataset
    falls = data.terminated()
    assert falls.any()  # Hopper falls within 300 random steps
    states = data.tensors()["next", "state"]
    # the head was fitted on the real next states (its scaling is theirs) and scored
    assert torch.allclose(head.state_loc, states.mean(0), atol=0.2)
    assert 0.0 <= logged["model/termination_val_accuracy"] <= 1.0
    # the planner ends each candidate where the head says: a head that calls every state
    # terminal leaves each candidate its first predicted reward, one that calls none all h
    td = make_env("Hopper-v5", seed=1).reset()
    model = world.model
    returns = {}
    for name, bias in (("ends", 50.0), ("never", -50.0)):
        with torch.no_grad():
            head.net[-1].bias.fill_(bias)
        torch.manual_seed(0)
        plan = world.planner.plan(td.clone())
        returns[name] = plan.returns
        if name == "ends":
            _, reward = model(
                td["state"].expand(*plan.first_actions.shape[:-1], -1), plan.first_actions
            )
            torch.testing.assert_close(plan.returns, reward[..., 0])
    assert not torch.allclose(returns["ends"], returns["never"])
    assert type(world.planner.env.termination_fn) is not HopperTermination


def test_off_by_default_and_the_rule_is_used(tmp_path):
    world = _trainer(tmp_path).world
    assert world.termination is None and "termination_head" not in world.checkpoint_components()
    assert isinstance(world.planner.env.termination_fn, HopperTermination)


@pytest.mark.parametrize("value", ["yes", 1, "null"])
def test_learn_termination_must_be_a_bool(tmp_path, value):
    cfg = _cfg("env=pendulum", "method=ppo_mpc", f"world_model.learn_termination={value}")
    with pytest.raises(
        ConfigError, match=r"learn_termination.*" + str(value if value != "null" else None)
    ):
        build_for_checks(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
