"""The phase schedule: which policy acts, refits and the warm start, per method."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from torchrl_mbmf.trainers.schedule import Actor, Phase, PhaseSchedule, Progress

CFG = {
    "planning_updates": 2,
    "world_model": {"refit_every": 2},
    "sac": {"refit_every_steps": 100, "init_random_frames": 50},
}


def _progress(phase: Phase, steps: int = 0, updates: int = 0) -> Progress:
    return Progress(phase=phase.value, real_steps=steps, updates=updates)


@pytest.mark.parametrize(
    ("method", "first", "planning_updates"),
    [
        ("ppo", Phase.MODEL_FREE, None),
        ("sac", Phase.MODEL_FREE, None),
        ("mpc", Phase.RANDOM, 2),
        ("ppo_mpc", Phase.RANDOM, 2),
        ("sac_mpc", Phase.RANDOM, None),
    ],
)
def test_each_method_reads_its_own_settings(method, first, planning_updates):
    schedule = PhaseSchedule.from_config(OmegaConf.create({"method": method, **CFG}))
    assert schedule.first_phase() is first
    assert schedule.planning_updates == planning_updates
    # only SAC methods refit by steps; a PPO-MPC run never reads sac.refit_every_steps
    assert (schedule.refit_every_steps is not None) == (method == "sac_mpc")
    assert (schedule.init_random_frames > 0) == (method == "sac")


def test_ppo_mpc_plans_refits_by_updates_then_switches():
    schedule = PhaseSchedule.from_config(OmegaConf.create({"method": "ppo_mpc", **CFG}))
    progress = _progress(Phase.RANDOM)
    assert schedule.actor(progress) is Actor.RANDOM
    schedule.start_planning(progress)
    assert schedule.actor(progress) is Actor.PLANNER
    progress.updates = 1
    assert not schedule.refit_due(progress, planned=True)
    assert not schedule.round_over(progress, Actor.PLANNER)
    progress.updates = 2  # planning is over: no refit, the round ends, the switch is due
    assert not schedule.refit_due(progress, planned=True)
    assert schedule.round_over(progress, Actor.PLANNER) and schedule.switch_due(progress)
    schedule.start_model_free(progress)
    assert schedule.actor(progress) is Actor.AGENT and progress.switch_step == 0


def test_sac_mpc_refits_every_steps_and_sac_starts_random():
    schedule = PhaseSchedule.from_config(OmegaConf.create({"method": "sac_mpc", **CFG}))
    progress = _progress(Phase.RANDOM, steps=300)
    schedule.start_planning(progress)
    assert progress.next_refit == 400
    progress.real_steps = 420
    assert schedule.refit_due(progress, planned=True) and progress.next_refit == 500
    assert not schedule.switch_due(progress)
    sac = PhaseSchedule.from_config(OmegaConf.create({"method": "sac", **CFG}))
    progress = _progress(Phase.MODEL_FREE, steps=0)
    assert sac.actor(progress) is Actor.RANDOM and sac.round_over(progress, Actor.RANDOM)
    progress.real_steps = 50
    assert sac.actor(progress) is Actor.AGENT


def test_bad_schedule_names_the_value():
    with pytest.raises(ValueError, match="planning_updates must be an integer >= 1, got 0"):
        PhaseSchedule(model_based=True, planning_updates=0)


def test_progress_round_trips_an_old_dict_checkpoint():
    # a progress record as checkpoints stored it before Progress, with an entry it does not know
    old = {
        "real_steps": 800,
        "random_steps": 200,
        "updates": 3,
        "phase": "planning",
        "episodes": 4,
        "last_returns": [1.0, 2.0],
        "next_eval": 1000,
        "next_checkpoint": 1200,
        "next_refit": 0,
        "switch_step": None,
        "fingerprint": {"seed": 0},
        "config": {"seed": 0},
        "last_fit_transitions": 600,
        "future_entry": 7,
    }
    progress = Progress()
    progress.load_dict(old)
    assert progress.real_steps == 800 and progress.phase == "planning"
    assert progress.last_fit_transitions == 600 and progress.disagreement_threshold is None
    assert progress.extra == {"future_entry": 7} and progress["future_entry"] == 7
    assert progress.to_dict() == old
    # a checkpoint older than saved configs has no "config": it stays unset and unwritten
    del old["config"]
    progress.load_dict(old)
    assert progress.config is None and progress.get("config") is None
    assert "config" not in progress.to_dict()
