"""The import paths of names that left ``torchrl_mbmf.trainers`` keep working for one release."""

from __future__ import annotations

import importlib
import re

import pytest

import torchrl_mbmf.trainers as trainers

# (old module, name, new module): the README's component table and the paths tests used.
T, W, R = "torchrl_mbmf.trainers", "torchrl_mbmf.world_model", "torchrl_mbmf.runs"
MOVED = [
    (f"{T}.dataset_replay", "DatasetReplay", f"{R}.dataset_replay"),
    (
        f"{T}.dataset_replay",
        "compact_checkpoint",
        f"{R}.dataset_replay",
    ),
    (
        f"{T}.dataset_replay",
        "expand_checkpoint",
        f"{R}.dataset_replay",
    ),
    ("torchrl_mbmf.trainers", "fit_dynamics", "torchrl_mbmf.world_model.fit"),
    ("torchrl_mbmf.trainers", "FusedPPOUpdate", "torchrl_mbmf.objectives.fused_ppo"),
    ("torchrl_mbmf.trainers", "FusedSACUpdate", "torchrl_mbmf.objectives.fused_sac"),
    ("torchrl_mbmf.trainers", "RunCheckpoint", "torchrl_mbmf.runs.checkpoint"),
    ("torchrl_mbmf.trainers", "fit_ensemble", "torchrl_mbmf.world_model.ensemble_fit"),
    ("torchrl_mbmf.trainers", "transition_tensors", "torchrl_mbmf.world_model.fit_data"),
    ("torchrl_mbmf.trainers.dynamics", "fit_dynamics_kwargs", "torchrl_mbmf.world_model.fit"),
    (f"{T}.world_model_fit", "fit_world_model", "torchrl_mbmf.world_model.fit"),
    ("torchrl_mbmf.trainers.fit_history", "FitHistory", "torchrl_mbmf.world_model.fit_history"),
    (
        f"{T}.fit_records",
        "save_fit_snapshot",
        f"{W}.snapshots",
    ),
    ("torchrl_mbmf.trainers.ensemble_fit", "fit_ensemble", "torchrl_mbmf.world_model.ensemble_fit"),
    ("torchrl_mbmf.trainers.checkpointing", "verify_checkpoint", "torchrl_mbmf.runs.storage"),
    ("torchrl_mbmf.trainers.resume", "RunCheckpoint", "torchrl_mbmf.runs.checkpoint"),
    ("torchrl_mbmf.trainers.resume", "write_run_record", "torchrl_mbmf.runs.layout"),
    ("torchrl_mbmf.trainers.resume_logs", "cut_csv_logs", "torchrl_mbmf.runs.logs"),
    ("torchrl_mbmf.trainers.export", "variant_tag", "torchrl_mbmf.runs.export"),
    ("torchrl_mbmf.trainers.guards", "check_finite", "torchrl_mbmf.checks"),
    ("torchrl_mbmf.trainers.ppo", "FusedPPOUpdate", "torchrl_mbmf.objectives.fused_ppo"),
    ("torchrl_mbmf.trainers.sac", "sac_update_step", "torchrl_mbmf.objectives.fused_sac"),
    ("torchrl_mbmf.trainers.sac", "ReplaySampler", "torchrl_mbmf.data.replay"),
    ("torchrl_mbmf.trainers.sac", "keep_freed_memory", "torchrl_mbmf.device"),
    (f"{T}.device", "resolve_device", "torchrl_mbmf.device"),
    (f"{T}.device", "keep_freed_memory", "torchrl_mbmf.device"),
    (f"{T}.signals", "StopRequest", f"{R}.signals"),
    (f"{T}.build", "make_collector", "torchrl_mbmf.collectors.factory"),
    (f"{T}.build", "evaluate_policy", "torchrl_mbmf.collectors.factory"),
    (f"{T}.planning", "make_world_model", f"{W}.networks"),
    (f"{T}.planning", "make_termination_head", f"{W}.networks"),
    (f"{T}.progress", "end_of_run_message", f"{R}.summary_text"),
    (f"{T}.progress", "format_seconds", f"{R}.summary_text"),
]


@pytest.mark.parametrize(("old", "name", "new"), MOVED, ids=[f"{o}.{n}" for o, n, _ in MOVED])
def test_old_path_warns_and_gives_the_same_object(old, name, new):
    module = importlib.import_module(old)
    with pytest.warns(DeprecationWarning, match=re.escape(f"{new}.{name}")):
        obj = getattr(module, name)
    assert obj is getattr(importlib.import_module(new), name)


def test_from_import_statement_of_an_old_module():
    with pytest.warns(DeprecationWarning, match=f"{R}.dataset_replay"):
        from torchrl_mbmf.trainers.dataset_replay import compact_checkpoint
    from torchrl_mbmf.runs.dataset_replay import compact_checkpoint as new

    assert compact_checkpoint is new


def test_every_name_of_every_moved_module_is_reachable():
    for old, targets in trainers.MOVED_MODULES.items():
        module = importlib.import_module(f"torchrl_mbmf.trainers.{old}")
        names = [n for t in targets for n in importlib.import_module(t).__all__]
        assert names and module.__all__ == names
        for name in names:
            with pytest.warns(DeprecationWarning):
                getattr(module, name)


def test_unknown_names_still_fail():
    with pytest.raises(AttributeError, match="no_such_name"):
        trainers.no_such_name  # noqa: B018
    with pytest.raises(AttributeError, match="no_such_name"):
        importlib.import_module(f"{T}.dataset_replay").no_such_name  # noqa: B018


def test_moved_names_left_the_public_list():
    assert not set(trainers.MOVED_NAMES) & set(trainers.__all__)


@pytest.mark.parametrize("module", [f"{T}.build", f"{T}.planning", f"{T}.progress"])
def test_live_modules_list_their_moved_names_and_still_refuse_others(module):
    live = importlib.import_module(module)
    assert live.MOVED_NAMES and not set(live.MOVED_NAMES) & set(live.__all__)
    with pytest.raises(AttributeError, match="no_such_name"):
        live.no_such_name  # noqa: B018
