"""The hybrid ablation table: LOOP-style acting and MBPO-style learning beside SAC and SB3's SAC.

    python scripts/hybrid_ablation.py                    # prints the tables, writes the JSON
    python scripts/hybrid_ablation.py --steps 20000 50000

Reads the committed run folders in ``results/hybrid/runs`` through :mod:`torchrl_mbmf.analysis`:
the two hybrid ablations of ``results/hybrid/ablation_queue.txt`` (HalfCheetah-v5 to 5e4 real
steps) and, under the same protocol (every real step counted, ten deterministic evaluation
episodes every 10,000 real steps), our SAC and Stable-Baselines3's SAC (runs to 1e5). For each
method and step: the latest evaluation at or before the step and the mean training return of
the last 10 episodes, per seed and as the IQM over seeds with its 95% bootstrap interval (a
seed that has not reached the step is left out and the seed count says so). Then the compute:
wall milliseconds per real step of each finished run over the whole run, and where the time of
its last process went (the summary's ``time_breakdown``; a resumed run's last process ran from
its checkpoint). Writes ``results/hybrid/hybrid_ablation.json``.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from torchrl_mbmf.analysis.runs import RETURN_CURVE, final_values, load_runs
from torchrl_mbmf.analysis.tables import TIME_PARTS, compute_row, compute_split, iqm_cell

ROOT = Path(__file__).resolve().parents[1]
#: ``<label>: run-name pattern`` (the seed is the name's last part).
METHODS = {
    "SAC (ours: l2, 50 updates per 50 steps)": r"^HalfCheetah-v5__sac__l2__fpb50__1e5__seed\d$",
    "SB3 SAC": r"^HalfCheetah-v5__sb3_sac__default__1e5__seed\d$",
    "(a) LOOP-style acting (hybrid_loop)": r"^HalfCheetah-v5__hybrid_loop__.*__5e4__seed\d$",
    "(b) MBPO-style learning (hybrid_mbpo)": r"^HalfCheetah-v5__hybrid_mbpo__.*-utd5__5e4__seed\d$",
    "(b2) MBPO-style, 10 updates per real step": (
        r"^HalfCheetah-v5__hybrid_mbpo__.*-utd10__5e4__seed\d$"
    ),
}
MEASURES = {"eval": "eval/return", "train_last10": RETURN_CURVE}
PARTS = TIME_PARTS


def main() -> None:
    """Command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[20_000, 30_000, 40_000, 50_000])
    parser.add_argument("--runs", type=Path, default=ROOT / "results/hybrid/runs")
    parser.add_argument("--out", type=Path, default=ROOT / "results/hybrid/hybrid_ablation.json")
    args = parser.parse_args()
    runs = load_runs([args.runs])
    table: dict[str, dict[str, object]] = {}
    for label, pattern in METHODS.items():
        chosen = sorted((r for r in runs if re.search(pattern, r.name)), key=lambda r: r.seed)
        if not chosen:
            continue
        rows: dict[str, object] = {
            "seeds": [r.seed for r in chosen],
            "last_step": [r.last_step for r in chosen],
            "commits": sorted({r.commit for r in chosen}),
            "compute": compute_split(chosen),
        }
        for step in args.steps:
            for key, scalar in MEASURES.items():
                text, record = iqm_cell(final_values(chosen, scalar, at_step=step))
                rows[f"{key}@{step}"] = {**record, "text": text}
        table[label] = rows
    for key, what in (("eval", "evaluation (10 episodes)"), ("train_last10", "last-10 training")):
        head = " | ".join(f"{s:,}" for s in args.steps)
        print(f"\n| HalfCheetah-v5, {what} return: IQM [95% CI] (seeds) | {head} |")
        print("|---" * (len(args.steps) + 1) + "|")
        for label, rows in table.items():
            cells = " | ".join(rows[f"{key}@{s}"]["text"] for s in args.steps)
            print(f"| {label} | {cells} |")
    print("\n| method | seeds: real steps reached | per seed at the last step (evaluation) |")
    print("|---|---|---|")
    last = args.steps[-1]
    for label, rows in table.items():
        reached = ", ".join(
            f"{s}: {n:,}" for s, n in zip(rows["seeds"], rows["last_step"], strict=True)
        )
        values = ", ".join(f"{v:,.0f}" for v in rows[f"eval@{last}"]["values"])
        print(f"| {label} | {reached} | {values or 'n/a'} |")
    print(
        "\n| method (finished runs) | wall ms per real step, per seed | last process: resumed "
        "from (its CPU) | its ms per real step: " + " | ".join(PARTS) + " |"
    )
    print("|---" * (len(PARTS) + 3) + "|")
    for label, rows in table.items():
        if (row := compute_row(label, rows["compute"])) is not None:
            print(row)
    args.out.write_text(json.dumps(table, indent=1) + "\n")
    print(f"\nwrote {args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out}")


if __name__ == "__main__":
    main()
