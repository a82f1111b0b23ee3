"""SAC's replay and sac_mbpo's model replay compacted to what rebuilds them, and resumed exactly.

A checkpoint compacted as ``scripts/campaign.py --snapshot`` commits it (the real transitions
kept as the actions that made them, the imagined ones as the record of their rollout rounds)
is rebuilt bit for bit on a fresh machine and continues the run like the uninterrupted one.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchrl_mbmf.runs.buffer_replay import REBUILD_DIR, replay_components
from torchrl_mbmf.runs.dataset_replay import (
    NotReplayableError,
    compact_checkpoint,
    expand_checkpoint,
)
from torchrl_mbmf.runs.storage import CheckpointIntegrityError, verify_checkpoint

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("campaign", ROOT / "scripts" / "campaign.py")
campaign = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("campaign", campaign)
_spec.loader.exec_module(campaign)

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
SAC = [
    "method=sac",
    "env=pendulum",
    "total_steps=600",
    "sac.frames_per_batch=100",
    "sac.init_random_frames=200",
    "sac.batch_size=32",
    "sac.hidden_sizes=[32,32]",
    "eval_every=300",
    "eval_episodes=1",
    "checkpoint.every_steps=300",
    "progress=false",
]
#: a rollout round every batch from 400 steps on; the model replay (150 rows, up to 80 a
#: round) has wrapped around by the checkpoint at 600 steps; the rounds at 400 and 500 use the
#: model fitted at 300, the one at 600 the model refitted at 500, which the checkpoint holds
MBPO = [
    *(o for o in SAC if not o.startswith("method=") and not o.startswith("total_steps=")),
    "method=sac_mbpo",
    "total_steps=900",
    "world_model.random_steps=300",
    "world_model.max_epochs=2",
    "world_model.hidden_sizes=[32,32]",
    "world_model.ensemble_size=2",
    "mbpo.rollout_every=100",
    "mbpo.refit_every=200",
    "mbpo.rollout_batch_size=40",
    "mbpo.rollout_horizon=2",
    "mbpo.model_replay_size=150",
    "sac.utd_ratio=0.5",
]


def _run(run_dir: Path, cfg: list[str]) -> dict:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), *cfg, f"run_dir={run_dir}"],
        cwd=run_dir.parent,
        capture_output=True,
        text=True,
        timeout=600,
        env=ENV,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((run_dir / "summary.json").read_text())


def _fresh_copy(run: Path, fresh: Path) -> None:
    """The run folder a fresh machine gets: no checkpoint, no summary (it resumes)."""
    shutil.copytree(run, fresh, ignore=shutil.ignore_patterns("checkpoints", "summary.json"))


def _compacted(tmp_path: Path, cfg: list[str], step: int) -> tuple[Path, Path, dict, Path]:
    straight = tmp_path / "straight"
    summary = _run(straight, cfg)
    fresh = tmp_path / "fresh" / "run"
    _fresh_copy(straight, fresh)
    name = f"checkpoint-{step:012d}"
    compacted = fresh / "checkpoints" / name
    env, seed = campaign._run_env(straight)
    rollouts = campaign.run_rollouts(straight)
    compact_checkpoint(
        straight / "checkpoints" / name, compacted, env, seed=seed, rollouts=rollouts
    )
    return straight, fresh, summary, compacted


def _no_unpickling(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("a checkpoint load unpickled")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(torch, "load", refuse)


@pytest.mark.parametrize("method", ["sac", "sac_mbpo"])
def test_compacted_replays_rebuild_bit_for_bit_and_resume_exactly(tmp_path, monkeypatch, method):
    cfg, step = (SAC, 300) if method == "sac" else (MBPO, 600)
    _, fresh, reference, compacted = _compacted(tmp_path, cfg, step)
    names = sorted(replay_components(compacted))
    assert names == (["replay"] if method == "sac" else ["model_replay", "replay"])
    for name in names:
        folder = replay_components(compacted)[name]
        assert sorted(p.name for p in folder.iterdir()) == [REBUILD_DIR, "replay.json"]
    # sac_mbpo's SAC replay shares the dataset's actions, its rounds the current model's
    # parameters (stored once)
    actions = replay_components(compacted)["replay"] / REBUILD_DIR / "actions"
    assert actions.is_dir() == (method == "sac")
    rounds = list((compacted / "components").glob("*-model_rounds"))
    assert [sorted(p.name for p in r.iterdir()) for r in rounds] == (
        [] if method == "sac" else [[REBUILD_DIR]]
    )
    with pytest.raises(CheckpointIntegrityError, match=r"integrity\.json"):
        verify_checkpoint(compacted)  # not resumable until rebuilt
    env, _ = campaign._run_env(fresh)
    if method == "sac_mbpo":  # a changed round record is refused before anything is rebuilt
        tampered = tmp_path / "tampered"
        shutil.copytree(compacted, tampered)
        rng = next((tampered / "components").glob("*-model_rounds")) / REBUILD_DIR / "t00000.bin"
        rng.write_bytes(bytes([rng.read_bytes()[0] ^ 1]) + rng.read_bytes()[1:])
        with pytest.raises(CheckpointIntegrityError, match=r"model_rounds.*SHA-256"):
            expand_checkpoint(tampered, env, rollouts=campaign.run_rollouts(fresh))
        assert not (replay_components(tampered)["model_replay"] / "data").exists()
    with monkeypatch.context() as patch:
        _no_unpickling(patch)
        assert expand_checkpoint(compacted, env, rollouts=campaign.run_rollouts(fresh))
    verify_checkpoint(compacted)  # every file as the run saved it
    resumed = _run(fresh, cfg)
    assert resumed["resumed"] is True
    for key in ("real_steps", "updates", "episodes", "params_sha256"):
        assert resumed[key] == reference[key], key


def test_a_tampered_compact_replay_is_refused(tmp_path):
    _, fresh, _, compacted = _compacted(tmp_path, SAC, 300)
    record = replay_components(compacted)["replay"] / REBUILD_DIR / "actions"
    meta = json.loads((record / "replay.json").read_text())
    actions = bytearray((record / "actions.bin").read_bytes())
    actions[40] ^= 1  # another action, its own checksum updated: only the rebuild tells
    (record / "actions.bin").write_bytes(bytes(actions))
    meta["actions_sha256"] = hashlib.sha256(bytes(actions)).hexdigest()
    (record / "replay.json").write_text(json.dumps(meta))
    env, _ = campaign._run_env(fresh)
    with pytest.raises(CheckpointIntegrityError, match=r"data.*SHA-256"):
        expand_checkpoint(compacted, env)


def test_a_wrapped_sac_replay_is_not_compacted(tmp_path):
    run = tmp_path / "run"
    _run(run, [*SAC, "sac.replay_size=250", "sac.batch_size=16"])
    env, seed = campaign._run_env(run)
    with pytest.raises(NotReplayableError, match="wrapped around"):
        compact_checkpoint(
            run / "checkpoints" / "checkpoint-000000000300", tmp_path / "c", env, seed=seed
        )
    assert not (tmp_path / "c").exists()


def test_a_model_replay_rerun_differently_is_accepted_only_when_asked(tmp_path):
    """Another CPU may round a few imagined values differently: the campaign's opt-in."""
    _, fresh, _, compacted = _compacted(tmp_path, MBPO, 600)
    queue_file = tmp_path / "queue.txt"
    queue_file.write_text(f"{fresh.name} train method=sac_mbpo\n")
    queue = campaign.read_queue(queue_file)
    rows = replay_components(compacted)["model_replay"].relative_to(compacted) / "data"
    record_file = compacted / "integrity.json"
    record = json.loads(record_file.read_text())
    saved = dict(record["files"])
    # what the run's machine saved, as another CPU would not re-run it
    changed = f"{rows.as_posix()}/action.memmap"
    record["files"][changed] = {**saved[changed], "sha256": "0" * 64}
    record_file.write_text(json.dumps(record))
    strict = tmp_path / "strict"
    assert campaign.restore(strict, queue, fresh.parent) == []
    assert [e["event"] for e in campaign._events(strict)] == ["lost"]
    accepting = tmp_path / "accepting"
    assert campaign.restore(accepting, queue, fresh.parent, rerun_model_replay=True) == ["run"]
    event = campaign._events(accepting)[-1]
    assert event["event"] == "restored" and event["model_replay_rerun"] == [changed]
    restored = accepting / "run" / "checkpoints" / compacted.name
    verify_checkpoint(restored)
    entries = json.loads((restored / "integrity.json").read_text())["files"]
    assert {k: v for k, v in entries.items() if k != changed} == {
        k: v for k, v in saved.items() if k != changed
    }
    table = campaign.ledger_table(
        accepting, queue, fresh.parent, [*campaign._events(strict), event]
    )
    assert "re-run on another CPU" in table and "restarted from 0" not in table
    # restored that way on two machines: said once, with the count
    twice = campaign.ledger_table(accepting, queue, fresh.parent, [event, event])
    assert twice.count("re-run on another CPU") == 1 and "(2 times)" in twice
    # any other file that differs still loses the checkpoint
    dataset = next(k for k in saved if "-dataset/" in k and k.endswith(".memmap"))
    record["files"][dataset] = {**saved[dataset], "sha256": "0" * 64}
    record_file.write_text(json.dumps(record))
    other = tmp_path / "other"
    assert campaign.restore(other, queue, fresh.parent, rerun_model_replay=True) == []
    assert [e["event"] for e in campaign._events(other)] == ["lost"]
