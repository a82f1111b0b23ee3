"""scripts/campaign.py: which run a worker takes next, and what it copies for committing."""

from __future__ import annotations

import datetime as dt
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("campaign", ROOT / "scripts" / "campaign.py")
campaign = importlib.util.module_from_spec(_spec)
sys.modules["campaign"] = campaign
_spec.loader.exec_module(campaign)

QUEUE = """\
# priority order
a train method=ppo seed=0
b sb3_reference method=sac seed=0
c train method=sac seed=0   # trailing comment
"""


def _queue(tmp_path: Path, text: str = QUEUE) -> list:
    path = tmp_path / "queue.txt"
    path.write_text(text)
    return campaign.read_queue(path)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_queue_lines_parse_and_bad_ones_are_named(tmp_path):
    queue = _queue(tmp_path)
    assert [(r.name, r.recipe, r.overrides) for r in queue] == [
        ("a", "train", ("method=ppo", "seed=0")),
        ("b", "sb3_reference", ("method=sac", "seed=0")),
        ("c", "train", ("method=sac", "seed=0")),
    ]
    assert [r.resumable for r in queue] == [True, False, True]
    with pytest.raises(ValueError, match=r"queue.txt:1: 'x fit seed=0'.*recipe"):
        _queue(tmp_path, "x fit seed=0\n")
    with pytest.raises(ValueError, match=r"queue.txt:2: run .a. is queued twice"):
        _queue(tmp_path, "a train\na train seed=1\n")


def test_worker_takes_the_first_run_neither_done_nor_claimed_by_a_live_process(tmp_path):
    root = tmp_path / "runs"
    queue = _queue(tmp_path)
    (root / "a").mkdir(parents=True)
    (root / "a" / "summary.json").write_text("{}")  # done
    assert campaign.run_state(root, queue[0]) == "done"
    first = campaign.claim_next(root, queue, None)
    assert first.name == "b"
    assert campaign.claim_owner(root, "b") == os.getpid()
    assert campaign.run_state(root, queue[1]) == "running"
    assert campaign.claim_next(root, queue, None).name == "c"
    assert campaign.claim_next(root, queue, None) is None  # every run done or running
    # a claim left by a process that died (an interrupted session) is taken again
    (root / ".claims" / "c").write_text(f"{_dead_pid()}\n")
    (root / "c" / "logs").mkdir(parents=True)
    assert campaign.run_state(root, queue[2]) == "interrupted"
    assert campaign.claim_next(root, queue, None).name == "c"


def test_a_fresh_machine_does_not_run_again_what_the_committed_copies_show_done(tmp_path):
    root, results = tmp_path / "runs", tmp_path / "results"
    queue = _queue(tmp_path)
    (results / "a").mkdir(parents=True)
    (results / "a" / "summary.json").write_text("{}")  # finished on an earlier machine
    (results / "b" / "logs").mkdir(parents=True)  # a partial snapshot: not done
    assert campaign.run_state(root, queue[0]) == "queued"  # without the copies: unknown here
    assert campaign.run_state(root, queue[0], results) == "done"
    assert campaign.run_state(root, queue[1], results) == "queued"
    assert campaign.claim_next(root, queue, None, results=results).name == "b"
    assert campaign.claim_next(root, queue, None, results=results).name == "c"
    assert campaign.claim_next(root, queue, None, results=results) is None


def test_failed_runs_and_unresumable_runs_without_time_are_passed_over(tmp_path):
    root = tmp_path / "runs"
    queue = _queue(tmp_path)
    soon = dt.datetime.now(dt.UTC) + dt.timedelta(minutes=10)
    # b (SB3 SAC) cannot resume and would not finish in 10 minutes: c goes first
    assert campaign.claim_next(root, queue, soon, frozenset({"a"})).name == "c"
    (root / ".claims" / "c").unlink()
    later = dt.datetime.now(dt.UTC) + dt.timedelta(hours=3)
    assert campaign.claim_next(root, queue, later, frozenset({"a"})).name == "b"


