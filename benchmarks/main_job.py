"""The README's main job (PPO-MPC, thesis settings, HalfCheetah-v5): where its time goes.

    .venv/bin/python benchmarks/main_job.py             # 2 rounds of A/B short runs (~10 min)
    .venv/bin/python benchmarks/main_job.py --quick     # 1 round, fewer updates
    .venv/bin/python benchmarks/main_job.py --thesis-only
    .venv/bin/python benchmarks/main_job.py --units-from benchmarks/results/main_job_threads.json

Runs the default recipe (``recipes/train.py``, the thesis' settings) at a short budget: the
thesis' 10,000 random steps and first fit (200 epochs), ``--planning-updates`` PPO-MPC
batches, then ``--ppo-updates`` PPO-only batches. Each variant is a fresh process, the
variants alternate (A B A B): ``autograd fit`` is the run with the world-model fit's minibatch
loss through autograd (the loop before ``FusedMSEGradient``), ``fused fit`` the code as it
stands (the same numbers, bit for bit). ``--threads 2`` adds ``threads=2`` runs.

From each run's logs (the pace ``time/steps_per_s`` logged at every batch gives the wall time
at each batch; ``time/update_s`` the batch's update; ``time/model_fit_s`` each fit), per unit:
seconds per planning step (env + planner), per PPO-only step (env + policy), per update, and
microseconds per fitted transition-epoch (``model_fit_s / (epochs * training split)``, the
first fit's). These are extrapolated to the 1e6-step job with the thesis' schedule, read from
the committed whole run (``--run``, default the README job run whole and uninterrupted): its
random steps, switch step, update count and its fits' sizes and epochs (refits grow with the
data: 10k, 112k, 215k and 317k transitions). The same decomposition of the committed run
itself gives its real breakdown. Prints a table, writes ``benchmarks/results/main_job.json``.

The fit cost per transition-epoch is the first fit's (9,000 training transitions); the larger
refits run at about the same rate (``benchmarks/world_model.py`` measures 100k). On a shared
machine absolute times drift by 20% and more: compare the variants of one invocation.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, write

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "train.py"
DEFAULT_RUN = ROOT / "results/main_job/runs/HalfCheetah-v5__ppo_mpc__default__h10__seed0"
FRAMES = 2048  # the thesis' ppo.frames_per_batch
VAL_FRACTION = 0.1  # the thesis' world_model.val_fraction

# Runs the recipe with the world-model fit's minibatch loss through autograd (the fit loop
# before FusedMSEGradient): the "A" of the A/B.
_AUTOGRAD_CHILD = """
import runpy, sys
import torchrl_mbmf.world_model.fit as fit

class NoFusedStep:
    @staticmethod
    def for_net(net):
        return None

fit.FusedMSEGradient = NoFusedStep
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def _csv(path: Path) -> list[tuple[int, float]]:
    if not path.exists():
        return []
    with path.open() as f:
        return [(int(float(step)), float(value)) for step, value in csv.reader(f)]


