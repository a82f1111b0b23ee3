"""Runs a queue of long training runs, one at a time per worker, resuming what was interrupted.

    python scripts/campaign.py --root ../runs/campaign --queue results/campaign/queue.txt \
        --results results/thesis/runs --stop-at 22:45 &     # one worker per core
    python scripts/campaign.py --root ../runs/campaign --queue results/campaign/queue.txt --status

Each queue line is ``<run name> <recipe> <overrides...>`` (``#`` starts a comment); the recipe is
``train`` (``recipes/train.py``, which resumes from the run folder's latest checkpoint) or
``sb3_reference`` (``recipes/sb3_reference.py``, which cannot resume: an interrupted SB3 run is
started again from scratch, and only when the time left before ``--stop-at`` covers its expected
length). A worker takes the first run that has no ``summary.json`` and no live claim and whose
part a fresh machine could not continue fits before ``--stop-at`` (:func:`claim_next`), claims it
(``<root>/.claims/<name>``, holding the worker's pid; a claim of a dead process is stale), runs
it with one torch thread in ``<root>/<name>``, and when it finishes copies its small files
(config, commit, machine, logs, summary, exported policy, train log, resume log) to
``--results/<name>``, with the root's parent folder cut from the paths they mention, so that the
copy can be committed. Every start, finish and failure is appended to ``<root>/campaign.log``.
``--snapshot`` (at a session's end) copies unfinished runs the same way, with their latest
checkpoint: as it is where it is small (PPO, and PPO-MPC once it fine-tunes), otherwise
compacted (:func:`~torchrl_mbmf.runs.dataset_replay.compact_checkpoint`, a few MB): its
real-transition dataset and SAC replay replaced by the actions that made them, ``sac_mbpo``'s
model replay by the record of its rollout rounds; a worker on a machine that lacks such a
run's folder restores it from that copy (replaying the actions and re-running the rounds to
rebuild them bit for bit) and resumes it. A run whose
committed copy holds a summary is done on any machine. ``--ledger`` appends the machine's events
to the committed ``events.jsonl`` beside the queue and writes the run table from all of them.
"""

from __future__ import annotations

import argparse
import datetime as dt
import fcntl
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPES = {"train": "recipes/train.py", "sb3_reference": "recipes/sb3_reference.py"}
#: Files and folders of a finished run that are small enough to commit.
SMALL_FILES = (
    "config.yaml",
    "git_commit.txt",
    "machine.json",
    "summary.json",
    "policy.pt",
    "policy.json",
    "resume_log.json",
    "logs",
    "train.log",
    "sb3_reference.log",
)
#: Largest checkpoint committed as it is with a partial run (PPO's are about 0.6 MB; a
#: model-based one holds its dataset and a SAC one its replay buffer, tens of MB).
SMALL_CHECKPOINT_BYTES = 5 * 2**20
#: Largest checkpoint committed compacted: its dataset and SAC replay replaced by the actions
#: that made them, sac_mbpo's model replay by its rollout rounds' record (MPC: about 3.7 MB of
#: networks and optimisers plus 24 bytes a real step, 14 MB at the end of the planning phase;
#: HalfCheetah SAC, measured: 5.2 MB at 5e4 real steps, 7.1 MB at 1e5).
COMPACT_CHECKPOINT_BYTES = 20 * 2**20
#: Methods whose checkpoints :func:`snapshot` commits compacted from the first one on (their
#: dataset and SAC replay as the actions that made them, sac_mbpo's model replay as its rollout
#: rounds' record; HalfCheetah SAC 7.1 MB at 1e5 real steps, sac_mbpo about 15.5 MB): a fresh
#: machine continues them from their last checkpoint, so nothing but the steps since it is at
#: risk. SAC-MPC is not listed: its compact size is unmeasured.
COMPACTED = ("mpc", "ppo_mpc", "sac", "sac_mbpo")
#: Minutes (one core of the busy 2-core machine; the campaign's runs so far, see LEDGER.md) a
#: run spends before its checkpoints can be committed, so that a fresh machine can continue
#: it: the whole run for SB3 (no resume) and SAC-MPC (replay buffer), none for PPO, nor for
#: the :data:`COMPACTED` methods. SB3 SAC: 17.2 ms per gradient step alone on a core (a
#: 16,000-step run, 11,000 gradient steps, on 2026-12-02), so about 57 min for 2e5 steps, with
#: a margin. (A whole sac run: about 70 min for 2e5; sac_mbpo with its hybrid_mbpo preset:
#: about 2.8-3.0 h projected for 1e5 steps, results/hybrid/mbpo_timing.md.)
AT_RISK_MIN = {"sb3_ppo": 35, "sb3_sac": 70, "ppo": 0, "sac_mpc": 100}
#: The budgets (real steps) those minutes are for: the thesis' (1e6 for PPO, 2e5 for SAC); a
#: run of another budget is expected to take proportionally as long.
AT_RISK_STEPS = {
    "sb3_ppo": 1_000_000,
    "sb3_sac": 200_000,
    "sac_mpc": 200_000,
}
#: Real steps between two checkpoints (``configs/train.yaml``'s ``checkpoint.every_steps``; a
#: queue line's override wins). A run checkpoints at the first collection end at or past each
#: multiple of it, and at its end.
CHECKPOINT_EVERY = 20_480
#: Milliseconds per real step, on the slowest machine measured, of the :data:`COMPACTED`
#: methods whose way to their next checkpoint takes long enough to matter: ``sac_mbpo`` with
#: the ``hybrid_mbpo`` preset ran at 53-61 ms on AMD EPYC machines with AVX-512, 118-125 ms on
#: an Intel Xeon and 137-138 ms on an AMD EPYC with AVX2 (``results/hybrid/final.md``'s
#: per-process table), so 150 with a margin; its restore from a committed copy (re-running the
#: actions and model-replay rounds) takes 1-1.5 min more, :data:`RESTORE_MIN`. The others
#: reach a checkpoint within minutes (SAC: about 27 min for 2e5 steps).
CHECKPOINT_MS_PER_STEP = {"sac_mbpo": 150.0}
RESTORE_MIN = 2.0
#: Minutes a worker has on a fresh machine: a 180-minute session less the set-up (the virtual
#: environment, about 3 min) and the closing snapshot and commit (about 8 min), with a margin. A
#: run whose at-risk part is longer can finish only across sessions that keep one machine.
FRESH_SESSION_MIN = 165


