"""Real steps/s of Stable-Baselines3 and ours on HalfCheetah-v5, side by side, one process per run.

    pip install -e ".[bench]"
    python benchmarks/peers.py                        # ppo, sac (vs SB3), ppo_mpc, sac_mpc (ours)
    python benchmarks/peers.py --quick                # tiny budgets, one repetition: a smoke test
    python benchmarks/peers.py --methods ppo,sac --repeats 3 --threads 2
    python benchmarks/peers.py --methods ppo --ours-override collector=stock
    python benchmarks/peers.py --methods ppo --repeats 4 --ours-at c0ad5c2
                                                      # also ours at a commit, alternated

Every run is a fresh process that trains from scratch for the same real step budget, seed and
thread count (torch threads and OMP/MKL/OpenBLAS env vars): ours is ``recipes/train.py`` (no
checkpoint inside the budget and, like SB3, no evaluation: ``eval_episodes=0`` unless
``--eval-episodes``), timed by its ``summary.json`` ``seconds``; SB3 is
``PPO``/``SAC`` ``.learn(total_timesteps=N)`` on ``gym.make("HalfCheetah-v5")``, timed around
``.learn``. Per repetition ours runs first, then SB3 (ours, SB3, ours, SB3, ...). SB3's PPO takes
our ``configs/algo/ppo.yaml`` (thesis table 6, 64x64 ReLU nets as ``make_ppo_actor_critic``
builds, one env, no VecNormalize since ours does not normalise; SB3 samples a Gaussian and
clips, ours a TanhNormal); SB3's SAC takes our
``configs/algo/sac.yaml``, which equals SB3's defaults (256x256 ReLU, batch 256, one gradient
step per env step, buffer 1e6, auto entropy from 1.0). ``ppo_mpc`` and ``sac_mpc`` have no SB3
counterpart: ours only. For our runs the table also splits a real step's time as the run's
``summary.json`` ``time_breakdown`` records it (``n/a`` where the run has none). With
``--ours-at COMMIT``, ours at that commit (a temporary git worktree, its package first on the
path) runs too, after ours in each repetition: the summary adds its rate and ``ours/ours@``.

Writes benchmarks/results/peers.json (peers_quick.json with --quick; --out overrides) and
prints tables.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, machine, print_table

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "HalfCheetah-v5"
METHODS = ("ppo", "sac", "ppo_mpc", "sac_mpc")
#: Methods with an SB3 counterpart, and which SB3 algorithm it is.
SB3_ALGO = {"ppo": "ppo", "sac": "sac"}
BREAKDOWN_KEYS = ("env_s", "act_s", "update_s", "refit_s", "other_s")
RESULT_TAG = "PEERS_RESULT "
PACKAGES = (
    "torch",
    "torchrl",
    "tensordict",
    "gymnasium",
    "mujoco",
    "numpy",
    "stable-baselines3",
)

# Real step budgets: (full, --quick). A run of ours stops at the first batch boundary at or past
# total_steps: SAC collects sac.frames_per_batch-step batches (50 by default; the budgets are
# multiples of it), the model-based methods their random steps first (ppo_mpc: random + updates x
# 2048, sac_mpc: random + k x 50).
BUDGETS = {
    "ppo_steps": (20480, 2048),
    "sac_steps": (8000, 1000),
    "sac_random": (3000, 500),
    "ppo_mpc_steps": (20240, 3048),
    "ppo_mpc_random": (10000, 1000),
    "ppo_mpc_updates": (5, 1),
    "sac_mpc_steps": (8000, 1500),
    "sac_mpc_random": (3000, 500),
}


# --------------------------------------------------------------------------- SB3 worker
def sb3_worker(spec: dict[str, Any]) -> None:
    """Trains one SB3 agent (in its own process) and prints its timing as a tagged JSON line."""
    import gymnasium as gym
    import torch

    from torchrl_mbmf.baselines.sb3 import make_sb3_model, sb3_grad_steps

    torch.set_num_threads(int(spec["threads"]))
    config = dict(spec["config"])
    if spec["algo"] == "sac":  # the benchmark's own random-step budget
        config["init_random_frames"] = int(spec["random_steps"])
    model = make_sb3_model(spec["algo"], gym.make(ENV_ID), config, seed=int(spec["seed"]))
    start = time.perf_counter()
    model.learn(total_timesteps=int(spec["steps"]))
    seconds = time.perf_counter() - start
    result = {
        "steps": int(model.num_timesteps),
        "seconds": seconds,
        "grad_steps": sb3_grad_steps(model),
        "torch_threads": torch.get_num_threads(),
    }
    print(RESULT_TAG + json.dumps(result), flush=True)


# ------------------------------------------------------------------------------ runners
def _subprocess_env(threads: int, root: Path = ROOT) -> dict[str, str]:
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[var] = str(threads)
    # The checkout's package wins over any other installed copy.
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), env.get("PYTHONPATH")]))
    return env


def _check(proc: subprocess.CompletedProcess, what: str) -> None:
    if proc.returncode != 0:
        raise RuntimeError(
            f"{what} failed with exit code {proc.returncode}:\n{proc.stderr[-4000:]}"
        )


def _algo_config(name: str) -> dict[str, Any]:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(OmegaConf.load(ROOT / "configs" / "algo" / f"{name}.yaml"))


def our_overrides(method: str, b: dict[str, int], quick: bool) -> tuple[int, list[str]]:
    """The real step budget and the method's ``recipes/train.py`` overrides."""
    if method == "ppo":
        return b["ppo_steps"], []
    if method == "sac":
        return b["sac_steps"], [f"sac.init_random_frames={b['sac_random']}"]
    fast_fit = ["world_model.max_epochs=5"] if quick else []
    if method == "ppo_mpc":
        return b["ppo_mpc_steps"], [
            f"world_model.random_steps={b['ppo_mpc_random']}",
            f"planning_updates={b['ppo_mpc_updates']}",
            *fast_fit,
        ]
    if method == "sac_mpc":
        return b["sac_mpc_steps"], [
            f"world_model.random_steps={b['sac_mpc_random']}",
            f"sac.init_random_frames={b['sac_mpc_random']}",
            *fast_fit,
        ]
    raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")


