"""Torch threads of a run, alone and beside another busy process: which default runs fastest.

    .venv/bin/python benchmarks/threads.py            # ppo_mpc, 2,000 random + 3 updates
    .venv/bin/python benchmarks/threads.py --quick    # 1,000 random + 1 update

Each measurement is a whole `recipes/train.py` process (the README's main job, PPO-MPC on
HalfCheetah-v5 with the thesis settings, at a small budget) with `threads=1` or `threads=2`,
run alone or while a second process of the same job (one thread) competes for the cores.
Alternates the thread counts; prints real steps/s of the training loop (from the run's summary:
the planning phase, refits and updates included) and writes benchmarks/results/threads.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, write

ROOT = Path(__file__).resolve().parents[1]


def _command(run_dir: Path, threads: int, random_steps: int, updates: int) -> list[str]:
    total = random_steps + updates * 2048
    return [
        sys.executable,
        str(ROOT / "recipes" / "train.py"),
        "method=ppo_mpc",
        f"threads={threads}",
        f"world_model.random_steps={random_steps}",
        f"planning_updates={updates}",
        f"total_steps={total}",
        "progress=false",
        f"eval_every={10 * total}",
        f"checkpoint.every_steps={10 * total}",
        f"run_dir={run_dir}",
    ]


def _env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    return env


def _run(threads: int, busy: bool, random_steps: int, updates: int, tmp: Path) -> float:
    run_dir = tmp / f"t{threads}_{'busy' if busy else 'alone'}_{len(list(tmp.iterdir()))}"
    other = None
    if busy:
        other_dir = tmp / f"competitor_{len(list(tmp.iterdir()))}"
        # the competitor runs the same job for longer, so it outlives the measured one
        other = subprocess.Popen(
            _command(other_dir, 1, random_steps, 3 * updates + 2),
            env=_env(1),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            cwd=tmp,
        )
    try:
        subprocess.run(
            _command(run_dir, threads, random_steps, updates),
            env=_env(threads),
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            cwd=tmp,
        )
    finally:
        if other is not None:
            other.kill()
            other.wait()
    summary = json.loads((run_dir / "summary.json").read_text())
    return summary["real_steps"] / summary["seconds"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    random_steps, updates = (1000, 1) if args.quick else (2000, 3)
    results: dict[tuple[int, bool], list[float]] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for _ in range(args.repeats):
            for busy in (False, True):
                for threads in (1, 2):  # alternating
                    rate = _run(threads, busy, random_steps, updates, tmp)
                    results.setdefault((threads, busy), []).append(rate)
    rows = [
        {
            "threads": threads,
            "machine": "shared with a 1-thread run" if busy else "alone",
            "real steps/s (each run)": ", ".join(f"{r:.0f}" for r in rates),
            "mean": sum(rates) / len(rates),
        }
        for (threads, busy), rates in sorted(results.items(), key=lambda kv: (kv[0][1], kv[0][0]))
    ]
    print_table(rows)
    path = write(
        "threads",
        rows,
        {"job": "ppo_mpc", "random_steps": random_steps, "planning_updates": updates},
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