@dataclass(frozen=True)
class QueuedRun:
    """One line of the queue.

    Args:
        name: the run folder's name (equal to the recipe's ``run_name``: checked after the run).
        recipe: ``train`` or ``sb3_reference``.
        overrides: the recipe's Hydra overrides.
    """

    name: str
    recipe: str
    overrides: tuple[str, ...]

    @property
    def resumable(self) -> bool:
        """Whether an interrupted run continues from a checkpoint (``train``) or restarts."""
        return self.recipe == "train"


def read_queue(path: Path) -> list[QueuedRun]:
    r"""Parses a queue file.

    Args:
        path: the queue file.

    Raises:
        ValueError: a line names an unknown recipe, lacks one, or a name repeats.

    Examples:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "q.txt"
        >>> _ = p.write_text("# a comment\nrun_a train method=ppo seed=0\n")
        >>> read_queue(p)[0].overrides
        ('method=ppo', 'seed=0')
    """
    runs: list[QueuedRun] = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        words = shlex.split(line, comments=True)
        if not words:
            continue
        if len(words) < 2 or words[1] not in RECIPES:
            raise ValueError(
                f"{path}:{number}: {line!r}: expected '<run name> <recipe> <overrides...>' "
                f"with a recipe in {sorted(RECIPES)}"
            )
        if any(r.name == words[0] for r in runs):
            raise ValueError(f"{path}:{number}: run {words[0]!r} is queued twice")
        runs.append(QueuedRun(words[0], words[1], tuple(words[2:])))
    return runs


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def claim_owner(root: Path, name: str) -> int | None:
    """The pid of the live process that claimed a run, or ``None``.

    Args:
        root: the campaign's run root.
        name: the run's name.

    Examples:
        >>> import tempfile, pathlib
        >>> claim_owner(pathlib.Path(tempfile.mkdtemp()), "run_a") is None
        True
    """
    path = root / ".claims" / name
    try:
        pid = int(path.read_text().split()[0])
    except (FileNotFoundError, ValueError, IndexError):
        return None
    return pid if _alive(pid) else None


def finished(folder: Path, run: QueuedRun) -> bool:
    """Whether ``folder`` holds the run finished at the budget its queue line names now.

    A ``train`` run that finished short of a ``total_steps`` raised on its line since (its
    ``summary.json`` counts fewer real steps) is not finished: it continues from its last
    checkpoint to the new budget.

    Args:
        folder: the run folder (on this machine or its committed copy).
        run: the queued run.

    Examples:
        >>> import tempfile, pathlib
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> _ = (d / "summary.json").write_text('{"real_steps": 100000}')
        >>> run = QueuedRun("r", "train", ("method=sac", "total_steps=200000"))
        >>> finished(d, run), finished(d, QueuedRun("r", "train", ("method=sac",)))
        (False, True)
    """
    path = folder / "summary.json"
    if not path.exists():
        return False
    overrides = dict(o.split("=", 1) for o in run.overrides if "=" in o)
    if not run.resumable or "total_steps" not in overrides:
        return True
    steps = json.loads(path.read_text()).get("real_steps")
    return steps is None or int(steps) >= int(overrides["total_steps"])