def run_ours(
    method: str,
    steps: int,
    extra: list[str],
    seed: int,
    threads: int,
    eval_episodes: int,
    root: Path = ROOT,
) -> dict[str, Any]:
    """One ``recipes/train.py`` process (of the checkout ``root``); its summary's seconds,
    steps and time breakdown."""
    from omegaconf import OmegaConf

    past = 100 * steps  # no periodic evaluation or checkpoint inside the budget
    with tempfile.TemporaryDirectory(prefix=f"peers_{method}_") as tmp:
        run_dir = Path(tmp) / "run"
        cmd = [
            sys.executable,
            str(root / "recipes" / "train.py"),
            f"method={method}",
            f"seed={seed}",
            f"total_steps={steps}",
            *extra,
            f"run_dir={run_dir}",
            "progress=false",
            f"threads={threads}",
            "logger=csv",
            f"eval_every={past}",
            f"eval_episodes={eval_episodes}",
            f"checkpoint.every_steps={past}",
        ]
        start = time.perf_counter()
        proc = subprocess.run(
            cmd, cwd=tmp, env=_subprocess_env(threads, root), capture_output=True, text=True
        )
        process_s = time.perf_counter() - start
        _check(proc, f"ours {method}")
        summary = json.loads((run_dir / "summary.json").read_text())
        cfg = OmegaConf.load(run_dir / "config.yaml")
        torch_threads = json.loads((run_dir / "machine.json").read_text()).get("torch_threads")
    if method in ("ppo", "ppo_mpc"):
        c = cfg.ppo
        grad_steps = (
            summary["updates"]
            * int(c.epochs)
            * math.ceil(int(c.frames_per_batch) / int(c.minibatch_size))
        )
    else:
        c = cfg.sac
        grad_steps = summary["updates"] * max(1, int(int(c.frames_per_batch) * float(c.utd_ratio)))
    breakdown = summary.get("time_breakdown")
    random_steps = int(summary["random_steps"])  # the world model's random data
    if method == "sac":  # random-policy batches until init_random_frames
        frames = int(c.frames_per_batch)
        random_steps = min(
            int(summary["real_steps"]), -(-int(c.init_random_frames) // frames) * frames
        )
    return {
        "steps": int(summary["real_steps"]),
        "random_steps": random_steps,
        "seconds": float(summary["seconds"]),
        "grad_steps": int(grad_steps),
        "torch_threads": torch_threads,
        "process_s": process_s,
        "breakdown": breakdown if isinstance(breakdown, dict) else None,
        "params_sha256": summary.get("params_sha256"),
    }


def checkout_at(commit: str) -> Path:
    """A temporary git worktree of ``commit`` (remove it with :func:`remove_checkout`)."""
    path = Path(tempfile.mkdtemp(prefix="peers_at_")) / commit
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), commit],
        check=True,
        capture_output=True,
    )
    return path


def remove_checkout(path: Path) -> None:
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)], capture_output=True
    )
    shutil.rmtree(path.parent, ignore_errors=True)


