"""Resume-safe settings changed on resume apply from the resume point on (issue 33, item 3).

What a user gets, tested row for row against a fresh run with the new settings:

* ``eval_every``: the evaluations after the resume step are those of a fresh run with the new
  schedule (the next one at the first batch reaching the next multiple of the new period);
* ``eval_episodes``: each later evaluation averages the new number of episodes;
* ``total_steps``: raised, the run continues to it (a finished run too); equal to the
  checkpoint's steps, it ends at once; lower, the resume is refused before anything is read
  but the checkpoint's progress;
* ``checkpoint.keep_last``: later saves keep the new number of checkpoints;
* ``device=auto`` resolving to the recorded device is not a change.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchrl_mbmf.checks import ConfigError
from torchrl_mbmf.runs.resume import resume_changes
from torchrl_mbmf.trainers import Trainer
from torchrl_mbmf.trainers.hooks import Evaluation

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "method=ppo",
    "env=pendulum",
    "ppo.frames_per_batch=160",
    "ppo.hidden_sizes=[16,16]",
    "checkpoint.every_steps=160",
    "progress=false",
    "threads=1",
]
#: The schedule the run is resumed with (and a fresh run runs from its start).
NEW = ["total_steps=960", "eval_every=320", "eval_episodes=2", "checkpoint.keep_last=1"]


def _cfg(*overrides: str):
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose("train", overrides=[*TINY, *overrides])


def _rows(run: Path, name: str) -> list[tuple[int, float]]:
    path = run / "logs" / "scalars" / f"{name}.csv"
    with path.open() as f:
        return [(int(step), float(value)) for step, value in csv.reader(f)]


@pytest.fixture(scope="module")
def first_part(tmp_path_factory):
    """A finished run of 480 steps: evaluation every 800 steps, 1 episode, 3 checkpoints."""
    run = tmp_path_factory.mktemp("first") / "run"
    old = ["total_steps=480", "eval_every=800", "eval_episodes=1", "checkpoint.keep_last=3"]
    Trainer(_cfg(*old), run).train()
    return run


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """A run with the new settings from its start."""
    run = tmp_path_factory.mktemp("fresh") / "run"
    return run, Trainer(_cfg(*NEW), run).train()


def test_new_schedule_on_resume_logs_the_rows_of_a_fresh_run(first_part, fresh, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(first_part, run)
    before = _rows(run, "eval/return")
    assert [step for step, _ in before] == [160]
    summary = Trainer(_cfg(*NEW), run).train()  # a raised total_steps continues a finished run
    fresh_run, fresh_summary = fresh
    assert summary["resumed"] and summary["real_steps"] == 960
    # the training is the same: the schedule changes only what is evaluated and kept
    assert summary["params_sha256"] == fresh_summary["params_sha256"]
    rows, reference = _rows(run, "eval/return"), _rows(fresh_run, "eval/return")
    assert [step for step, _ in reference] == [160, 320, 640, 960]
    # up to the resume step the old schedule's rows, after it exactly the fresh run's (the
    # returns too: the same policy evaluated over the same 2 episodes)
    assert rows[:1] == before and rows[1:] == [r for r in reference if r[0] > 480]
    assert summary["final_eval_return"] == pytest.approx(fresh_summary["final_eval_return"])
    kept = sorted(p.name for p in (run / "checkpoints").glob("checkpoint-*"))
    assert kept == ["checkpoint-000000000960"]
    log = json.loads((run / "resume_log.json").read_text())[-1]["allowed_changes"]
    assert set(log) == {"total_steps", "eval_every", "eval_episodes", "checkpoint.keep_last"}


def test_total_steps_below_the_checkpoint_is_refused_equal_ends_at_once(first_part, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(first_part, run)
    (run / "summary.json").unlink()  # as a run killed after its last checkpoint
    rows = (run / "logs" / "scalars" / "eval" / "return.csv").read_text()
    old = ["eval_every=800", "eval_episodes=1", "checkpoint.keep_last=3"]
    with pytest.raises(ConfigError, match=r"total_steps=320 is below the 480 real steps"):
        Trainer(_cfg("total_steps=320", *old), run)
    # refused before the logs were cut or the resume recorded
    assert (run / "logs" / "scalars" / "eval" / "return.csv").read_text() == rows
    assert not (run / "resume_log.json").exists()
    summary = Trainer(_cfg("total_steps=480", *old), run).train()
    assert summary["real_steps"] == 480 and summary["resumed"]


@pytest.mark.parametrize("every", [320, 200, 100, 1000])
@pytest.mark.parametrize(("random_steps", "batch"), [(0, 160), (300, 160), (1000, 200)])
def test_next_eval_at_is_the_hook_run_from_the_start(every, random_steps, batch):
    hook = Evaluation(every=every, episodes=0)
    trainer = type("T", (), {})()
    from torchrl_mbmf.trainers.schedule import Progress

    trainer.progress = Progress(real_steps=random_steps, random_steps=random_steps)
    for _ in range(12):
        trainer.progress.real_steps += batch
        hook(trainer, None)
        steps = trainer.progress.real_steps
        assert hook.next_eval_at(steps, random_steps, batch) == trainer.progress.next_eval


def test_device_auto_resolving_to_the_recorded_device_is_no_change():
    here = "cuda:0" if torch.cuda.is_available() else "cpu"
    assert resume_changes({"device": here}, {"device": "auto"}) == ({}, {})
    assert resume_changes({"device": "auto"}, {"device": here}) == ({}, {})
    other = "cpu" if here != "cpu" else "cuda:0"
    refused, _ = resume_changes({"device": other}, {"device": "auto"})
    assert refused == {"device": (other, "auto")}