def test_a_run_starts_only_where_what_a_fresh_machine_would_lose_fits_in_the_session(tmp_path):
    queue = _queue(
        tmp_path,
        "sac train method=sac_mpc total_steps=200000 seed=0\n"
        "sb3 sb3_reference method=sac seed=0\n"
        "tune train method=ppo_mpc seed=0\n"
        "plan train method=mpc planner.horizon=25 total_steps=419600 seed=0\n"
        "ppo train method=ppo seed=0\n",
    )
    minutes = [campaign.at_risk_seconds(run) / 60 for run in queue]
    # SAC-MPC's compact size is unmeasured, SB3 cannot resume; MPC and PPO-MPC planning
    # checkpoints are committed compacted (their dataset replaced by its replay), PPO's as
    # they are
    assert minutes == [100, 70, 0, 0, 0]
    root = tmp_path / "runs"
    hours = lambda h: dt.datetime.now(dt.UTC) + dt.timedelta(hours=h)  # noqa: E731
    assert [campaign.claim_next(root, queue, hours(3)).name for _ in range(3)] == [
        "sac",
        "sb3",
        "tune",
    ]
    for name in ("sac", "sb3", "tune"):
        (root / ".claims" / name).unlink()
    assert campaign.claim_next(root, queue, hours(0.5)).name == "tune"  # neither SAC fits
    (root / ".claims" / "tune").unlink()
    # the SAC-MPC run, interrupted on this machine at 150,000 steps: 25 minutes of it left
    steps = root / "sac" / "logs" / "scalars" / "train"
    steps.mkdir(parents=True)
    (steps / "episode_return.csv").write_text("150000,1.0\n")
    assert campaign.at_risk_seconds(queue[0], 150_000) / 60 == pytest.approx(25)
    assert campaign.claim_next(root, queue, hours(0.5)).name == "sac"  # fits, and kept here
    (root / ".claims" / "sac").unlink()
    # nothing fits: a resumable run continues only if the next session keeps this machine
    # (a fallback); an SB3 run that would not finish is never started
    sac_only = [queue[1], queue[0]]
    assert campaign.claim_next(root, sac_only, hours(0.1)).name == "sac"
    (root / ".claims" / "sac").unlink()
    assert campaign.claim_next(root, sac_only, hours(0.1), fallback=False) is None
    assert campaign.claim_next(root, queue[1:2], hours(0.1)) is None
    # among fallbacks, one interrupted here goes before one not started
    fresh = tmp_path / "fresh"
    sac_mpc = campaign.QueuedRun("sm", "train", ("method=sac_mpc", "total_steps=200000"))
    (fresh / "sac" / "logs").mkdir(parents=True)
    assert campaign.claim_next(fresh, [sac_mpc, queue[0]], hours(0.1)).name == "sac"
    assert campaign.claim_next(fresh, [sac_mpc, queue[0]], hours(0.1)).name == "sm"


def test_runs_interrupted_here_that_fit_go_before_the_queue_order(tmp_path):
    queue = _queue(
        tmp_path,
        "first train method=ppo_mpc total_steps=419600 seed=0\n"
        "second train method=ppo_mpc total_steps=419600 seed=1\n",
    )
    root = tmp_path / "runs"
    steps = root / "second" / "logs" / "scalars" / "train"
    steps.mkdir(parents=True)
    (steps / "episode_return.csv").write_text("200000,1.0\n")  # interrupted here
    later = dt.datetime.now(dt.UTC) + dt.timedelta(hours=3)
    assert campaign.claim_next(root, queue, later).name == "second"  # its work is kept
    assert campaign.claim_next(root, queue, later).name == "first"


def test_small_files_are_copied_without_the_machines_paths(tmp_path):
    root = tmp_path / "far" / "runs"
    run = root / "r"
    (run / "logs" / "scalars" / "train").mkdir(parents=True)
    (run / "checkpoints" / "checkpoint-1").mkdir(parents=True)
    (run / "checkpoints" / "checkpoint-1" / "big.bin").write_bytes(b"x")
    (run / "config.yaml").write_text(f"run_dir: {run}\nseed: 0\n")
    (run / "train.log").write_text(f"resumed from {run}/checkpoints/checkpoint-1\n")
    (run / "logs" / "scalars" / "train" / "episode_return.csv").write_text("1000,5.0\n")
    (run / "policy.pt").write_bytes(b"\x00\x01")
    dest = tmp_path / "results" / "r"
    dest.mkdir(parents=True)
    (dest / "stale.txt").write_text("an older copy")
    campaign.copy_small_files(run, dest, str(root.parent) + os.sep)
    assert (dest / "config.yaml").read_text() == "run_dir: runs/r\nseed: 0\n"
    assert (dest / "train.log").read_text() == "resumed from runs/r/checkpoints/checkpoint-1\n"
    assert (dest / "logs/scalars/train/episode_return.csv").read_text() == "1000,5.0\n"
    assert (dest / "policy.pt").read_bytes() == b"\x00\x01"
    assert not (dest / "checkpoints").exists() and not (dest / "stale.txt").exists()