def run_breakdown(run_dir: Path) -> dict[str, object]:
    """Per-phase seconds of a finished, uninterrupted run folder, from its logs and summary."""
    summary = json.loads((run_dir / "summary.json").read_text())
    scalars = run_dir / "logs" / "scalars"
    pace = _csv(scalars / "time" / "steps_per_s.csv")
    updates = dict(_csv(scalars / "time" / "update_s.csv"))
    fit_s = _csv(scalars / "time" / "model_fit_s.csv")
    epochs = dict(_csv(scalars / "model" / "epochs.csv"))
    switch = int(summary["switch_step"])
    random_steps = int(summary["random_steps"])
    fits = [
        {
            "transitions": n,
            "epochs": int(epochs[n]),
            "seconds": s,
            "us_per_transition_epoch": s / (epochs[n] * (n - round(n * VAL_FRACTION))) * 1e6,
        }
        for n, s in fit_s
    ]
    fit_at = {f["transitions"]: f["seconds"] for f in fits}
    elapsed = [(step, step / rate) for step, rate in pace]  # a fresh run's pace counts from 0
    phases: dict[str, dict[str, float]] = {
        p: {"steps": 0, "batches": 0, "collect_s": 0.0, "update_s": 0.0}
        for p in ("planning", "ppo")
    }
    for (prev_step, prev_t), (step, t) in itertools.pairwise(elapsed):
        phase = phases["planning" if step <= switch else "ppo"]
        # a refit runs in the batch's ``updated`` hooks, inside its logged update time
        refit = fit_at.get(step, 0.0) if step > random_steps else 0.0
        phase["steps"] += step - prev_step
        phase["batches"] += 1
        phase["update_s"] += updates.get(step, 0.0) - refit
        phase["collect_s"] += t - prev_t - updates.get(step, 0.0)
    for phase in phases.values():
        phase["s_per_step"] = phase["collect_s"] / max(1, phase["steps"])
        phase["s_per_update"] = phase["update_s"] / max(1, phase["batches"])
    return {
        "run": run_dir.name,
        "seconds": summary["seconds"],
        "real_steps": summary["real_steps"],
        "random_steps": random_steps,
        "switch_step": switch,
        "updates": summary["updates"],
        "time_breakdown": summary.get("time_breakdown"),
        "fits": fits,
        "phases": phases,
        # the random phase, the first fit and the first batch, before the first logged pace
        "first_batch_s": elapsed[0][1] if elapsed else None,
        "first_batch_step": elapsed[0][0] if elapsed else None,
    }


def extrapolate(unit: dict[str, object], schedule: dict[str, object]) -> dict[str, float]:
    """Seconds of the whole job: ``unit``'s per-step/update/fit costs on ``schedule``."""
    phases = unit["phases"]
    first = unit["fits"][0]
    per_fit = first["us_per_transition_epoch"] * 1e-6
    fit_s = sum(
        f["epochs"] * (f["transitions"] - round(f["transitions"] * VAL_FRACTION)) * per_fit
        for f in schedule["fits"]
    )
    # the short run's first logged batch holds its random phase, first fit and a planning batch
    random_s = unit["first_batch_s"] - first["seconds"]
    random_s -= FRAMES * phases["planning"]["s_per_step"] + phases["planning"]["s_per_update"]
    planning_steps = schedule["switch_step"] - schedule["random_steps"]
    ppo_steps = schedule["real_steps"] - schedule["switch_step"]
    planning_updates = planning_steps // FRAMES
    out = {
        "random phase": random_s * schedule["random_steps"] / unit["random_steps"],
        "planning: env + planner": planning_steps * phases["planning"]["s_per_step"],
        "planning: PPO updates": planning_updates * phases["planning"]["s_per_update"],
        "world-model fits": fit_s,
        "PPO-only: env + policy": ppo_steps * phases["ppo"]["s_per_step"],
        "PPO-only: PPO updates": (schedule["updates"] - planning_updates)
        * phases["ppo"]["s_per_update"],
    }
    out["total"] = sum(out.values())
    return out


def committed_rows(run: dict[str, object]) -> dict[str, float]:
    """The committed whole run's own seconds, split as :func:`extrapolate` splits them."""
    phases = run["phases"]
    plan = phases["planning"]
    first_batch = FRAMES * plan["s_per_step"] + plan["s_per_update"]  # in the first pace
    out = {
        "random phase": run["first_batch_s"] - run["fits"][0]["seconds"] - first_batch,
        "planning: env + planner": plan["collect_s"] + FRAMES * plan["s_per_step"],
        "planning: PPO updates": plan["update_s"] + plan["s_per_update"],
        "world-model fits": sum(f["seconds"] for f in run["fits"]),
        "PPO-only: env + policy": phases["ppo"]["collect_s"],
        "PPO-only: PPO updates": phases["ppo"]["update_s"],
    }
    out["total"] = sum(out.values())
    return out


