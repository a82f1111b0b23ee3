"""The train config is parsed once into typed settings; nothing reads it after the build."""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_object
from omegaconf import OmegaConf

from torchrl_mbmf.runs.resume import DEFAULT_TARGETS
from torchrl_mbmf.trainers import Trainer
from torchrl_mbmf.trainers.settings import GROUPS, TrainConfig

ROOT = Path(__file__).resolve().parents[2]
#: Fields a group's settings may have before its builder takes them (none today).
PENDING: dict[str, set[str]] = {}


def _compose(*overrides: str):
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose("train", overrides=list(overrides))


@pytest.mark.parametrize("group", sorted(GROUPS))
def test_group_fields_are_the_builders_keys_with_its_defaults(group):
    params = inspect.signature(get_object(DEFAULT_TARGETS[group])).parameters.values()
    builder = {p.name: p.default for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY}
    fields = {
        f.name: f.default
        for f in dataclasses.fields(GROUPS[group])
        if f.name not in ("target", "extra")
    }
    assert set(fields) - set(builder) <= PENDING.get(group, set())
    for name, default in builder.items():
        assert name in fields, name
        expected = dataclasses.MISSING if default is inspect.Parameter.empty else default
        assert fields[name] == expected, name


def test_the_parsed_config_holds_every_group_value():
    cfg = _compose("method=ppo_mpc", "env=pendulum", "planner.horizon=7", "ppo.lr=0.001")
    config = TrainConfig.from_config(cfg)
    assert config.planner.horizon == 7 and config.ppo.lr == 0.001
    for group in GROUPS:
        node = OmegaConf.to_container(cfg[group], resolve=True)
        options = getattr(config, group).options()
        assert {k: v for k, v in node.items() if k != "_target_"}.items() <= options.items()
    assert (
        config.env.id == "Pendulum-v1" and config.checkpoint.keep_last == cfg.checkpoint.keep_last
    )


def test_nothing_reads_the_raw_config_after_the_trainer_is_built(tmp_path):
    # a model-based run builds its planner after the first fit: from the parsed settings
    cfg = _compose(
        "method=ppo_mpc",
        "env=pendulum",
        "total_steps=500",
        "ppo.frames_per_batch=100",
        "ppo.minibatch_size=50",
        "ppo.hidden_sizes=[16]",
        "planning_updates=1",
        "world_model.random_steps=200",
        "world_model.max_epochs=1",
        "world_model.hidden_sizes=[16]",
        "world_model.save_fits=false",
        "planner.num_candidates=4",
        "planner.horizon=2",
        "eval_every=100000",
        "checkpoint.every_steps=100000",
        "progress=false",
        "threads=1",
    )
    trainer = Trainer(cfg, tmp_path / "run")
    OmegaConf.set_readonly(cfg, False)
    OmegaConf.set_struct(cfg, False)
    for key in list(cfg.keys()):
        del cfg[key]
    summary = trainer.train()
    assert summary["real_steps"] == 500 and summary["switch_step"] is not None