def _partial_run(root: Path, name: str, checkpoint_bytes: int) -> None:
    run = root / name
    (run / "logs" / "scalars" / "train").mkdir(parents=True)
    (run / "logs" / "scalars" / "train" / "episode_return.csv").write_text("1000,5.0\n2000,6.0\n")
    (run / "config.yaml").write_text(f"run_dir: {run}\n")
    for step in (1000, 2000):
        ckpt = run / "checkpoints" / f"checkpoint-{step:012d}"
        ckpt.mkdir(parents=True)
        (ckpt / "state.bin").write_bytes(b"x" * checkpoint_bytes)


def test_snapshot_keeps_small_checkpoints_and_a_fresh_machine_restores_them(tmp_path):
    root = tmp_path / "machine1" / "runs"
    results = tmp_path / "results"
    queue = _queue(tmp_path)
    _partial_run(root, "a", 100)  # a PPO-sized checkpoint (or a fine-tuning PPO-MPC one)
    _partial_run(root, "c", campaign.SMALL_CHECKPOINT_BYTES + 1)  # holds a dataset
    for name in ("a", "c"):  # world-model fit snapshots
        (root / name / "world_models" / "fit-000001000").mkdir(parents=True)
        (root / name / "world_models" / "fit-000001000" / "state").write_bytes(b"w")
    assert campaign.snapshot(root, queue, results) == ["a", "c"]
    assert [p.name for p in (results / "a" / "checkpoints").iterdir()] == [
        "checkpoint-000000002000"
    ]
    # the fits go with a restorable checkpoint (the finished run's fit evaluation reads them)
    assert (results / "a" / "world_models" / "fit-000001000" / "state").read_bytes() == b"w"
    assert not (results / "c" / "checkpoints").exists()
    assert not (results / "c" / "world_models").exists()
    assert (results / "c" / "logs/scalars/train/episode_return.csv").exists()
    fresh = tmp_path / "machine2" / "runs"
    fresh.mkdir(parents=True)
    assert campaign.restore(fresh, queue, results) == ["a"]
    restored = fresh / "a" / "checkpoints" / "checkpoint-000000002000" / "state.bin"
    assert restored.read_bytes() == b"x" * 100
    assert campaign.restore(fresh, queue, results) == []  # never over an existing folder
    # not past its committed checkpoint: the fresh machine's snapshot keeps the copy as it is
    assert campaign.snapshot(fresh, queue, results) == []
    table = campaign.ledger_table(fresh, queue, results)
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines()[2:]}
    assert "| interrupted | 2,000 | 1,000,000 | 2000 |" in rows["a"]
    assert "| lost, restarts | 2,000 | 1,000,000 | - |" in rows["c"]  # committed logs only
    assert "| queued | 0 |" in rows["b"]
    # the run then finishes on the fresh machine and its copy is committed; the first machine,
    # back later with its stale folder, neither snapshots it over the copy nor lists it open
    (results / "a" / "summary.json").write_text('{"real_steps": 3000}')
    assert campaign.snapshot(root, queue, results) == ["c"]
    assert (results / "a" / "summary.json").exists()
    done = campaign.ledger_table(root, queue, results).splitlines()[2]
    assert done.startswith("| a | done | 3,000 |")


def test_a_budget_raised_on_its_line_continues_a_finished_run_in_queue_order(tmp_path):
    root, results = tmp_path / "machine1" / "runs", tmp_path / "results"
    first = "x train method=sac seed=0 total_steps=2000\ny train method=sac seed=1\n"
    queue = _queue(tmp_path, first)
    for name in ("x", "y"):
        _partial_run(root, name, 100)
        (root / name / "summary.json").write_text('{"real_steps": 2000}')
    assert [campaign.run_state(root, r) for r in queue] == ["done", "done"]
    # x's line raised to 4000 (y names no total_steps: its summary ends it, as before)
    queue = _queue(tmp_path, first.replace("2000", "4000") + "z train method=ppo seed=0\n")
    (root / "z" / "logs").mkdir(parents=True)  # interrupted here
    assert campaign.run_state(root, queue[0]) == "raised"
    assert campaign.run_state(root, queue[1]) == "done"
    # the interrupted run goes first, the raised one keeps its queue place after it
    assert campaign.claim_next(root, queue, None).name == "z"
    assert campaign.claim_next(root, queue, None).name == "x"
    for name in ("x", "z"):
        (root / ".claims" / name).unlink()
    # its committed copy does not count as done, and carries its checkpoint
    assert campaign.snapshot(root, queue, results) == ["x", "z"]
    assert (results / "x" / "checkpoints" / "checkpoint-000000002000").is_dir()
    table = campaign.ledger_table(root, queue, results)
    assert "| x | raised | 2,000 | 4,000 |" in table
    fresh = tmp_path / "machine2" / "runs"
    fresh.mkdir(parents=True)
    assert campaign.run_state(fresh, queue[0], results) == "queued"
    assert campaign.restore(fresh, queue, results) == ["x"]
    assert campaign.run_state(fresh, queue[0], results) == "raised"
    # once it reaches the raised budget it is done everywhere
    (results / "x" / "summary.json").write_text('{"real_steps": 4000}')
    assert campaign.run_state(fresh, queue[0], results) == "done"