def run_state(root: Path, run: QueuedRun, results: Path | None = None) -> str:
    """``done``, ``running`` (a live claim), ``raised``, ``interrupted`` or ``queued``.

    A run is also ``done`` when its committed copy in ``results`` holds a summary: on a fresh
    machine, whose run root is empty, a finished run is not run again. A run is ``raised`` when
    it finished here short of a budget raised on its queue line since (see :func:`finished`),
    ``interrupted`` when it has a folder and no summary.

    Args:
        root: the campaign's run root.
        run: the queued run.
        results: where finished runs' committed copies are (``None``: only ``root`` counts).
    """
    folder = root / run.name
    if finished(folder, run):
        return "done"
    if results is not None and finished(results / run.name, run):
        return "done"
    if claim_owner(root, run.name) is not None:
        return "running"
    if (folder / "summary.json").exists():
        return "raised"
    if (folder / "logs").exists():
        return "interrupted"
    return "queued"


def _log(root: Path, **event: object) -> None:
    event = {"time": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), **event}
    with (root / "campaign.log").open("a") as f:
        f.write(json.dumps(event) + "\n")


def _seconds_left(stop_at: dt.datetime | None) -> float:
    if stop_at is None:
        return float("inf")
    return (stop_at - dt.datetime.now(dt.UTC)).total_seconds()


