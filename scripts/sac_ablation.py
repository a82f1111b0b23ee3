"""The SAC ablation table: our SAC's variants beside Stable-Baselines3's SAC at fixed real steps.

    python scripts/sac_ablation.py                   # prints the table, writes the JSON

Reads the committed run folders (``results/hybrid/runs``: the ablation; ``results/thesis/runs``:
the default SAC and SB3's SAC with the same settings) through :mod:`torchrl_mbmf.analysis` and
reports, per variant and seed, the mean training return of the last 10 episodes and the latest
deterministic evaluation at or before each step (the thesis runs evaluated one episode every
20,480 steps, the ablation ten every 10,000: their evaluation columns are not comparable, the
training column is). Then the variants run under one protocol to 1e5 (ours and SB3's, five seeds
each, ten evaluation episodes every 10,000 steps; then ours with SB3's actor scale,
``sac_scale_queue.txt``) side by side: the IQM over seeds of each
measure with its 95% bootstrap interval. Writes ``results/hybrid/sac_ablation.json``.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from torchrl_mbmf.analysis.runs import Run, load_runs
from torchrl_mbmf.analysis.stats import bootstrap_ci, iqm

ROOT = Path(__file__).resolve().parents[1]
#: ``<label>: run-name pattern`` (the seed is the name's last part).
VARIANTS = {
    "ours: smooth_l1, 1000 updates per 1000 steps (the first defaults)": (
        r"^HalfCheetah-v5__sac__default__h10__seed\d$"
    ),
    "ours: l2, 1000 per 1000": r"^HalfCheetah-v5__sac__l2__fpb1000__seed\d$",
    "ours: l2, 50 per 50": r"^HalfCheetah-v5__sac__l2__fpb50__seed\d$",
    "ours: smooth_l1, 50 per 50": r"^HalfCheetah-v5__sac__smoothl1__fpb50__seed\d$",
    "SB3 SAC (squared error, 1 per step)": r"^HalfCheetah-v5__sb3_sac__default__seed\d$",
    "ours, l2, 50 per 50, torchrl's softplus scale, runs to 1e5": (
        r"^HalfCheetah-v5__sac__l2__fpb50__1e5__seed\d$"
    ),
    "SB3 SAC, runs to 1e5 (10 evaluation episodes)": (
        r"^HalfCheetah-v5__sb3_sac__default__1e5__seed\d$"
    ),
    "ours, SB3's clamped log-std scale (the default since), runs to 1e5": (
        r"^HalfCheetah-v5__sac__l2__fpb50__clampedlogstd__1e5__seed\d$"
    ),
}


def value_at(run: Run, scalar: str, step: int) -> float | None:
    """The last value of ``scalar`` logged at or before ``step`` (``None`` if none or short).

    Args:
        run: the run.
        scalar: the scalar's name.
        step: the real step.
    """
    steps, values = run.scalar(scalar)
    if run.last_step < step or not (steps <= step).any():
        return None
    return float(values[steps <= step][-1])


def main() -> None:
    """Command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[50_000])
    parser.add_argument("--out", type=Path, default=ROOT / "results/hybrid/sac_ablation.json")
    args = parser.parse_args()
    runs = load_runs([ROOT / "results/hybrid/runs", ROOT / "results/thesis/runs"])
    table: dict[str, dict] = {}
    for label, pattern in VARIANTS.items():
        chosen = [r for r in runs if re.search(pattern, r.name)]
        if not chosen:
            continue
        rows = {}
        for step in args.steps:
            train = [value_at(r, "train/return_last10_mean", step) for r in chosen]
            evals = [value_at(r, "eval/return", step) for r in chosen]
            rows[str(step)] = {
                "seeds": [r.seed for r in chosen],
                "train_last10": train,
                "eval": evals,
                "commits": sorted({r.commit for r in chosen}),
            }
        table[label] = rows
    for step in args.steps:
        print(
            f"\n| variant (HalfCheetah-v5, {step:,} real steps) | seeds | last-10 training "
            "return per seed | mean | latest evaluation per seed |"
        )
        print("|---|---|---|---|---|")
        for label, rows in table.items():
            row = rows[str(step)]
            train = [v for v in row["train_last10"] if v is not None]
            fmt = ", ".join("n/a" if v is None else f"{v:,.0f}" for v in row["train_last10"])
            ev = ", ".join("n/a" if v is None else f"{v:,.0f}" for v in row["eval"])
            mean = f"{np.mean(train):,.0f}" if train else "n/a"
            print(f"| {label} | {row['seeds']} | {fmt} | {mean} | {ev} |")
    same_protocol = [label for label in table if "runs to 1e5" in label]
    print(
        "\n| variant (one protocol) | real steps | seeds | last-10 training return: IQM "
        "[95% CI] | evaluation: IQM [95% CI] |"
    )
    print("|---|---|---|---|---|")
    for label in same_protocol:
        for step in args.steps:
            row = table[label][str(step)]
            cells = []
            for measure in ("train_last10", "eval"):
                values = [v for v in row[measure] if v is not None]
                if not values:
                    cells.append("n/a")
                    continue
                ci = bootstrap_ci(values)
                row[f"{measure}_iqm"] = float(iqm(values))
                row[f"{measure}_ci95"] = [float(ci.low), float(ci.high)]
                cells.append(f"{float(iqm(values)):,.0f} [{ci.low:,.0f}, {ci.high:,.0f}]")
            print(f"| {label} | {step:,} | {len(row['seeds'])} | {cells[0]} | {cells[1]} |")
    args.out.write_text(json.dumps(table, indent=1) + "\n")
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
