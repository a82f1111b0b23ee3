"""Every train setting is type- and range-checked, and unknown keys are refused, before any work.

The trainer's own settings and the checks across keys are the config's
(``validate_train_config``); a component group's values are checked by its constructor when the
run builds it (``build_for_checks``: what ``recipes/train.py`` does before collecting).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from rl_helpers import build_for_checks

from torchrl_mbmf.trainers import ConfigError, validate_train_config
from torchrl_mbmf.trainers.components import DEFAULT_TARGETS
from torchrl_mbmf.trainers.config import flatten_config, resume_changes, train_setting_keys

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")


def _compose(*overrides: str):
    with initialize_config_dir(CONFIGS, version_base="1.3"):
        return compose("train", overrides=list(overrides))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["ppo.gamma=5"], "ppo.gamma must be a number in (0, 1], got 5"),
        (["env.id=Nonexistent-v0"], "env.id='Nonexistent-v0' is not a registered Gymnasium id"),
        (["env.id=Hoper-v5"], "close ids: ['Hopper-v5'"),
        (["env.device=banana"], "env.device='banana' is not a torch device"),
        (
            ["method=sac", "sac.batch_size=512", "sac.replay_size=300"],
            "sac.batch_size=512 is larger than sac.replay_size=300",
        ),
        (
            ["method=sac", "sac.frames_per_batch=1000", "sac.replay_size=500"],
            "sac.replay_size=500 is smaller than sac.frames_per_batch=1000",
        ),
        (
            ["method=sac", "total_steps=5000"],
            "sac.init_random_frames=5000 leaves no steps of total_steps=5000",
        ),
        (["method=sac", "sac.gamma=0"], "sac.gamma must be a number in (0, 1], got 0"),
        (["method=sac", "sac.scale=exp"], "sac.scale='exp' is not supported; allowed: ['biased"),
        (["eval_episodes=-1"], "eval_episodes must be an integer >= 0, got -1"),
        (["method=sac", "sac.utd_ratio=-1"], "sac.utd_ratio must be a number > 0, got -1"),
        (
            ["method=sac", "sac.init_random_frames=-5"],
            "sac.init_random_frames must be an integer >= 0, got -5",
        ),
        (["seed=-1"], "seed must be an integer in [0, 4294967295], got -1"),
        (["ppo.lr=abc"], "ppo.lr must be a number > 0, got 'abc'"),
        (["ppo.lr=nan"], "ppo.lr must be a number > 0, got nan"),
        (["ppo.clip_epsilon=inf"], "ppo.clip_epsilon must be a number in (0, 1], got inf"),
        (["ppo.hidden_sizes=[0]"], "ppo.hidden_sizes must be a list of integers >= 1, got [0]"),
        (
            ["world_model.hidden_sizes=[64,-1]"],
            "world_model.hidden_sizes must be a sequence of integers >= 1, got [64, -1]",
        ),
        (
            ["method=sac", "sac.hidden_sizes=64"],
            "sac.hidden_sizes must be a list of integers >= 1, got 64",
        ),
        (["planner.horizon=2.5"], "planner.horizon must be an integer >= 1, got 2.5"),
        # the refinement keys are checked without a refinement too (were accepted unused)
        (["planner.temperature=nan"], "planner.temperature must be a finite number >= 0, got nan"),
        (["planner.temperature=0"], "planner.temperature must be > 0, got 0"),
        (["planner.min_std=-1"], "planner.min_std must be a finite number >= 0, got -1"),
        (["planner.iterations=2.5"], "planner.iterations must be an integer >= 1, got 2.5"),
        (["planner.policy_fraction=1"], "planner.policy_fraction must be in [0, 1.0), got 1"),
        (["ppo.epochs=true"], "ppo.epochs must be an integer >= 1, got True"),
        (["progress=yes"], "progress must be true or false, got 'yes'"),
        (["threads=0"], "threads must be null or an integer >= 1, got 0"),
        (["ppo.distribution=beta"], "ppo.distribution='beta' is not supported; allowed"),
        (["ppo.lmbda=1.5"], "ppo.lmbda must be a number in [0, 1], got 1.5"),
        (["method=sac", "sac.tau=0"], "sac.tau must be a number in (0, 1], got 0"),
        (["world_model.val_fraction=1"], "world_model.val_fraction must be a number in (0, 1)"),
        (["world_model.lr=-1e-4"], "world_model.lr must be a number > 0"),
        (["planning_updates=-1"], "planning_updates must be an integer >= 0, got -1"),
        (["checkpoint.keep_last=0"], "checkpoint.keep_last must be an integer >= 1, got 0"),
        (["ppo.entropy_coeff=-1"], "ppo.entropy_coeff must be a number >= 0, got -1"),
        (["ppo.init_log_std=nan"], "ppo.init_log_std must be a finite number, got nan"),
        # unknown keys, anywhere in the tree, are named (with the setting probably meant)
        (["+planer.horizon=5"], "planer.horizon is not a setting of the train config"),
        (["+ppo.learning_rate=1e-3"], "ppo.learning_rate is not a setting of the train config"),
        (["+total_step=10"], "total_step is not a setting of the train config"),
        (["+reward.kwargs.treshold=-0.3"], "reward.kwargs.treshold is not a parameter of"),
        (
            ["reward=head_pen", "reward.kwargs.threshold=nan"],
            "reward.kwargs: threshold must be a finite number, got nan",
        ),
    ],
)
def test_bad_setting_names_key_and_value(overrides, message, tmp_path):
    cfg = _compose(*overrides)
    escaped = message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
    with pytest.raises(ConfigError, match=escaped.replace("]", r"\]")):
        build_for_checks(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()  # nothing written for a refused config


def test_unknown_key_suggests_the_close_setting():
    with pytest.raises(ConfigError, match=r"did you mean 'planner\.horizon'"):
        validate_train_config(_compose("+planer.horizon=5"))


def test_every_composed_setting_has_a_check():
    """The schema covers every key of every shipped config group (no drift either way)."""
    groups = ("env", "reward", "world_model", "planner", "logger", "experiment", "budget")
    root = Path(CONFIGS)
    for group in groups:
        for path in sorted((root / group).glob("*.yaml")):
            validate_train_config(_compose(f"{group}={path.stem}"))
    keys = set(train_setting_keys(_compose()))
    assert {"ppo.gamma", "sac.utd_ratio", "seed", "eval_episodes", "planner._target_"} <= keys


def test_groups_name_their_builders():
    """Each component group's ``_target_`` is the builder a config without one means."""
    cfg = _compose()
    assert {group: cfg[group]["_target_"] for group in DEFAULT_TARGETS} == DEFAULT_TARGETS