def at_risk_seconds(run: QueuedRun, done_steps: int = 0, checkpoint_step: int = 0) -> float:
    """Expected wall time until a run's checkpoints can be committed (a fresh machine resumes).

    For SAC-MPC and SB3 the rest of the run (SB3 runs restart, so ``done_steps`` does not
    count); for PPO nothing, nor for the :data:`COMPACTED` methods (MPC, PPO-MPC, SAC,
    ``sac_mbpo``), whose checkpoints :func:`snapshot` commits compacted, except the way from
    their latest checkpoint to the next one (or to the run's end) where it is long enough to
    matter (:data:`CHECKPOINT_MS_PER_STEP`: ``sac_mbpo``), with the restore before it: a run
    stopped before it would redo those steps.

    Args:
        run: the queued run.
        done_steps: the real steps it has already run on this machine.
        checkpoint_step: the real step of its latest checkpoint, here or in its committed copy
            (0: none).

    Examples:
        >>> run = QueuedRun("r", "train", ("method=sac_mpc", "total_steps=200000"))
        >>> at_risk_seconds(run) / 60, at_risk_seconds(run, done_steps=150_000) / 60
        (100.0, 25.0)
        >>> hybrid = QueuedRun("r", "train", ("method=sac_mbpo", "total_steps=200000"))
        >>> at_risk_seconds(hybrid) / 60  # 0 to 20,480 at 150 ms a step, and the restore
        53.2
        >>> at_risk_seconds(hybrid, checkpoint_step=100_000) / 60  # to the next at 102,400
        8.0
        >>> at_risk_seconds(QueuedRun("r", "train", ("method=sac", "total_steps=100000")))
        0.0
    """
    overrides = dict(o.split("=", 1) for o in run.overrides if "=" in o)
    method = str(overrides.get("method", "ppo_mpc"))
    key = method if run.resumable else f"sb3_{method}"
    scale = budget(run) / AT_RISK_STEPS[key] if key in AT_RISK_STEPS else 1.0
    if not run.resumable:
        return 60.0 * AT_RISK_MIN.get(key, 120) * scale
    if method in COMPACTED:
        if method not in CHECKPOINT_MS_PER_STEP:
            return 0.0
        every = int(overrides.get("checkpoint.every_steps", CHECKPOINT_EVERY))
        upcoming = min((checkpoint_step // every + 1) * every, budget(run))
        steps = max(0, upcoming - checkpoint_step)
        return 60.0 * RESTORE_MIN + CHECKPOINT_MS_PER_STEP[method] * steps / 1000.0
    minutes, risky_steps = AT_RISK_MIN.get(method, 180) * scale, budget(run)
    left = max(0.0, 1.0 - done_steps / risky_steps) if risky_steps else 0.0
    return 60.0 * minutes * left


def latest_checkpoint_step(root: Path, run: QueuedRun, results: Path | None = None) -> int:
    """The real step of a run's latest checkpoint on this machine or in its committed copy.

    Args:
        root: the campaign's run root.
        run: the queued run.
        results: where the committed copies are (``None``: only ``root`` counts).

    Examples:
        >>> import tempfile, pathlib
        >>> root = pathlib.Path(tempfile.mkdtemp())
        >>> (root / "r" / "checkpoints" / "checkpoint-000000163850").mkdir(parents=True)
        >>> latest_checkpoint_step(root, QueuedRun("r", "train", ())), latest_checkpoint_step(
        ...     root, QueuedRun("s", "train", ())
        ... )
        (163850, 0)
    """
    folders = [root / run.name, *([results / run.name] if results is not None else [])]
    found = [latest_checkpoint(folder) for folder in folders]
    return max((int(c.name.removeprefix("checkpoint-")) for c in found if c), default=0)


def claim_next(
    root: Path,
    queue: list[QueuedRun],
    stop_at: dt.datetime | None,
    skip: frozenset[str] = frozenset(),
    results: Path | None = None,
    fallback: bool = True,
) -> QueuedRun | None:
    """Claims the next run that is neither done nor running (atomically, under a lock).

    The first whose :func:`at_risk_seconds` fit in the time before ``stop_at`` (so that a fresh
    machine can continue it, or it is done), runs interrupted on this machine before the
    others, then in queue order. When none fits, a resumable run that continues only if the
    next session has this machine: one interrupted here first, then one whose at-risk part is
    longer than a fresh machine's session (:data:`FRESH_SESSION_MIN`; it can finish in no other
    way), then the others in queue order (``fallback=False``: none of these; the worker
    stops). A non-resumable run that would not finish is never started.

    Args:
        root: the campaign's run root.
        queue: the queue, in priority order.
        stop_at: when the machine's session ends (``None``: never).
        skip: names to pass over (runs that failed in this worker).
        results: where finished runs' committed copies are (a run with a summary there is done).
        fallback: whether to take a run that continues only if the next session keeps this
            machine when none fits.
    """
    (root / ".claims").mkdir(parents=True, exist_ok=True)
    with (root / ".claims" / ".lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        open_runs = [
            run
            for run in queue
            if run.name not in skip and run_state(root, run, results) not in ("done", "running")
        ]
        left = _seconds_left(stop_at)
        # interrupted here (a raised budget puts nothing at risk: it keeps its queue place)
        here = [
            r
            for r in open_runs
            if r.resumable
            and (root / r.name / "logs").exists()
            and not (root / r.name / "summary.json").exists()
        ]
        first = sorted(open_runs, key=lambda r: r not in here)  # stable: else queue order
        risk = {
            r.name: at_risk_seconds(
                r, _last_step(root / r.name), latest_checkpoint_step(root, r, results)
            )
            for r in first
        }
        fits = [r for r in first if risk[r.name] <= left]
        fresh_fits = lambda r: at_risk_seconds(r) <= 60.0 * FRESH_SESSION_MIN  # noqa: E731
        kept_only = sorted(  # runs that only a kept machine would finish
            (r for r in first if r.resumable), key=lambda r: r not in here and fresh_fits(r)
        )
        kept_only = kept_only if fallback else []
        for run in (fits or kept_only)[:1]:
            (root / ".claims" / run.name).write_text(f"{os.getpid()}\n")
            return run
    return None


def copy_small_files(folder: Path, dest: Path, cut: str) -> None:
    """Copies a run's small files to ``dest`` (replacing an older copy), cutting ``cut`` from paths.

    Args:
        folder: the run folder.
        dest: where the copy goes (for example ``results/thesis/runs/<name>``).
        cut: a path prefix to remove from the text files (the run root's parent folder).
    """
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for name in SMALL_FILES:
        src = folder / name
        if src.is_dir():
            shutil.copytree(src, dest / name)
        elif src.exists():
            shutil.copy2(src, dest / name)
    # the world-model fit snapshots stay (about 1.1 MB each); records computed from them go
    for record in sorted((folder / "world_models").glob("*.json")):
        (dest / "world_models").mkdir(exist_ok=True)
        shutil.copy2(record, dest / "world_models" / record.name)
    for path in dest.rglob("*"):
        if path.is_file() and path.suffix in (".yaml", ".json", ".txt", ".log", ".csv"):
            text = path.read_text()
            if cut in text:
                path.write_text(text.replace(cut, ""))


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def latest_checkpoint(folder: Path) -> Path | None:
    """The newest ``checkpoints/checkpoint-*`` folder of a run (``None`` without one).

    Args:
        folder: the run folder.
    """
    found = sorted((folder / "checkpoints").glob("checkpoint-*"))
    return found[-1] if found else None


def snapshot(root: Path, queue: list[QueuedRun], results: Path) -> list[str]:
    """Copies every unfinished run's small files, and its latest checkpoint when small, to commit.

    The partial copy goes to ``results/<name>`` like a finished one; a checkpoint of at most
    :data:`SMALL_CHECKPOINT_BYTES` goes with it (``results/<name>/checkpoints/``), with the
    world-model fit snapshots so far (``world_models/fit-*``, about 1.1 MB each), so that
    :func:`restore` can continue the run on a machine that lacks its folder. PPO checkpoints are
    small, and so are a PPO-MPC run's once it fine-tunes (they leave the dataset out); those of
    its planning phase, of MPC and of SAC hold the dataset or the replay buffer and stay behind.
    A run whose committed copy already holds its latest checkpoint (restored from it, not yet
    past it) is left as committed.

    Args:
        root: the campaign's run root.
        queue: the queue.
        results: where finished runs' small files go.

    Returns:
        The names copied.
    """
    copied = []
    for run in queue:
        folder = root / run.name
        # done here or, finished on another machine, in its committed copy: never overwritten
        if run_state(root, run, results) == "done" or not (folder / "logs").exists():
            continue
        dest = results / run.name
        latest = latest_checkpoint(folder)
        if latest is not None and (dest / "checkpoints" / latest.name).is_dir():
            continue  # restored from its committed copy and not past it: kept as committed
        copy_small_files(folder, dest, str(root.parent) + os.sep)
        target = None if latest is None else dest / "checkpoints" / latest.name
        if latest is not None and _size(latest) <= SMALL_CHECKPOINT_BYTES:
            shutil.copytree(latest, target)
        elif latest is not None and (latest / "manifest.json").exists():
            _compact(folder, latest, target)
        if target is not None and target.exists():
            relocate_checkpoint(target, str(root), ROOT_MARK)  # no path of this machine
            # the world-model fits so far, which the finished run's fit evaluation reads
            for fit in sorted((folder / "world_models").glob("fit-*")):
                shutil.copytree(fit, dest / "world_models" / fit.name)
        copied.append(run.name)
    return copied


#: What a committed checkpoint's JSON files say in place of the machine's run root.
ROOT_MARK = "<run root>"


def relocate_checkpoint(checkpoint: Path, old: str, new: str) -> None:
    """Replaces ``old`` by ``new`` in a checkpoint's JSON files and updates their integrity entries.

    The ``progress`` and ``logger`` components record the run folder's absolute path; the
    snapshot writes :data:`ROOT_MARK` there instead, and a restore writes its own run root.

    Args:
        checkpoint: the checkpoint folder.
        old: the text to replace.
        new: its replacement.
    """
    from torchrl_mbmf.runs.storage import reseal_files

    record_file = checkpoint / "integrity.json"
    if not record_file.exists():
        return
    listed = json.loads(record_file.read_text())["files"]
    changed = []
    for path in sorted(checkpoint.rglob("*.json")):
        if path == record_file or path.parent.name == "replay":
            continue
        text = path.read_text()
        if old not in text:
            continue
        path.write_text(text.replace(old, new))
        name = path.relative_to(checkpoint).as_posix()
        if name in listed:
            changed.append(name)
    if changed:
        reseal_files(checkpoint, changed)


def _run_env(folder: Path) -> tuple[object, int]:
    """A fresh copy of a run's real env (from its ``config.yaml``) and the run's seed."""
    from omegaconf import OmegaConf

    from torchrl_mbmf.trainers.build import make_train_env

    cfg = OmegaConf.load(folder / "config.yaml")
    return make_train_env(cfg, int(cfg.seed)), int(cfg.seed)


def run_rollouts(folder: Path) -> object | None:
    """Rollouts built like a ``sac_mbpo`` run's (from its ``config.yaml``), else ``None``.

    They re-run the rollout rounds of its model replay when its checkpoint is compacted or
    rebuilt (their parameters are loaded from the checkpoint's round record).

    Args:
        folder: the run folder.
    """
    import torch
    from omegaconf import OmegaConf

    from torchrl_mbmf.trainers.agents import make_agent
    from torchrl_mbmf.trainers.build import make_train_env
    from torchrl_mbmf.trainers.settings import TrainConfig
    from torchrl_mbmf.world_model.branched_rollouts import policy_as_planner

    cfg = OmegaConf.load(folder / "config.yaml")
    if cfg.get("method") != "sac_mbpo":
        return None
    config = TrainConfig.from_config(cfg)
    settings = config.settings
    env = make_train_env(cfg, settings.seed)
    device = torch.device("cpu")
    agent = make_agent(settings.family, env, config.agent, device)
    world = config.world_model.build(
        env=env, agent=agent, device=device, planner=policy_as_planner, seed=settings.seed
    )
    return config.mbpo.build(
        world_model=world.model,
        env=env,
        actor=agent.actor,
        keys=agent.loss.in_keys,
        termination_fn=world.termination,
        device=device,
    )


def _compact(folder: Path, checkpoint: Path, target: Path) -> bool:
    """Writes ``checkpoint`` compacted to ``target`` if it fits :data:`COMPACT_CHECKPOINT_BYTES`."""
    from torchrl_mbmf.runs.dataset_replay import compact_checkpoint

    try:
        env, seed = _run_env(folder)
        rollouts = run_rollouts(folder)
        compact_checkpoint(checkpoint, target, env, seed=seed, rollouts=rollouts)
    except Exception as err:  # a run that cannot be compacted is copied without a checkpoint
        shutil.rmtree(target, ignore_errors=True)
        print(f"{folder.name}: {checkpoint.name} not compacted: {err}", file=sys.stderr)
        return False
    if _size(target) > COMPACT_CHECKPOINT_BYTES:
        print(
            f"{folder.name}: {checkpoint.name} is {_size(target):,} bytes even compacted "
            f"(more than {COMPACT_CHECKPOINT_BYTES:,}): not committed",
            file=sys.stderr,
        )
        shutil.rmtree(target)
        return False
    return True


def restore(
    root: Path, queue: list[QueuedRun], results: Path, *, rerun_model_replay: bool = False
) -> list[str]:
    """Recreates the folders of unfinished runs whose committed copy holds a checkpoint.

    Only where ``root`` lacks the run's folder (a fresh machine): the committed small files and
    checkpoint are copied into ``root/<name>``, and the run resumes from that checkpoint (its
    logs are cut back to it on resume, as after any interruption). A checkpoint that does not
    rebuild bit for bit is lost (the run starts again from 0), except with
    ``rerun_model_replay``: where the only files that differ are ``sac_mbpo``'s model replay
    re-run from its rounds' record (another CPU can round a few imagined values differently),
    the re-run rows are accepted, their integrity entries rewritten and the event logged with
    the files; everything else must still match as saved.

    Args:
        root: the campaign's run root.
        queue: the queue.
        results: where the committed copies are.

    Keyword Args:
        rerun_model_replay: accept a model replay that re-runs differently on this machine.
            Defaults to ``False``.

    Returns:
        The names restored.
    """
    restored = []
    (root / ".claims").mkdir(parents=True, exist_ok=True)
    # under the claims' lock: no worker claims a folder while another is still copying it
    with (root / ".claims" / ".lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        for run in queue:
            copy = results / run.name
            if (root / run.name).exists() or finished(copy, run):
                continue
            if latest_checkpoint(copy) is None:
                continue
            staging = root / f".{run.name}.restoring"
            shutil.rmtree(staging, ignore_errors=True)
            shutil.copytree(copy, staging)
            checkpoint = latest_checkpoint(staging)
            relocate_checkpoint(checkpoint, ROOT_MARK, str(root))
            rerun: list[str] = []
            try:
                try:
                    replayed = _expand(staging, checkpoint)
                except Exception:
                    rerun = _rerun_model_replay(checkpoint) if rerun_model_replay else []
                    if not rerun:
                        raise
                    replayed = True
            except Exception as err:  # the run starts again from 0, as a lost one
                shutil.rmtree(staging)
                step = int(checkpoint.name.removeprefix("checkpoint-"))
                why = f"its committed checkpoint did not rebuild: {err}"
                _log(root, event="lost", run=run.name, real_steps=step, why=why)
                print(f"{run.name}: {why}", file=sys.stderr)
                continue
            staging.rename(root / run.name)  # whole, or not at all
            _log(
                root,
                event="restored",
                run=run.name,
                checkpoint=checkpoint.name,
                **({"replayed": True} if replayed else {}),
                **({"model_replay_rerun": rerun} if rerun else {}),
            )
            restored.append(run.name)
    return restored


def _rerun_model_replay(checkpoint: Path) -> list[str]:
    """Accepts a fully rebuilt checkpoint whose only changed files are its model replay's rows.

    Returns the files whose entries were rewritten; none (nothing written) where any other file
    differs, is missing or is not listed (a rebuild that stopped early leaves its records).
    """
    from torchrl_mbmf.runs.buffer_replay import replay_components
    from torchrl_mbmf.runs.storage import changed_files, reseal_files, verify_checkpoint

    folder = replay_components(checkpoint).get("model_replay")
    if folder is None:
        return []
    rows = (folder / "data").relative_to(checkpoint).as_posix() + "/"
    changed = changed_files(checkpoint)
    if not changed or not all(name.startswith(rows) for name in changed):
        return []
    reseal_files(checkpoint, changed)
    verify_checkpoint(checkpoint)
    return changed


def _expand(folder: Path, checkpoint: Path) -> bool:
    """Rebuilds a compacted checkpoint in place (``False``: it holds nothing to rebuild)."""
    if not (checkpoint / "manifest.json").exists():
        return False
    manifest = json.loads((checkpoint / "manifest.json").read_text())
    paths = [entry["path"] for entry in manifest.get("components", {}).values()]
    records = ("replay", "rebuild")  # the dataset's and the replay buffers' rebuild records
    if not any((checkpoint / path / name).is_dir() for path in paths for name in records):
        return False
    from torchrl_mbmf.runs.dataset_replay import expand_checkpoint

    env, _ = _run_env(folder)
    return expand_checkpoint(checkpoint, env, rollouts=run_rollouts(folder))


def run_one(root: Path, run: QueuedRun, results: Path | None, restart: bool) -> int:
    """Runs (or resumes) one queued run in ``root/<name>``; returns the recipe's exit code.

    Args:
        root: the campaign's run root.
        run: the run.
        results: where to copy its small files when it finishes (``None``: nowhere).
        restart: pass ``restart=true`` (an interrupted non-resumable run).
    """
    folder = root / run.name
    cmd = [
        sys.executable,
        str(ROOT / RECIPES[run.recipe]),
        *run.overrides,
        "threads=1",
        f"run_dir={folder}",
    ]
    if run.recipe == "train":
        cmd.append("progress=false")
    if restart:
        cmd.append("restart=true")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[var] = "1"
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    _log(root, event="start", run=run.name, commit=commit, restart=restart)
    start = time.time()
    with (root / f"{run.name}.out").open("a") as out:
        code = subprocess.call(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    _log(root, event="exit", run=run.name, code=code, wall_s=round(time.time() - start, 1))
    if code == 0 and (folder / "summary.json").exists() and (folder / "world_models").is_dir():
        # tables 8 and 9 at every refit, while the run's snapshots are on this machine
        evaluate = [sys.executable, str(ROOT / "recipes" / "evaluate_fits.py"), f"run_dir={folder}"]
        with (root / f"{run.name}.out").open("a") as out:
            fits = subprocess.call(evaluate, cwd=ROOT, env=env, stdout=out, stderr=out)
        _log(root, event="evaluate_fits", run=run.name, code=fits)
    if code == 0 and (folder / "summary.json").exists():
        config = (folder / "config.yaml").read_text()
        if f"run_name: {run.name}\n" not in config:
            _log(root, event="warning", run=run.name, what="config run_name differs from name")
        if results is not None:
            copy_small_files(folder, results / run.name, str(root.parent) + os.sep)
            _log(root, event="copied", run=run.name, to=str(results / run.name))
    return code


def _events(root: Path) -> list[dict]:
    path = root / "campaign.log"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def merge_events(root: Path, history: Path) -> list[dict]:
    """Appends this machine's campaign events that ``history`` lacks to it; returns them all.

    ``history`` (``events.jsonl`` beside the queue) is committed, so the starts, exits and wall
    times of runs that ran on an earlier machine outlive that machine's ``campaign.log``. A
    ``prior`` record carries what an earlier ledger table showed of a run whose machine's log
    was lost before this file existed: ``segments``, ``wall_s`` and ``commits``; a ``lost``
    record, the ``real_steps`` of a run that restarted from 0 when its machine was lost.

    Args:
        root: the campaign's run root (its ``campaign.log``).
        history: the committed event file (created when missing).
    """
    lines = history.read_text().splitlines() if history.exists() else []
    known = {line for line in lines if line.strip()}
    events = _events(root)
    for event in events:  # the committed file names no path of this machine
        if "to" in event:
            event["to"] = Path(event["to"]).name
        for key, value in event.items():
            if isinstance(value, str):
                event[key] = value.replace(str(root), ROOT_MARK)
    new = [json.dumps(event) for event in events if json.dumps(event) not in known]
    if new:
        history.parent.mkdir(parents=True, exist_ok=True)
        with history.open("a") as f:
            f.write("".join(line + "\n" for line in new))
    return [json.loads(line) for line in [*lines, *new] if line.strip()]


def _last_step(folder: Path) -> int:
    summary = folder / "summary.json"
    if summary.exists():
        return int(json.loads(summary.read_text())["real_steps"])
    path = folder / "logs" / "scalars" / "train" / "episode_return.csv"
    if not path.exists():
        return 0
    rows = [line.split(",")[0] for line in path.read_text().splitlines() if line.strip()]
    return int(float(rows[-1])) if rows else 0


def budget(run: QueuedRun) -> int:
    """A queued run's budget in real steps: its ``total_steps``, else its recipe's default.

    Args:
        run: the queued run.
    """
    overrides = dict(o.split("=", 1) for o in run.overrides if "=" in o)
    if "total_steps" in overrides:
        return int(overrides["total_steps"])
    if run.recipe == "sb3_reference" and overrides.get("method") == "sac":
        return 200_000  # recipes/sb3_reference.py: the thesis' SAC budget
    return 1_000_000


def ledger_table(
    root: Path, queue: list[QueuedRun], results: Path | None, events: list[dict] | None = None
) -> str:
    """The markdown table of every queued run: state, steps, budget, commits, segments, wall time.

    A run's folder is looked up in ``root`` and, where ``root`` lacks it, in ``results`` (the
    committed copy). Segments and wall time come from ``root/campaign.log`` (the worker's
    starts and exits; a run started by hand before the campaign log existed shows none).

    Args:
        root: the campaign's run root.
        queue: the queue.
        results: where the committed copies are (``None``: only ``root``).
        events: the campaign events (``None``: ``root/campaign.log``; see :func:`merge_events`).
    """
    events = _events(root) if events is None else events
    lines = [
        "| run | state | real steps | budget | checkpoint | commits | segments | wall (min) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in queue:
        folder = root / run.name
        finished_elsewhere = results is not None and finished(results / run.name, run)
        if results is not None and (not folder.exists() or finished_elsewhere):
            folder = results / run.name
        state = run_state(root, run) if (root / run.name).exists() else "queued"
        if finished_elsewhere:
            state = "done"
        if not (root / run.name).exists() and (folder / "logs").exists():
            # only the committed copy: done, or lost with the machine (restarts from 0)
            state = "done" if finished(folder, run) else "lost, restarts"
            if state != "done" and latest_checkpoint(folder) is not None:
                state = "interrupted, resumes from its committed checkpoint"
        mine = [e for e in events if e.get("run") == run.name]
        starts = [e for e in mine if e["event"] == "start"]
        prior = [e for e in mine if e["event"] == "prior"]
        commits = {e["commit"] for e in starts if e.get("commit")}
        commits |= {c for e in prior for c in e.get("commits", [])}
        if (folder / "git_commit.txt").exists():
            commits = commits or {(folder / "git_commit.txt").read_text().strip()[:7]}
        wall = sum(float(e.get("wall_s", 0)) for e in mine if e["event"] in ("exit", "prior"))
        segments = len(starts) + sum(int(e.get("segments", 0)) for e in prior)
        reruns: dict[int, int] = {}  # checkpoint step -> restores that re-ran its model replay
        for i, event in enumerate(mine):
            later = [e["event"] for e in mine[i + 1 :]]
            if event["event"] == "lost" and "restored" not in later:
                step = int(event["real_steps"])
                state += f" (lost at {step:,} with its machine, restarted from 0)"
            if event["event"] == "restored" and event.get("model_replay_rerun"):
                step = int(event["checkpoint"].removeprefix("checkpoint-"))
                reruns[step] = reruns.get(step, 0) + 1
        if reruns:
            at = " and ".join(
                f"{s:,}" + (f" ({n} times)" if n > 1 else "") for s, n in reruns.items()
            )
            state += f" (restored at {at} with its model replay re-run on another CPU)"
        latest = latest_checkpoint(folder)
        lines.append(
            f"| {run.name} | {state} | {_last_step(folder):,} | {budget(run):,} | "
            f"{latest.name.removeprefix('checkpoint-').lstrip('0') if latest else '-'} | "
            f"{', '.join(sorted(commits)) or '-'} | {segments} | {wall / 60:.0f} |"
        )
    return "\n".join(lines) + "\n"


def parse_stop_at(text: str, now: dt.datetime) -> dt.datetime:
    """The moment ``HH:MM`` (UTC) names: today's, or tomorrow's when today's passed long ago.

    A time that passed less than 12 hours ago is today's, so a worker started just after its
    session's stop time claims nothing; one that passed longer ago is tomorrow's (a session
    that runs past midnight).

    Args:
        text: ``HH:MM``.
        now: the current time (aware, UTC).

    Examples:
        >>> import datetime as dt
        >>> now = dt.datetime(2026, 12, 3, 23, 30, tzinfo=dt.UTC)
        >>> parse_stop_at("23:29", now).day, parse_stop_at("01:00", now).day
        (3, 4)
    """
    hour, minute = (int(x) for x in text.split(":"))
    stop_at = now.replace(hour=hour, minute=minute, second=0, microsecond=0)
    if stop_at < now - dt.timedelta(hours=12):
        stop_at += dt.timedelta(days=1)
    return stop_at


def main() -> None:
    """Command line: one worker, or ``--status``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="run folders (outside git)")
    parser.add_argument("--queue", type=Path, required=True, help="the queue file")
    parser.add_argument("--results", type=Path, help="copy finished runs' small files here")
    parser.add_argument(
        "--stop-at", help="HH:MM UTC when the session ends (the next one: today or tomorrow)"
    )
    parser.add_argument("--status", action="store_true", help="print each run's state")
    parser.add_argument(
        "--snapshot", action="store_true", help="copy unfinished runs to --results, then exit"
    )
    parser.add_argument("--ledger", type=Path, help="write the run table into this markdown file")
    parser.add_argument(
        "--rerun-model-replay",
        action="store_true",
        help="on restore, accept a sac_mbpo model replay that re-running its rounds on this "
        "machine does not give bit for bit (every other file must match; logged)",
    )
    parser.add_argument(
        "--no-fallback",
        action="store_true",
        help="when no run fits before --stop-at, stop instead of starting one that only a kept "
        "machine would finish",
    )
    args = parser.parse_args()
    root = args.root.resolve()
    root.mkdir(parents=True, exist_ok=True)
    queue = read_queue(args.queue)
    if args.status:
        for run in queue:
            print(f"{run_state(root, run, args.results):12s} {run.name}")
        return
    if args.ledger is not None:
        text = args.ledger.read_text() if args.ledger.exists() else ""
        begin, end = "<!-- campaign table -->", "<!-- end campaign table -->"
        events = merge_events(root, args.queue.parent / "events.jsonl")
        table = f"{begin}\n{ledger_table(root, queue, args.results, events)}{end}"
        if begin in text and end in text:
            text = text[: text.index(begin)] + table + text[text.index(end) + len(end) :]
        else:
            text = text + "\n" + table + "\n"
        args.ledger.write_text(text)
        return
    if args.snapshot:
        if args.results is None:
            raise SystemExit("--snapshot needs --results")
        print("\n".join(snapshot(root, queue, args.results)))
        return
    if args.results is not None:
        restore(root, queue, args.results, rerun_model_replay=args.rerun_model_replay)
    stop_at = parse_stop_at(args.stop_at, dt.datetime.now(dt.UTC)) if args.stop_at else None
    failed: set[str] = set()

    def next_run() -> QueuedRun | None:
        return claim_next(
            root, queue, stop_at, frozenset(failed), args.results, fallback=not args.no_fallback
        )

    while (run := next_run()) is not None:
        restart = not run.resumable and (root / run.name / "logs").exists()
        code = run_one(root, run, args.results, restart)
        (root / ".claims" / run.name).unlink(missing_ok=True)
        if code != 0:
            failed.add(run.name)
            if len(failed) >= 3:
                raise SystemExit("three runs failed: stopping this worker (see campaign.log)")


if __name__ == "__main__":
    main()
