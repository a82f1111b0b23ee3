"""The hybrid's final table: hybrid_mbpo beside our SAC, SB3's SAC and the ablations, per task.

    python scripts/hybrid_final.py                         # tables, JSON and figures
    python scripts/hybrid_final.py --steps 50000 100000

Reads the committed run folders in ``results/hybrid/runs`` through :mod:`torchrl_mbmf.analysis`:
the final runs of ``results/hybrid/final_queue.txt`` (``experiment=hybrid_mbpo`` on
HalfCheetah-v5, seeds 0-4, and on Hopper-v5 and Walker2d-v5, seeds 0-2; SB3's SAC and our SAC
beside them), the ablations of ``results/hybrid/ablation_queue.txt`` (to 5e4) and the SAC runs
of ``results/hybrid/sac_vs_sb3_queue.txt`` (to 1e5). Every real step is counted (the uniform
random ones too); the evaluation is ten deterministic episodes every 10,000 real steps.

For each task, method and step: the latest evaluation at or before the step, per seed and as
the IQM over seeds with its 95% bootstrap interval (a seed that has not reached the step is left
out and the seed count says so); the ratio of the hybrid's IQM to SB3 SAC's with its bootstrap
interval; the compute of the runs at each budget they finished at, earlier budgets of runs since
continued included (wall milliseconds per real step over the whole run to that budget, and where
the time of the process that reached it went). Writes ``results/hybrid/hybrid_final.json`` and
one figure per task, ``results/hybrid/final_<task>.png``: the evaluation curves of the hybrid and
both SACs, with the published numbers on HalfCheetah-v5 beside them.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from torchrl_mbmf.analysis.plots import plot_curves
from torchrl_mbmf.analysis.runs import RETURN_CURVE, Run, aggregate_curve, final_values, load_runs
from torchrl_mbmf.analysis.stats import iqm_ratio_ci
from torchrl_mbmf.analysis.tables import (
    TIME_PARTS,
    compute_row,
    compute_split,
    iqm_cell,
    process_rows,
)

ROOT = Path(__file__).resolve().parents[1]
HYBRID = "hybrid_mbpo (final)"
SAC_SOFTPLUS = "SAC (ours, softplus scale)"
#: ``{task: {label: run-name pattern}}`` (the seed is the name's last part); the rows in order
METHODS = {
    "HalfCheetah-v5": {
        # torchrl's softplus actor scale (the default until 2026-12-06), then SB3's (the default)
        f"{SAC_SOFTPLUS}, 1e5 runs": r"^HalfCheetah-v5__sac__l2__fpb50__1e5__seed\d$",
        f"{SAC_SOFTPLUS}, 2e5 runs": r"^HalfCheetah-v5__sac__l2__fpb50__2e5__seed\d$",
        "SAC (ours, SB3's clamped log-std scale: the default), 1e5 runs": (
            r"^HalfCheetah-v5__sac__l2__fpb50__clampedlogstd__1e5__seed\d$"
        ),
        "SB3 SAC, 1e5 runs": r"^HalfCheetah-v5__sb3_sac__default__1e5__seed\d$",
        "SB3 SAC, 2e5 runs": r"^HalfCheetah-v5__sb3_sac__default__2e5__seed\d$",
        "(a) LOOP-style acting, ablation": r"^HalfCheetah-v5__hybrid_loop__.*__5e4__seed\d$",
        "(b) MBPO-style, 5 updates, ablation": (
            r"^HalfCheetah-v5__hybrid_mbpo__.*-utd5__5e4__seed\d$"
        ),
        "(b2) MBPO-style, 10 updates, ablation": (
            r"^HalfCheetah-v5__hybrid_mbpo__.*-utd10__5e4__seed\d$"
        ),
        HYBRID: r"^HalfCheetah-v5__hybrid_mbpo__H1-r0\.05-utd5__seed\d$",
    },
    "Hopper-v5": {
        "SB3 SAC, 1e5 runs": r"^Hopper-v5__sb3_sac__default__1e5__seed\d$",
        HYBRID: r"^Hopper-v5__hybrid_mbpo__H1-r0\.05-utd5__1e5__seed\d$",
    },
    "Walker2d-v5": {
        "SB3 SAC, 1e5 runs": r"^Walker2d-v5__sb3_sac__default__1e5__seed\d$",
        HYBRID: r"^Walker2d-v5__hybrid_mbpo__H1-r0\.05-utd5__1e5__seed\d$",
    },
}
#: Published HalfCheetah evaluation returns at 1e5 and 2e5 environment steps (the authors' or
#: third parties' committed result files): ``{method: ((step, low, high), ...)}``.
ANCHORS = {
    "HalfCheetah-v5": {
        "DHMBPO": ((100_000, 9_878, 9_878), (200_000, 10_568, 10_568)),
        "MBPO": ((100_000, 9_553, 9_553), (200_000, 10_681, 10_681)),
        "MACURA": ((100_000, 9_182, 9_182), (200_000, 11_520, 11_520)),
        "DR.Q": ((100_000, 9_439, 9_439), (200_000, 10_729, 10_729)),
        "BRO": ((100_000, 8_330, 8_330), (200_000, 9_772, 9_772)),
        "CrossQ": ((100_000, 8_112, 8_112), (200_000, 9_363, 9_363)),
        "TD-MPC2": ((100_000, 7_251, 7_251), (200_000, 9_975, 9_975)),
        "SAC (range)": ((100_000, 6_156, 7_178), (200_000, 7_679, 8_315)),
    }
}
MEASURES = {"eval": "eval/return", "train_last10": RETURN_CURVE}
EVAL = "eval/return"


def _rows(chosen: list[Run], steps: list[int]) -> dict[str, object]:
    """One method's JSON record: seeds, progress, commits, compute and a cell per step."""
    rows: dict[str, object] = {
        "seeds": [r.seed for r in chosen],
        "last_step": [r.last_step for r in chosen],
        "commits": sorted({r.commit for r in chosen}),
        # one record per budget the runs finished at (a run continued to a raised budget keeps
        # its earlier summary): the hybrid's 1e5 runs stay timed once continued towards 2e5
        "compute": [
            compute_split(chosen, at_step=step)
            for step in sorted({s for r in chosen for s in r.finished_at()})
        ],
    }
    for step in steps:
        for key, scalar in MEASURES.items():
            text, record = iqm_cell(final_values(chosen, scalar, at_step=step))
            rows[f"{key}@{step}"] = {**record, "text": text}
    return rows