def run_sb3(algo: str, steps: int, random_steps: int, seed: int, threads: int) -> dict[str, Any]:
    """One SB3 process (this script's ``--sb3-worker`` mode); its ``.learn`` seconds."""
    spec = {
        "algo": algo,
        "steps": steps,
        "random_steps": random_steps,
        "seed": seed,
        "threads": threads,
        "config": _algo_config(algo),
    }
    cmd = [sys.executable, str(Path(__file__).resolve()), "--sb3-worker", json.dumps(spec)]
    start = time.perf_counter()
    proc = subprocess.run(cmd, env=_subprocess_env(threads), capture_output=True, text=True)
    process_s = time.perf_counter() - start
    _check(proc, f"SB3 {algo}")
    lines = [line for line in proc.stdout.splitlines() if line.startswith(RESULT_TAG)]
    if not lines:
        raise RuntimeError(f"SB3 {algo} printed no result line:\n{proc.stdout[-2000:]}")
    out = json.loads(lines[-1][len(RESULT_TAG) :])
    return {
        **out,
        "random_steps": random_steps if algo == "sac" else 0,
        "process_s": process_s,
        "breakdown": None,
    }


# ---------------------------------------------------------------------------- reporting
def _versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def sb3_available() -> bool:
    try:
        importlib.metadata.version("stable-baselines3")
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


def breakdown_row(run: dict[str, Any]) -> dict[str, object]:
    """ms per real step and % of the breakdown's total, per part, or ``n/a``."""
    row: dict[str, object] = {"method": run["method"], "rep": run["rep"]}
    parts = run["breakdown"]
    if not parts:
        row.update({key[:-2]: "n/a" for key in BREAKDOWN_KEYS})
        return row
    total = sum(float(v) for v in parts.values())
    keys = list(BREAKDOWN_KEYS) + [k for k in parts if k not in BREAKDOWN_KEYS]
    for key in keys:
        sec = float(parts.get(key, 0.0))
        pct = 100 * sec / total if total > 0 else 0.0
        row[key.removesuffix("_s")] = f"{1e3 * sec / run['steps']:.3f} ms ({pct:.0f}%)"
    row["total"] = f"{1e3 * total / run['steps']:.3f} ms"
    return row


def summarise(
    runs: list[dict[str, Any]], methods: list[str], at: str | None = None
) -> list[dict[str, object]]:
    rows = []
    for method in methods:
        rates = {
            impl: [r["steps_per_s"] for r in runs if r["method"] == method and r["impl"] == impl]
            for impl in ("ours", "sb3", f"ours@{at}")
        }
        ours = statistics.mean(rates["ours"]) if rates["ours"] else None
        sb3 = statistics.mean(rates["sb3"]) if rates["sb3"] else None
        row = {
            "method": method,
            "ours steps/s": ours,
            "sb3 steps/s": sb3,
            "ours/sb3": ours / sb3 if ours and sb3 else None,
            "ours runs": len(rates["ours"]),
            "sb3 runs": len(rates["sb3"]),
        }
        if at is not None:
            old = rates[f"ours@{at}"]
            row[f"ours@{at} steps/s"] = statistics.mean(old) if old else None
            # per repetition (run back to back), then the median: drift hits both alike
            pairs = [a / b for a, b in zip(rates["ours"], old, strict=False) if a and b]
            row["ours/ours@"] = statistics.median(pairs) if pairs else None
        rows.append(row)
    return rows


