"""A run killed with SIGKILL and resumed ends exactly like an uninterrupted run."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TRAIN = str(ROOT / "recipes" / "train.py")
# One torch thread per run: two OpenMP threads per process on a shared 2-vCPU machine slow the
# tiny networks down several times.
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
TINY = [
    "env=pendulum",
    "total_steps=1600",
    "ppo.frames_per_batch=160",
    "planning_updates=2",
    "world_model.random_steps=300",
    "world_model.max_epochs=2",
    "world_model.hidden_sizes=[32,32]",
    "world_model.refit_every=1",
    "sac.frames_per_batch=100",
    "sac.init_random_frames=200",
    "sac.batch_size=32",
    "sac.hidden_sizes=[32,32]",
    "sac.refit_every_steps=300",
    "eval_every=800",
    "checkpoint.every_steps=400",
    "progress=false",
]


def _run(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, TRAIN, *overrides, f"run_dir={run_dir}"],
        cwd=run_dir.parent,
        capture_output=True,
        text=True,
        timeout=600,
        env=ENV,
    )


def _kill_when(run_dir: Path, ready: Callable[[], bool], *overrides: str) -> None:
    proc = subprocess.Popen(
        [sys.executable, TRAIN, *overrides, f"run_dir={run_dir}"],
        cwd=run_dir.parent,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=ENV,
    )
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None and not ready():
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (run_dir / "summary.json").exists(), "the run finished before it could be killed"


#: A Hopper run whose planner ends candidates by a learned termination head (saved with the
#: checkpoint at 400 steps, in the planning phase, and refitted after the resume).
LEARNED_TERMINATION = [
    *(o for o in TINY if not o.startswith("env=")),
    "env=hopper",
    "world_model.learn_termination=true",
]


#: sac_mbpo on the tiny budget: a rollout round every batch and a model replay that wraps
#: around before the checkpoint at 400 steps (its FIFO position is restored too).
MBPO = [
    "world_model.ensemble_size=2",
    "mbpo.rollout_every=100",
    "mbpo.refit_every=300",
    "mbpo.rollout_batch_size=64",
    "mbpo.rollout_horizon=3",
    "mbpo.model_replay_size=150",
    "sac.utd_ratio=0.5",
]


@pytest.mark.parametrize(
    "method",
    [
        "ppo",
        "ppo_mpc",
        "sac",
        "sac_mbpo",
        pytest.param("sac_mpc", marks=pytest.mark.slow),
        pytest.param("ppo_mpc_learned_termination", marks=pytest.mark.slow),
    ],
)
def test_sigkill_then_resume_matches_uninterrupted_run(tmp_path, method):
    cfg = [f"method={method}", *TINY, *(MBPO if method == "sac_mbpo" else [])]
    if method == "ppo_mpc_learned_termination":
        cfg = ["method=ppo_mpc", *LEARNED_TERMINATION]
    straight = tmp_path / "straight"
    proc = _run(straight, *cfg)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = tmp_path / "resumed"
    _kill_when(run, lambda: any((run / "checkpoints").glob("checkpoint-*")), *cfg)
    done = _run(run, *cfg)
    assert done.returncode == 0, done.stderr[-3000:]
    resumed = json.loads((run / "summary.json").read_text())
    reference = json.loads((straight / "summary.json").read_text())
    assert resumed["resumed"] is True and reference["resumed"] is False
    for key in ("real_steps", "random_steps", "updates", "episodes", "params_sha256"):
        assert resumed[key] == reference[key], key
    assert resumed["final_eval_return"] == pytest.approx(reference["final_eval_return"])
    # at most keep_last (2) checkpoints are kept
    assert len(list((run / "checkpoints").glob("checkpoint-*"))) <= 2


def test_incompatible_checkpoint_names_the_key(tmp_path):
    run = tmp_path / "run"
    cfg = ["method=ppo", *TINY, "total_steps=400", "checkpoint.every_steps=160"]
    assert _run(run, *cfg).returncode == 0
    for override, key in (
        ("method=sac", "method"),
        ("ppo.hidden_sizes=[16,16]", "ppo.hidden_sizes"),
        ("seed=3", "seed"),
    ):
        proc = _run(run, *cfg, override)
        assert proc.returncode != 0
        assert f"was written with {key}=" in proc.stderr, proc.stderr[-2000:]


def test_changed_training_settings_are_refused_and_safe_ones_recorded(tmp_path):
    run = tmp_path / "run"
    cfg = ["method=ppo", *TINY, "total_steps=400", "checkpoint.every_steps=160"]
    assert _run(run, *cfg).returncode == 0
    written = (run / "config.yaml").read_text()
    proc = _run(run, *cfg, "ppo.lr=0.01", "ppo.clip_epsilon=0.5")
    assert proc.returncode != 0
    # every changed setting is named with both values
    assert "was written with ppo.lr=0.0003, this run has ppo.lr=0.01" in proc.stderr, proc.stderr[
        -2000:
    ]
    assert "was written with ppo.clip_epsilon=0.2, this run has ppo.clip_epsilon=0.5" in (
        proc.stderr
    )
    # config.yaml still shows what ran
    assert (run / "config.yaml").read_text() == written
    # settings that do not change training are accepted, recorded, and shown in config.yaml
    proc = _run(run, *cfg, "total_steps=800", "eval_every=300", "checkpoint.keep_last=3")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "summary.json").read_text())["real_steps"] == 800
    entries = json.loads((run / "resume_log.json").read_text())
    changes = entries[-1]["allowed_changes"]
    assert changes["total_steps"] == {"checkpoint": 400, "now": 800}
    assert changes["eval_every"] == {"checkpoint": 800, "now": 300}
    assert changes["checkpoint.keep_last"] == {"checkpoint": 2, "now": 3}
    assert "total_steps: 800" in (run / "config.yaml").read_text()
    # the finished run's summary it continued from is kept in the resume log (the first run
    # stopped at the batch boundary past 400)
    assert entries[-1]["previous_summary"]["real_steps"] == 480
    # and the commit and machine of the process before (both processes ran here)
    assert entries[-1]["previous_machine"] == json.loads((run / "machine.json").read_text())
    assert entries[-1]["previous_commit"] == (run / "git_commit.txt").read_text().strip()


def test_a_finished_run_continued_is_unfinished_until_its_new_summary(tmp_path):
    run = tmp_path / "run"
    cfg = ["method=ppo", *TINY, "total_steps=400", "checkpoint.every_steps=160"]
    assert _run(run, *cfg).returncode == 0
    first = json.loads((run / "summary.json").read_text())
    raised = [*cfg, "total_steps=1600"]
    continuing = (run / "resume_log.json").exists
    _kill_when(run, lambda: continuing() and not (run / "summary.json").exists(), *raised)
    # killed while continuing: no summary claims the run finished; the old one is in the log
    (entry,) = json.loads((run / "resume_log.json").read_text())
    assert entry["previous_summary"] == first
    proc = _run(run, *raised)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "summary.json").read_text())["real_steps"] == 1600


# Checkpoints at 460 (the first after the 300 random steps and one planning batch), 620 (where
# the planning phase ends: train/switch_to_model_free is logged at 620 *after* that save), 940,
# 1260, 1580 and 1600.
LOG_CFG = ["method=ppo_mpc", *TINY, "checkpoint.every_steps=310"]


def _csv_logs(run_dir: Path) -> dict[str, list[str]]:
    root = run_dir / "logs" / "scalars"
    out = {}
    for path in sorted(root.rglob("*.csv")):
        name = str(path.relative_to(root))
        rows = path.read_text().splitlines()
        if name.startswith("time/"):  # wall-clock values: compare the steps only
            rows = [row.split(",")[0] for row in rows]
        out[name] = rows
    return out


@pytest.fixture(scope="module")
def straight_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("straight") / "run"
    proc = _run(run, *LOG_CFG)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run


@pytest.fixture(scope="module")
def straight_logs(straight_run):
    return _csv_logs(straight_run)


def _rows_after(run_dir: Path, step: int) -> bool:
    path = run_dir / "logs" / "scalars" / "loss" / "loss_objective.csv"
    if not path.exists():
        return False
    return any(int(row.split(",")[0]) > step for row in path.read_text().split())


def _checkpoint(run_dir: Path, step: int) -> Path:
    return run_dir / "checkpoints" / f"checkpoint-{step:012d}"


@pytest.mark.parametrize(
    "kill", ["before_first_checkpoint", "after_checkpoint", "during_checkpoint_write"]
)
def test_logs_after_sigkill_and_resume_equal_uninterrupted_run(tmp_path, straight_logs, kill):
    run = tmp_path / "run"
    if kill == "before_first_checkpoint":
        val_loss = run / "logs" / "scalars" / "model" / "val_loss.csv"
        _kill_when(run, val_loss.exists, *LOG_CFG)
        assert not any((run / "checkpoints").glob("checkpoint-*")), "killed too late"
    else:
        # rows beyond the checkpoint at 620, including the one logged at 620 after its save
        _kill_when(run, lambda: _checkpoint(run, 620).exists() and _rows_after(run, 620), *LOG_CFG)
        if kill == "during_checkpoint_write":
            # as if the kill came while the checkpoint at 620 was written: it never appeared
            shutil.rmtree(_checkpoint(run, 620))
            assert _checkpoint(run, 460).exists()
    assert _csv_logs(run) != straight_logs  # the killed attempt left rows to cut
    _resume_and_compare_logs(run, straight_logs)


def _resume_and_compare_logs(run: Path, straight_logs: dict[str, list[str]]) -> None:
    done = _run(run, *LOG_CFG)
    assert done.returncode == 0, done.stderr[-3000:]
    resumed = _csv_logs(run)
    assert sorted(resumed) == sorted(straight_logs)
    for name, rows in straight_logs.items():
        assert resumed[name] == rows, name


def _manifest_components(checkpoint: Path) -> set[str]:
    return set(json.loads((checkpoint / "manifest.json").read_text())["components"])


def test_model_free_checkpoints_leave_the_dataset_out_and_resume_alone(
    tmp_path, straight_run, straight_logs
):
    """A fine-tuning checkpoint is all a fresh machine needs to continue the run exactly."""
    run = tmp_path / "run"
    _kill_when(run, lambda: _checkpoint(run, 940).exists() and _rows_after(run, 940), *LOG_CFG)
    planning, model_free = _checkpoint(run, 620), _checkpoint(run, 940)
    assert "dataset" in _manifest_components(planning)
    assert "dataset" not in _manifest_components(model_free)
    assert {"world_model", "model_optim", "loss", "optim", "progress", "rng"} <= (
        _manifest_components(model_free)
    )
    # what a fresh machine has: the small files and the newest (small) checkpoint only
    shutil.rmtree(planning)
    assert [p.name for p in (run / "checkpoints").glob("checkpoint-*")] == [model_free.name]
    _resume_and_compare_logs(run, straight_logs)
    entries = json.loads((run / "resume_log.json").read_text())
    assert entries[-1]["checkpoint"] == model_free.name
    # every weight, the world model's (unused after the switch) included, as uninterrupted
    resumed = json.loads((run / "summary.json").read_text())
    reference = json.loads((straight_run / "summary.json").read_text())
    assert resumed["params_sha256"] == reference["params_sha256"]


def test_a_planning_checkpoint_without_its_dataset_is_refused(tmp_path):
    run = tmp_path / "run"
    _kill_when(run, lambda: _checkpoint(run, 620).exists(), *LOG_CFG)
    manifest = _checkpoint(run, 620) / "manifest.json"
    # a checkpoint whose manifest lost the dataset: its integrity record no longer matches, so
    # write one for it (as a buggy writer would) and check the resume names what is missing
    record = json.loads(manifest.read_text())
    del record["components"]["dataset"]
    manifest.write_text(json.dumps(record))
    from torchrl_mbmf.runs.storage import write_integrity_record

    (_checkpoint(run, 620) / "integrity.json").unlink()
    write_integrity_record(_checkpoint(run, 620))
    shutil.rmtree(_checkpoint(run, 460), ignore_errors=True)
    proc = _run(run, *LOG_CFG)
    assert proc.returncode != 0
    assert "holds no dataset, which a run at its progress (phase 'planning') needs" in proc.stderr


def test_a_planning_checkpoint_compacted_to_its_replay_resumes_exactly(
    tmp_path, straight_run, straight_logs
):
    """What a fresh machine gets from a committed planning checkpoint (its dataset replaced by
    the actions that made it, as ``scripts/campaign.py --snapshot`` commits it) continues the
    run exactly: the dataset is rebuilt bit for bit by replaying the actions."""
    from omegaconf import OmegaConf

    from torchrl_mbmf.runs.dataset_replay import compact_checkpoint, expand_checkpoint
    from torchrl_mbmf.runs.storage import CheckpointIntegrityError, verify_checkpoint
    from torchrl_mbmf.trainers.build import make_train_env

    run = tmp_path / "run"
    _kill_when(run, lambda: _checkpoint(run, 620).exists() and _rows_after(run, 620), *LOG_CFG)
    planning = _checkpoint(run, 620)
    assert "dataset" in _manifest_components(planning)
    cfg = OmegaConf.load(run / "config.yaml")
    fresh = tmp_path / "fresh" / "run"
    shutil.copytree(run, fresh, ignore=shutil.ignore_patterns("checkpoints"))
    compacted = _checkpoint(fresh, 620)
    compact_checkpoint(planning, compacted, make_train_env(cfg, int(cfg.seed)), seed=int(cfg.seed))
    dataset = compacted / "components" / "0000-dataset"
    assert sorted(p.name for p in dataset.iterdir()) == ["replay"]
    with pytest.raises(CheckpointIntegrityError, match=r"integrity\.json"):
        verify_checkpoint(compacted)  # not resumable until rebuilt
    assert expand_checkpoint(compacted, make_train_env(cfg, int(cfg.seed))) is True
    verify_checkpoint(compacted)  # every file as the run saved it
    _resume_and_compare_logs(fresh, straight_logs)
    resumed = json.loads((fresh / "summary.json").read_text())
    reference = json.loads((straight_run / "summary.json").read_text())
    assert resumed["params_sha256"] == reference["params_sha256"]


def _signal_after_first_checkpoint(run_dir: Path, sig: signal.Signals, *overrides: str):
    proc = subprocess.Popen(
        [sys.executable, TRAIN, *overrides, f"run_dir={run_dir}"],
        cwd=run_dir.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    deadline = time.time() + 300
    while not list((run_dir / "checkpoints").glob("checkpoint-*")):
        assert proc.poll() is None and time.time() < deadline, "no checkpoint was written"
        time.sleep(0.05)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=300)
    return proc.returncode, out + err


SIGNAL_CFG = ["method=ppo", *TINY, "checkpoint.every_steps=320"]


@pytest.fixture(scope="module")
def straight_signal_run(tmp_path_factory):
    straight = tmp_path_factory.mktemp("signal") / "straight"
    assert _run(straight, *SIGNAL_CFG).returncode == 0
    return json.loads((straight / "summary.json").read_text())


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_saves_and_the_rerun_ends_like_an_uninterrupted_run(
    tmp_path, sig, straight_signal_run
):
    cfg = SIGNAL_CFG
    run = tmp_path / "stopped"
    code, output = _signal_after_first_checkpoint(run, sig, *cfg)
    assert code == 0, output[-3000:]
    assert f"stopped by {sig.name} after the checkpoint at" in output
    assert "Traceback" not in output
    assert not (run / "summary.json").exists()
    done = _run(run, *cfg)
    assert done.returncode == 0, done.stderr[-3000:]
    resumed = json.loads((run / "summary.json").read_text())
    reference = straight_signal_run
    assert resumed["resumed"] is True
    for key in ("real_steps", "updates", "episodes", "params_sha256"):
        assert resumed[key] == reference[key], key


def test_a_run_folder_is_the_runs(tmp_path):
    cfg = ["method=ppo", *TINY, "total_steps=400", "checkpoint.every_steps=160"]
    # a folder with the user's own files is refused, and nothing in it is touched
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("precious")
    proc = _run(mine, *cfg)
    assert proc.returncode != 0 and "files that are not a training run's: ['thesis.tex']" in (
        proc.stderr
    )
    assert sorted(p.name for p in mine.iterdir() if p.name not in (".hydra", "train.log")) == [
        "thesis.tex"
    ]
    # a finished run is refused (its checkpoints removed too), restart=true moves it aside
    run = tmp_path / "run"
    assert _run(run, *cfg).returncode == 0
    summary = (run / "summary.json").read_text()
    proc = _run(run, *cfg)
    steps = json.loads(summary)["real_steps"]
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (
        f"holds this config's finished run (summary.json: {steps} real steps)"
        in proc.stdout + proc.stderr
    )
    assert (run / "summary.json").read_text() == summary
    shutil.rmtree(run / "checkpoints")
    rows = _csv_logs(run)
    for override in ("seed=1", "total_steps=800"):  # another config, a larger budget
        proc = _run(run, *cfg, override)
        assert proc.returncode != 0 and "restart=true" in proc.stderr, override
    proc = _run(run, *cfg)  # the same config: nothing to train, nothing touched
    assert proc.returncode == 0 and "nothing to train" in proc.stdout + proc.stderr
    assert _csv_logs(run) == rows and (run / "summary.json").read_text() == summary
    proc = _run(run, *cfg, "restart=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    (aside,) = run.glob("replaced-*")
    assert (aside / "summary.json").read_text() == summary
    assert _csv_logs(aside) == rows


def test_a_second_process_on_a_run_folder_is_refused(tmp_path):
    from torchrl_mbmf.runs.claim import RunFolderLock

    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; "
            "from torchrl_mbmf.runs.claim import RunFolderLock; "
            f"lock = RunFolderLock(Path({str(run)!r})).acquire(); print('locked', flush=True); "
            "time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        proc = _run(run, "method=ppo", *TINY, "total_steps=400")
        assert proc.returncode != 0
        assert f"is in use by process {holder.pid}" in proc.stderr, proc.stderr[-2000:]
    finally:
        holder.kill()
        holder.wait()
    # the dead holder's lock is taken over
    lock = RunFolderLock(run).acquire()
    assert lock.held
    lock.release()