TINY_PLANNING = [
    "method=ppo_mpc",
    "env=pendulum",
    "total_steps=620",  # ends with the planning phase: its last checkpoint holds the dataset
    "planning_updates=2",
    "ppo.frames_per_batch=160",
    "world_model.random_steps=300",
    "world_model.max_epochs=2",
    "world_model.hidden_sizes=[32,32]",
    "eval_episodes=0",
    "checkpoint.every_steps=400",
    "progress=false",
]


def test_a_planning_checkpoint_is_committed_compacted_and_rebuilt_on_a_fresh_machine(
    tmp_path, monkeypatch
):
    from torchrl_mbmf.runs.storage import verify_checkpoint

    root = tmp_path / "machine1" / "runs"
    run = root / "p"
    run.parent.mkdir(parents=True)
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), *TINY_PLANNING, f"run_dir={run}"],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    (run / "summary.json").unlink()  # as if the session ended before the run did
    checkpoint = campaign.latest_checkpoint(run)
    assert checkpoint.name == "checkpoint-000000000620"
    queue = _queue(tmp_path, "p train method=ppo_mpc\n")
    results = tmp_path / "results"
    monkeypatch.setattr(campaign, "SMALL_CHECKPOINT_BYTES", 0)  # the real ones are tens of MB
    assert campaign.snapshot(root, queue, results) == ["p"]
    copy = results / "p" / "checkpoints" / checkpoint.name
    assert sorted(p.name for p in (copy / "components" / "0000-dataset").iterdir()) == ["replay"]
    assert campaign._size(copy) < campaign._size(checkpoint)
    table = campaign.ledger_table(tmp_path / "elsewhere", queue, results)
    row = table.splitlines()[2].split(" | ")
    assert row[1] == "interrupted, resumes from its committed checkpoint" and row[4] == "620"
    # a fresh machine rebuilds the dataset by replaying the actions: every file as saved
    fresh = tmp_path / "machine2" / "runs"
    assert campaign.restore(fresh, queue, results) == ["p"]
    restored = fresh / "p" / "checkpoints" / checkpoint.name
    verify_checkpoint(restored)
    # the committed copy names no path of the first machine; the restored one names its own root
    committed = "".join(p.read_text() for p in copy.rglob("*.json"))
    assert str(root) not in committed and campaign.ROOT_MARK in committed
    restored_text = "".join(p.read_text() for p in restored.rglob("*.json"))
    assert str(fresh) in restored_text and campaign.ROOT_MARK not in restored_text
    assert "replayed" in (fresh / "campaign.log").read_text()
    # a committed replay that does not rebuild leaves no folder: the run starts again from 0
    actions = copy / "components" / "0000-dataset" / "replay" / "actions.bin"
    actions.write_bytes(actions.read_bytes()[:-4])
    third = tmp_path / "machine3" / "runs"
    assert campaign.restore(third, queue, results) == []
    assert not (third / "p").exists()
    lost = [e for e in campaign._events(third) if e["event"] == "lost"]
    assert lost[0]["real_steps"] == 620 and "did not rebuild" in lost[0]["why"]
    assert campaign.run_state(third, queue[0], results) == "queued"