def _ratio(candidate: list[float], reference: list[float]) -> dict[str, object]:
    """``{"text", ...}``: the IQM ratio with its interval (``n/a`` under two seeds a side)."""
    if len(candidate) < 2 or len(reference) < 2 or min(reference) <= 0:
        return {"text": "n/a"}  # an interval needs two seeds a side
    ci = iqm_ratio_ci(candidate, reference)
    text = (
        f"{ci.estimate:.2f}x [{ci.low:.2f}, {ci.high:.2f}] ({len(candidate)} vs {len(reference)})"
    )
    return {"text": text, "ratio": ci.estimate, "ci95": [ci.low, ci.high]}


def _figure(task: str, groups: dict[str, list[Run]], path: Path) -> list[str]:
    """The evaluation curves of the hybrid and both SACs.

    Each SAC's 2e5 runs once as many of them have finished as it has 1e5 runs, else its 1e5 runs.
    """
    shown: dict[str, list[Run]] = {}
    for name in (SAC_SOFTPLUS, "SB3 SAC"):
        longer, shorter = groups.get(f"{name}, 2e5 runs", []), groups.get(f"{name}, 1e5 runs", [])
        whole = sum(r.summary is not None for r in longer)  # partial copies do not count
        runs = longer if longer and whole >= len(shorter) else shorter
        if runs:
            shown[f"{name}, {'2e5' if runs is longer else '1e5'} runs"] = runs
    if groups.get(HYBRID):
        shown[HYBRID] = groups[HYBRID]
    if not shown:
        return []
    end = max(r.last_step for runs in shown.values() for r in runs)
    grid = np.arange(10_000, max(end, 10_000) + 1, 10_000)
    curves = {label: aggregate_curve(runs, EVAL, grid=grid) for label, runs in shown.items()}
    plot_curves(
        curves,
        path,
        title=f"{task}: evaluation return (IQM over seeds, 95% bootstrap interval)",
        ylabel="evaluation return (10 deterministic episodes)",
        anchors=ANCHORS.get(task),
    )
    return list(curves)


def _number(value: object, style: str = ".0f") -> str:
    """A table cell: ``value`` formatted (``","``: thousands, no decimals), ``n/a`` if None."""
    if value is None:
        return "n/a"
    return f"{float(value):,.0f}" if style == "," else f"{float(value):{style}}"