def test_a_run_folder_config_from_before_targets_validates_and_resumes(tmp_path):
    """``data/config_before_targets.yaml`` is a run folder's ``config.yaml`` written before the
    groups named their builders (the command of the campaign's runs). It validates, builds, and
    a resume with today's config of the same command changes nothing."""
    from torchrl_mbmf.runs.resume import fingerprint

    old = OmegaConf.load(Path(__file__).parent / "data" / "config_before_targets.yaml")
    assert "_target_" not in old.planner
    command = ["method=sac_mpc", "planner.horizon=10", "reward=head_pen", "seed=2"]
    # the campaign's SAC settings, the defaults before the SAC ablation changed them
    command += ["sac.frames_per_batch=1000", "sac.loss_function=smooth_l1"]
    command += ["sac.scale=biased_softplus"]  # and before SB3's scale became the default
    now = _compose(*command, "budget=thesis", "threads=1", "progress=false")
    validate_train_config(old)
    assert resume_changes(flatten_config(old), flatten_config(now)) == ({}, {})
    assert fingerprint(old) == fingerprint(now)
    old.world_model.hidden_sizes = [8]  # the default builders, from a config without targets
    old.sac.hidden_sizes = [8]
    build_for_checks(old, tmp_path / "run")
    assert (tmp_path / "run" / "config.yaml").exists()
    old.planner._target_ = "some.other.planner"
    refused, _ = resume_changes(flatten_config(old), flatten_config(now))
    assert "planner._target_" in refused