def test_the_ledger_keeps_every_machines_events_and_each_runs_budget(tmp_path):
    queue = _queue(tmp_path)
    history = tmp_path / "events.jsonl"
    history.write_text(
        '{"event": "prior", "run": "a", "segments": 2, "wall_s": 600, "commits": ["abc1234"]}\n'
    )
    root = tmp_path / "machine2" / "runs"
    root.mkdir(parents=True)
    (root / "campaign.log").write_text(
        '{"time": "t0", "event": "start", "run": "a", "commit": "def5678", "restart": false}\n'
        '{"time": "t1", "event": "exit", "run": "a", "code": 0, "wall_s": 300.0}\n'
    )
    events = campaign.merge_events(root, history)
    assert [e["event"] for e in events] == ["prior", "start", "exit"]
    assert campaign.merge_events(root, history) == events  # nothing appended twice
    assert len(history.read_text().splitlines()) == 3
    rows = campaign.ledger_table(root, queue, None, events).splitlines()[2:]
    assert rows[0].endswith("| abc1234, def5678 | 3 | 15 |")  # 2 earlier + 1, 600 s + 300 s
    assert [campaign.budget(run) for run in queue] == [1_000_000, 200_000, 1_000_000]
    with history.open("a") as f:
        f.write('{"event": "lost", "run": "c", "real_steps": 69000, "checkpoint": 62000}\n')
    events = campaign.merge_events(root, history)
    row = campaign.ledger_table(root, queue, None, events).splitlines()[4]
    assert "| c | queued (lost at 69,000 with its machine, restarted from 0) | 0 |" in row
    # an event's text naming this machine's run root is committed with the root's mark instead
    with (root / "campaign.log").open("a") as f:
        why = f"{root}/.c.restoring/checkpoints/x does not match its SHA-256"
        f.write(json.dumps({"time": "t2", "event": "lost", "run": "c", "why": why}) + "\n")
    events = campaign.merge_events(root, history)
    assert str(root) not in history.read_text()
    assert (
        events[-1]["why"]
        == f"{campaign.ROOT_MARK}/.c.restoring/checkpoints/x does not match its SHA-256"
    )


def test_a_stop_time_just_passed_is_todays_and_one_long_past_is_tomorrows(tmp_path):
    now = dt.datetime(2026, 12, 3, 9, 46, tzinfo=dt.UTC)
    assert campaign.parse_stop_at("09:45", now) == now.replace(minute=45)  # nothing is started
    assert campaign.parse_stop_at("12:30", now) == now.replace(hour=12, minute=30)
    late = dt.datetime(2026, 12, 3, 23, 10, tzinfo=dt.UTC)  # a session past midnight
    assert campaign.parse_stop_at("01:30", late) == dt.datetime(2026, 12, 4, 1, 30, tzinfo=dt.UTC)
    # a worker without fallbacks, started after its stop time, takes nothing
    queue = _queue(tmp_path, "p train method=ppo_mpc seed=0\n")
    stop = campaign.parse_stop_at("09:45", now)  # in the past for any real clock now
    assert stop < dt.datetime.now(dt.UTC)
    assert campaign.claim_next(tmp_path / "runs", queue, stop, fallback=False) is None


def test_a_hybrid_starts_near_the_end_only_where_its_next_checkpoint_fits(tmp_path):
    queue = _queue(
        tmp_path,
        "far train method=sac_mbpo total_steps=200000 seed=1\n"
        "near train method=sac_mbpo total_steps=200000 seed=2\n",
    )
    root, results = tmp_path / "runs", tmp_path / "results"
    # far's latest checkpoint here is at 163,850 (the next at 184,320); near's committed copy
    # holds one at 100,000 (the next at 102,400)
    (root / "far" / "checkpoints" / "checkpoint-000000163850").mkdir(parents=True)
    (results / "near" / "checkpoints" / "checkpoint-000000100000").mkdir(parents=True)
    assert campaign.latest_checkpoint_step(root, queue[0], results) == 163_850
    assert campaign.latest_checkpoint_step(root, queue[1], results) == 100_000
    assert campaign.latest_checkpoint_step(root, queue[1]) == 0
    far = campaign.at_risk_seconds(queue[0], checkpoint_step=163_850) / 60
    near = campaign.at_risk_seconds(queue[1], checkpoint_step=100_000) / 60
    assert far == pytest.approx(2 + 20_470 * 0.150 / 60)
    assert near == pytest.approx(2 + 2_400 * 0.150 / 60)
    soon = dt.datetime.now(dt.UTC) + dt.timedelta(minutes=30)
    assert campaign.claim_next(root, queue, soon, results=results, fallback=False).name == "near"
    (root / ".claims" / "near").unlink()
    assert campaign.claim_next(root, queue[:1], soon, results=results, fallback=False) is None
    later = dt.datetime.now(dt.UTC) + dt.timedelta(hours=1)
    assert campaign.claim_next(root, queue, later, results=results, fallback=False).name == "far"
    # the run's own checkpoint period: a line's override counts
    short = campaign.QueuedRun("s", "train", ("method=sac_mbpo", "checkpoint.every_steps=1000"))
    assert campaign.at_risk_seconds(short, checkpoint_step=5_000) / 60 == pytest.approx(2.0 + 2.5)