def _write(path: Path, extra: dict[str, Any], runs: list[dict[str, Any]], summary: list) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": machine(), **extra, "summary": summary, "runs": runs}
    path.write_text(json.dumps(doc, indent=2) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sb3-worker", metavar="SPEC", help=argparse.SUPPRESS)
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    parser.add_argument(
        "--repeats", type=int, help="repetitions per side (default 2, 1 with --quick)"
    )
    parser.add_argument("--threads", type=int, default=1, help="threads per run (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every run (default 0)")
    parser.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test")
    parser.add_argument("--out", type=Path, help="JSON path (default results/peers.json)")
    parser.add_argument(
        "--ours-override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra recipes/train.py override for every run of ours (repeatable), for example "
        "collector=stock",
    )
    parser.add_argument(
        "--ours-at", metavar="COMMIT", help="also run ours at this commit (a git worktree)"
    )
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=0,
        help="our runs' eval_episodes (default 0: ours evaluates after its first batch and at "
        "the end, SB3's .learn never does)",
    )
    for key, (full, quick) in BUDGETS.items():
        parser.add_argument(
            "--" + key.replace("_", "-"),
            type=int,
            help=f"default {full} ({quick} with --quick)",
        )
    args = parser.parse_args()
    if args.sb3_worker is not None:
        sb3_worker(json.loads(args.sb3_worker))
        return

    methods = [m for m in args.methods.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        parser.error(f"--methods {args.methods!r}: expected a comma-separated subset of {METHODS}")
    if args.repeats is None:
        args.repeats = 1 if args.quick else 2
    for name in ("repeats", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.eval_episodes < 0:
        parser.error(f"--eval-episodes must be >= 0, got {args.eval_episodes}")
    budget = {
        key: int(BUDGETS[key][args.quick] if getattr(args, key) is None else getattr(args, key))
        for key in BUDGETS
    }
    with_sb3 = sb3_available()
    if not with_sb3 and any(m in SB3_ALGO for m in methods):
        print("stable-baselines3 is not installed (pip install -e '.[bench]'): ours only")
    out = args.out or RESULTS / ("peers_quick.json" if args.quick else "peers.json")
    versions = _versions()
    note = (
        f"{ENV_ID}, one env, {args.threads} thread(s) per process, seed {args.seed}, every run a "
        "fresh process; alternated ours, SB3 per repetition. steps/s = real env steps / training "
        f"wall time (ours: summary.json seconds with eval_episodes={args.eval_episodes} and the "
        "final checkpoint; SB3: .learn, which neither evaluates nor saves). SAC: "
        "ours takes one update per frame past init_random_frames after each batch of "
        "sac.frames_per_batch steps (50 by default), "
        "SB3 one after every env step past learning_starts: the same gradient step counts "
        "(grad_steps). Shared machines: compare ratios, not absolute rates."
    )
    extra = {
        "note": note,
        "quick": args.quick,
        "threads": args.threads,
        "repeats": args.repeats,
        "eval_episodes": args.eval_episodes,
        "ours_overrides": args.ours_override,
        "ours_at": args.ours_at,
        "seed": args.seed,
        "budgets": budget,
        "versions": versions,
    }
    runs: list[dict[str, Any]] = []
    at_root = checkout_at(args.ours_at) if args.ours_at else None
    try:
        _run_all(args, methods, budget, with_sb3, at_root, out, extra, runs, versions)
    finally:
        if at_root is not None:
            remove_checkout(at_root)
    summary = summarise(runs, methods, args.ours_at)
    _write(out, extra, runs, summary)
    _print_tables(runs, summary, note, out)


def _run_all(
    args: argparse.Namespace,
    methods: list[str],
    budget: dict[str, int],
    with_sb3: bool,
    at_root: Path | None,
    out: Path,
    extra: dict[str, Any],
    runs: list[dict[str, Any]],
    versions: dict[str, str | None],
) -> None:
    for method in methods:
        steps, overrides = our_overrides(method, budget, args.quick)
        overrides += args.ours_override
        for rep in range(args.repeats):
            impls = ["ours"] + ([f"ours@{args.ours_at}"] if at_root is not None else [])
            impls += ["sb3"] if with_sb3 and method in SB3_ALGO else []
            for impl in impls:
                if impl.startswith("ours"):
                    root = ROOT if impl == "ours" else at_root
                    res = run_ours(
                        method, steps, overrides, args.seed, args.threads, args.eval_episodes, root
                    )
                else:
                    random_steps = budget["sac_random"] if method == "sac" else 0
                    res = run_sb3(SB3_ALGO[method], steps, random_steps, args.seed, args.threads)
                run = {
                    "method": method,
                    "impl": impl,
                    "rep": rep,
                    "seed": args.seed,
                    **res,
                    "steps_per_s": res["steps"] / res["seconds"],
                    "threads": args.threads,
                    "versions": versions,
                    "cpu_count": os.cpu_count(),
                }
                runs.append(run)
                print(
                    f"{method:8s} {impl:4s} rep {rep}: {run['steps']} steps in "
                    f"{run['seconds']:.1f} s = {run['steps_per_s']:.1f} steps/s",
                    flush=True,
                )
                # partial results survive an interrupted benchmark
                _write(out, extra, runs, summarise(runs, methods, args.ours_at))


def _print_tables(
    runs: list[dict[str, Any]], summary: list[dict[str, object]], note: str, out: Path
) -> None:
    print()
    print_table(
        [
            {
                "method": r["method"],
                "impl": r["impl"],
                "rep": r["rep"],
                "steps": r["steps"],
                "random": r["random_steps"],
                "grad steps": r["grad_steps"],
                "seconds": r["seconds"],
                "steps/s": r["steps_per_s"],
            }
            for r in runs
        ]
    )
    print()
    print_table(summary)
    ours = [r for r in runs if r["impl"].startswith("ours")]
    if ours:
        print("\nWhere a real step's time goes (ours; ms per real step, % of the total):")
        print_table([{**breakdown_row(r), "impl": r["impl"]} for r in ours])
    print()
    print(note)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