def test_valid_edge_values_pass():
    cfg = _compose(
        "ppo.gamma=1",
        "sac.init_random_frames=0",
        "threads=2",
        "planning_updates=0",
        "world_model.hidden_sizes=[]",
        "ppo.lr=1",
    )
    validate_train_config(cfg)
    assert math.isclose(cfg.ppo.gamma, 1.0)


def test_resume_changes_split():
    saved = flatten_config(_compose("env=pendulum"))
    now = flatten_config(
        _compose(
            "env=pendulum",
            "ppo.lr=0.01",
            "checkpoint.every_steps=100",
            "logger.backend=tensorboard",
            "total_steps=5",
            "threads=2",
            "eval_episodes=3",
            "experiment=exp1_horizon",
        )
    )
    refused, allowed = resume_changes(saved, now)
    assert set(refused) >= {"ppo.lr", "checkpoint.every_steps", "logger.backend"}
    assert refused["ppo.lr"] == (3e-4, 0.01)
    assert {"total_steps", "threads", "eval_episodes", "experiment.name"} <= set(allowed)
    assert not set(refused) & set(allowed)
    assert resume_changes(saved, dict(saved)) == ({}, {})


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("planner.horizon=0", "planner.horizon must be an integer >= 1, got 0"),
        ("planner.num_candidates=2.5", "planner.num_candidates must be an integer >= 1, got 2.5"),
    ],
)
def test_planner_errors_name_the_planner_group(override, message, tmp_path):
    # the planner is built inside the world-model part: its error names its own group only
    cfg = _compose("method=ppo_mpc", "env=pendulum", override)
    with pytest.raises(ConfigError) as err:
        build_for_checks(cfg, tmp_path / "run")
    assert str(err.value) == message


def test_a_run_dir_that_is_a_file_is_refused_naming_it(tmp_path):
    from torchrl_mbmf.runs.claim import RunFolderError

    path = tmp_path / "notes.txt"
    path.write_text("mine")
    cfg = _compose("method=ppo", "env=pendulum")
    with pytest.raises(
        RunFolderError, match=r"run_dir='.*notes\.txt' is a file, expected a folder"
    ):
        build_for_checks(cfg, path)
    assert path.read_text() == "mine"


def test_a_run_dir_that_cannot_be_created_or_written_is_refused(tmp_path, monkeypatch):
    import torchrl_mbmf.runs.claim as claim

    (tmp_path / "file").write_text("")
    cfg = _compose("method=ppo", "env=pendulum")
    with pytest.raises(claim.RunFolderError, match=r"file/run' cannot be created"):
        build_for_checks(cfg, tmp_path / "file" / "run")
    # an unwritable folder (root writes anywhere: the permission check is what is tested)
    monkeypatch.setattr(claim.os, "access", lambda path, mode: False)
    with pytest.raises(claim.RunFolderError, match=r"run' is not writable"):
        build_for_checks(cfg, tmp_path / "run")


def test_a_ppo_run_resumes_across_a_change_of_the_sac_defaults():
    """The policy group a method does not train is no change on resume (nothing builds it)."""
    old = OmegaConf.load(Path(__file__).parent / "data" / "config_before_targets.yaml")
    old.method = "ppo_mpc"
    now = _compose("method=ppo_mpc", "planner.horizon=10", "reward=head_pen", "seed=2")
    now.budget = old.budget
    refused, _ = resume_changes(flatten_config(old), flatten_config(now))
    assert not any(key.startswith("sac.") for key in refused)
    now.sac.lr = 1.0
    now.ppo.lr = 1.0
    refused, _ = resume_changes(flatten_config(old), flatten_config(now))
    assert "ppo.lr" in refused and "sac.lr" not in refused