def _short_run(variant: str, args: argparse.Namespace, tmp: Path, index: int) -> Path:
    run_dir = tmp / f"{re.sub('[^a-z0-9]+', '_', variant)}_{index}"
    total = args.random_steps + (args.planning_updates + args.ppo_updates) * FRAMES
    threads = 2 if variant.endswith("threads=2") else 1
    overrides = [
        f"world_model.random_steps={args.random_steps}",
        f"planning_updates={args.planning_updates}",
        f"total_steps={total}",
        f"threads={threads}",
        "progress=false",
        f"eval_every={10 * total}",
        f"checkpoint.every_steps={10 * total}",
        "world_model.save_fits=false",
        f"run_dir={run_dir}",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    if variant == "autograd fit":
        command = [sys.executable, "-c", _AUTOGRAD_CHILD, str(RECIPE), *overrides]
    else:
        command = [sys.executable, str(RECIPE), *overrides]
    proc = subprocess.run(command, env=env, cwd=tmp, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{variant} run failed:\n{proc.stderr[-3000:]}")
    return run_dir


def _median_unit(units: list[dict[str, object]]) -> dict[str, object]:
    """Per-unit costs: the median over a variant's runs."""
    out = json.loads(json.dumps(units[0]))
    out["first_batch_s"] = statistics.median(u["first_batch_s"] for u in units)
    out["fits"][0]["seconds"] = statistics.median(u["fits"][0]["seconds"] for u in units)
    out["fits"][0]["us_per_transition_epoch"] = statistics.median(
        u["fits"][0]["us_per_transition_epoch"] for u in units
    )
    for name, phase in out["phases"].items():
        for key in ("s_per_step", "s_per_update"):
            phase[key] = statistics.median(u["phases"][name][key] for u in units)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 round, 2+2 updates")
    parser.add_argument("--rounds", type=int, default=2, help="A/B rounds")
    parser.add_argument("--random-steps", type=int, default=10_000)
    parser.add_argument("--planning-updates", type=int, default=4)
    parser.add_argument("--ppo-updates", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="*", default=[1], choices=[1, 2])
    parser.add_argument("--run", type=Path, default=DEFAULT_RUN, help="committed whole run")
    parser.add_argument("--thesis-only", action="store_true", help="only the committed run")
    parser.add_argument(
        "--units-from",
        type=Path,
        default=None,
        help="reuse the short runs' unit costs of an earlier result JSON instead of measuring",
    )
    parser.add_argument("--out", default="main_job")
    args = parser.parse_args()
    if args.quick:
        args.rounds, args.planning_updates, args.ppo_updates = 1, 3, 2
    schedule = run_breakdown(args.run)
    table = {"committed run": committed_rows(schedule)}
    units: dict[str, list[dict[str, object]]] = {}
    if args.units_from is not None:
        units = json.loads(args.units_from.read_text())["runs"]
    elif not args.thesis_only:
        variants = ["autograd fit", "fused fit"] + (["fused fit, threads=2"] * (2 in args.threads))
        with tempfile.TemporaryDirectory() as d:
            for r in range(args.rounds):
                for variant in variants if r % 2 == 0 else variants[::-1]:
                    run_dir = _short_run(variant, args, Path(d), r)
                    units.setdefault(variant, []).append(run_breakdown(run_dir))
                    print(f"round {r}: {variant} done", flush=True)
    for variant, runs in units.items():
        table[variant] = extrapolate(_median_unit(runs), schedule)
    rows = [
        {"component": name, **{column: values[name] for column, values in table.items()}}
        for name in table["committed run"]
    ]
    units_rows = [
        {
            "variant": variant,
            "fit us/transition-epoch": _median_unit(runs)["fits"][0]["us_per_transition_epoch"],
            "planning ms/step": _median_unit(runs)["phases"]["planning"]["s_per_step"] * 1e3,
            "PPO-only ms/step": _median_unit(runs)["phases"]["ppo"]["s_per_step"] * 1e3,
            "update s": _median_unit(runs)["phases"]["ppo"]["s_per_update"],
            "runs": len(runs),
        }
        for variant, runs in [("committed run", [schedule]), *units.items()]
    ]
    print_table(units_rows)
    print_table(rows)
    extra = {
        "job": "recipes/train.py defaults (PPO-MPC, HalfCheetah-v5, thesis settings)",
        "committed_run": schedule,
        "units_from": None if args.units_from is None else args.units_from.name,
        "short_run": {
            "random_steps": args.random_steps,
            "planning_updates": args.planning_updates,
            "ppo_updates": args.ppo_updates,
            "rounds": args.rounds,
        },
        "units": units_rows,
        "load_average": os.getloadavg(),
        "runs": dict(units),
    }
    print(f"wrote {write(args.out, rows, extra)}")


if __name__ == "__main__":
    main()