def main() -> None:
    """Command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[50_000, 100_000, 200_000])
    parser.add_argument("--runs", type=Path, default=ROOT / "results/hybrid/runs")
    parser.add_argument("--out", type=Path, default=ROOT / "results/hybrid/hybrid_final.json")
    parser.add_argument(
        "--figures", type=Path, default=ROOT / "results/hybrid", help="folder of the figures"
    )
    args = parser.parse_args()
    runs = load_runs([args.runs])
    result: dict[str, dict[str, object]] = {}
    for task, methods in METHODS.items():
        groups = {
            label: sorted((r for r in runs if re.search(pattern, r.name)), key=lambda r: r.seed)
            for label, pattern in methods.items()
        }
        groups = {label: chosen for label, chosen in groups.items() if chosen}
        if not groups:
            continue
        longest = max(r.last_step for chosen in groups.values() for r in chosen)
        steps = [s for s in args.steps if s <= longest] or args.steps[:1]
        table = {label: _rows(chosen, steps) for label, chosen in groups.items()}
        ratios = {}
        if HYBRID in groups:
            for label in (lab for lab in groups if lab.startswith("SB3 SAC")):
                ratios[f"hybrid / {label}"] = {
                    f"eval@{s}": _ratio(
                        final_values(groups[HYBRID], EVAL, at_step=s),
                        final_values(groups[label], EVAL, at_step=s),
                    )
                    for s in steps
                }
        figure = args.figures / f"final_{task}.png"
        shown = _figure(task, groups, figure)
        processes = {r.seed: process_rows(r) for r in groups.get(HYBRID, [])}
        result[task] = {
            "processes": processes,
            "steps": steps,
            "methods": table,
            "ratios": ratios,
            "figure": {"path": figure.name, "curves": shown} if shown else None,
            "anchors": {k: [list(p) for p in v] for k, v in ANCHORS.get(task, {}).items()},
        }
        head = " | ".join(f"{s:,}" for s in steps)
        print(f"\n| {task}, evaluation (10 episodes): IQM [95% CI] (seeds) | {head} |")
        print("|---" * (len(steps) + 1) + "|")
        for label, rows in table.items():
            print(f"| {label} | " + " | ".join(rows[f"eval@{s}"]["text"] for s in steps) + " |")
        for label, cells in ratios.items():
            print(f"| {label} | " + " | ".join(cells[f"eval@{s}"]["text"] for s in steps) + " |")
        print(f"\n| {task}, last-10 training return: IQM [95% CI] (seeds) | {head} |")
        print("|---" * (len(steps) + 1) + "|")
        for label, rows in table.items():
            cells = " | ".join(rows[f"train_last10@{s}"]["text"] for s in steps)
            print(f"| {label} | {cells} |")
        print(
            f"\n| {task}: method | seeds: real steps reached | evaluation per seed at each step |"
        )
        print("|---|---|---|")
        for label, rows in table.items():
            reached = ", ".join(
                f"{s}: {n:,}" for s, n in zip(rows["seeds"], rows["last_step"], strict=True)
            )
            per_step = "; ".join(
                f"{s:,}: " + ", ".join(f"{v:,.0f}" for v in rows[f"eval@{s}"]["values"])
                for s in steps
                if rows[f"eval@{s}"]["values"]
            )
            print(f"| {label} | {reached} | {per_step or 'n/a'} |")
        print(
            f"\n| {task}: method (runs finished at the budget) | wall ms per real step, per "
            "seed | the budget's last process: resumed from (its CPU) | its ms per real step: "
            + " | ".join(TIME_PARTS)
            + " |"
        )
        print("|---" * (len(TIME_PARTS) + 3) + "|")
        for label, rows in table.items():
            for record in rows["compute"]:
                if (row := compute_row(label, record)) is not None:
                    print(row)
        if processes:
            print(
                f"\n| {task}: {HYBRID}, per process | real steps | CPU | wall ms per real step "
                "| its ms per real step: learning | of it refits | rollouts | updates, "
                "evaluations, checkpoints | refit µs per transition and epoch | transitions per "
                "refit |"
            )
            print("|---" * 10 + "|")
        for seed, rows in processes.items():
            for row in rows:
                cells = [
                    f"seed {seed}",
                    f"{row['start']:,}-{row['end']:,}",
                    "?" if row["cpu"] == "?" else f"{row['cpu_name']}, {row['cpu']}",
                    _number(row["ms_per_real_step"]),
                    *(_number(row[f"{part}_ms"]) for part in ("learn", "refit", "rollout", "rest")),
                    _number(row["refit_us_per_transition_epoch"]),
                    _number(row["refit_transitions"], ","),
                ]
                print("| " + " | ".join(cells) + " |")
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"\nwrote {args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out}")


if __name__ == "__main__":
    main()
