"""The thesis' experiments 1-4 from run folders: figures, tables, intervals and verdicts.

:func:`analyze_experiments` reads every training run under some folders, groups them by method,
reward and horizon, and writes the figures of the thesis' sections 7.1.1-7.1.4 with the tables
behind them into one ``analysis.json``. Research questions Q1-Q4 (thesis section 1.1) get a
verdict from 95% bootstrap intervals of the IQM over seeds, compared at the same real-step count.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchrl_mbmf.analysis.horizon import THESIS_HORIZON_MSE
from torchrl_mbmf.analysis.plots import plot_curves, plot_gait_comparison, save_image
from torchrl_mbmf.analysis.refits import refit_errors
from torchrl_mbmf.analysis.runs import (
    MODEL_BASED_METHODS,
    Run,
    aggregate_curve,
    compare_intervals,
    final_values,
    fixed_threshold_table,
    group_runs,
    load_runs,
    ppo_maximum_table,
)
from torchrl_mbmf.analysis.stats import Interval, interval_summary
from torchrl_mbmf.runs.export import load_policy
from torchrl_mbmf.runs.layout import (
    CONFIG,
    GIT_COMMIT,
    MACHINE,
    POLICY,
    POLICY_RECORD,
    SUMMARY,
    TRAIN_LOG,
    RunFolder,
)

DEFAULT_HORIZON = 10
REWARDS = ("default", "head_pen", "shin_pen")


#: Stable-Baselines3 reference runs (``recipes/sb3_reference.py``: method ``sb3_<algo>``) and
#: their label on the figures of our PPO and SAC.
SB3_REFERENCES = {"ppo": "sb3_ppo (Stable-Baselines3)", "sac": "sb3_sac (Stable-Baselines3)"}


#: Returns the thesis states for its PPO, used as levels fixed in advance (default reward):
#: table 10's PPO maximum within the planning budget, and PPO's return at 1e6 (figure 11b).
THESIS_LEVELS = {
    "planning": (
        1247.0,
        "the thesis' PPO maximum within its planning budget (table 10: 1,247 at 393,216)",
    ),
    "finetune": (
        3000.0,
        "the thesis' PPO at 1e6 steps (about 3,000, figure 11b), which it says fine-tuned "
        "PPO-MPC reaches at about 7e5",
    ),
}


def _as_interval(d: dict[str, Any]) -> Interval:
    return Interval(d["iqm"], d["low"], d["high"], 0.95, d["n"])


def _common_step(groups: Iterable[Sequence[Run]]) -> int:
    """The largest real step every run of every group has reached."""
    return min(r.last_step for runs in groups for r in runs)


def _comparison(
    named: dict[str, list[Run]],
    reference: str,
    *,
    budget: int | None = None,
    thesis_level: tuple[float, str] | None = None,
) -> dict[str, Any]:
    """Intervals at a common step, PPO-maximum tables and fixed-level tables.

    The fixed levels (no bias from reading the level off the reference's own curve): the
    reference's IQM at the common step and, where given, ``thesis_level`` (value, source).
    """
    named = {k: v for k, v in named.items() if v}
    if reference not in named or len(named) < 2:
        return {"available": sorted(named), "complete": False}
    step = _common_step(named.values())
    # the step the comparison is meant for: the shortest configured budget, or ``budget``
    intended = min(r.total_steps for v in named.values() for r in v)
    if budget is not None:
        intended, step = min(intended, budget), min(step, budget)
    out: dict[str, Any] = {
        "available": sorted(named),
        "complete": True,
        "common_step": step,
        "intended_step": intended,
        # unfinished runs that hold the comparison below the step it is meant for
        "cut_short": {
            r.name: r.last_step for v in named.values() for r in v if r.last_step < intended
        },
        "runs": {k: [r.name for r in v] for k, v in named.items()},
        "partial_runs": {
            r.name: r.last_step for v in named.values() for r in v if r.last_step < r.total_steps
        },
        "intervals": {k: interval_summary(final_values(v, at_step=step)) for k, v in named.items()},
        "tables": {
            key: ppo_maximum_table(named, reference, budget=step, exclude_random=excl)
            for key, excl in (("all_steps", False), ("without_random", True))
        },
    }
    ref = out["intervals"][reference]
    levels = {}
    if ref is not None:
        levels["reference_at_step"] = (
            float(ref["iqm"]),
            f"{reference}'s IQM return at {step:,} real steps",
        )
    if thesis_level is not None:
        levels["thesis"] = thesis_level
    out["fixed_tables"] = {
        key: fixed_threshold_table(named, value, source=source, budget=step)
        for key, (value, source) in levels.items()
    }
    out["versus_reference"] = {
        k: compare_intervals(_as_interval(v), _as_interval(ref))
        for k, v in out["intervals"].items()
        if k != reference and v is not None and ref is not None
    }
    return out


# Planner statistics of the beyond-the-thesis variants, averaged over each run's training.
PLANNER_STATISTICS = ("planner/effective_horizon", "planner/disagreement")


def _planner_statistics(runs: Sequence[Run], step: int) -> dict[str, Any]:
    """Per-run mean of each logged planner statistic up to ``step``, with the IQM over runs."""
    out: dict[str, Any] = {}
    for name in PLANNER_STATISTICS:
        means = []
        for run in runs:
            steps, values = run.scalar(name)
            kept = values[steps <= step]
            if kept.size:
                means.append(float(kept.mean()))
        if means:
            out[name.split("/")[-1]] = interval_summary(means)
    return out


def _curves_figure(
    named: dict[str, list[Run]],
    path: Path,
    *,
    title: str,
    hline: float | None = None,
    hline_label: str = "",
    vlines: dict[str, float] | None = None,
    end: int | None = None,
) -> str | None:
    named = {k: v for k, v in named.items() if v}
    if not named:
        return None
    end = end or max(r.last_step for v in named.values() for r in v)
    grid = np.linspace(0, end, 101)[1:].round().astype(np.int64)
    curves = {k: aggregate_curve(v, grid=grid) for k, v in named.items()}
    plot_curves(curves, path, title=title, hline=hline, hline_label=hline_label, vlines=vlines)
    return path.name


def _gait(
    runs: dict[str, Run], out_dir: Path, *, steps: int, render: bool, clip_seconds: float = 0.0
) -> dict[str, Any]:
    """Gait metrics (and frames, and a video clip if ``clip_seconds``) of one policy per label."""
    from torchrl_mbmf.analysis.gait import frame_strip, gait_metrics, record_gait, render_states

    metrics, out = {}, {"policies": {}, "metrics": {}}
    for label, run in runs.items():
        if not (run.path / POLICY).exists():
            continue
        actor, env, info = load_policy(run.path)
        rollout = record_gait(env, actor, steps=steps)
        m = gait_metrics(rollout)
        metrics[label] = m
        out["policies"][label] = {"run": run.name, "real_steps": info["real_steps"]}
        out["metrics"][label] = {
            "average_power_W": dict(zip(m.joints, m.average_power, strict=True)),
            "total_abs_power_W": float(np.sum(m.average_abs_power)),
            "height_std_m": m.height_std,
            "distance_m": m.distance,
            "episode_return_60_steps": float(rollout.get(("next", "reward")).sum()),
        }
        if render:
            frames = render_states(rollout.get(("next", "state"))[:40])
            name = f"gait_frames_{label}.png"
            save_image(frame_strip(frames, num=8), out_dir / name)
            out["policies"][label]["frames"] = name
        if render and clip_seconds > 0:
            from torchrl_mbmf.analysis.video import record_policy

            clip = f"clip_{label}.mp4"
            record_policy(run.path, out_dir / clip, seconds=clip_seconds)
            out["policies"][label]["clip"] = clip
    if metrics:
        plot_gait_comparison(metrics, out_dir / "gait.png")
        out["figure"] = "gait.png"
        m = out["metrics"]
        out["steadiest"] = min(m, key=lambda k: m[k]["height_std_m"])
        out["least_power"] = min(m, key=lambda k: m[k]["total_abs_power_W"])
        out["furthest"] = max(m, key=lambda k: m[k]["distance_m"])
    return out


def _log_std_figure(runs: dict[str, list[Run]], path: Path) -> str | None:
    named = {k: v for k, v in runs.items() if v and v[0].scalar("train/policy_log_std")[0].size}
    if not named:
        return None
    end = max(r.last_step for v in named.values() for r in v)
    grid = np.linspace(0, end, 101)[1:].round().astype(np.int64)
    curves = {k: aggregate_curve(v, "train/policy_log_std", grid=grid) for k, v in named.items()}
    plot_curves(
        curves,
        path,
        title="PPO-MPC policy log standard deviation per reward (figure 19)",
        ylabel="mean log std of the policy (log of action units)",
        band=False,
    )
    return path.name


def _horizon(roots: Sequence[str | Path], out_dir: Path) -> dict[str, Any]:
    """Tables 8 and 9 over the seeds of ``recipes/fit_world_model.py`` folders.

    The first folder's prediction plots (figures 9, 10) are copied into ``out_dir``.
    """
    files = sorted(p for root in roots for p in Path(root).rglob("horizon_mse.json"))
    by_h: dict[int, dict[str, list[float]]] = {}
    folders = []
    for f in files:
        folders.append(f.parent.name)
        for e in json.loads(f.read_text()):
            row = by_h.setdefault(int(e["horizon"]), {"x_mse": [], "reward_mse": []})
            if e["x_mse"] is not None:  # None: a state without an x position
                row["x_mse"].append(float(e["x_mse"]))
            row["reward_mse"].append(float(e["reward_mse"]))
    thesis = THESIS_HORIZON_MSE
    rows = []
    for h in sorted(by_h):
        rows.append(
            {
                "horizon": h,
                "x_mse": interval_summary(by_h[h]["x_mse"]),
                "reward_mse": interval_summary(by_h[h]["reward_mse"]),
                "thesis_x_mse": thesis.get(h, (None, None))[0],
                "thesis_reward_mse": thesis.get(h, (None, None))[1],
            }
        )
    figures = {}
    for quantity in ("x", "reward"):
        plots = [f.parent / f"horizon_{quantity}.png" for f in files]
        plots = [p for p in plots if p.exists()]
        if plots:
            shutil.copy2(plots[0], out_dir / f"horizon_{quantity}.png")
            figures[quantity] = f"horizon_{quantity}.png"
    return {"folders": folders, "rows": rows, "figures": figures}


def collect_runs(runs: Iterable[Run], dest: str | Path, *, max_file_bytes: int = 1_000_000) -> int:
    r"""Copies each run's small result files into ``dest/<run name>/``.

    Copied: config, summary, commit, scalar CSVs, exported policy and log; checkpoints are not.

    Args:
        runs: the runs.
        dest: destination folder.

    Keyword Args:
        max_file_bytes: files above this size are skipped. Defaults to 1 MB.

    Returns:
        The number of files copied.

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.runs import load_runs
        >>> from torchrl_mbmf.analysis.experiments import collect_runs
        >>> src, dst = (pathlib.Path(tempfile.mkdtemp()) for _ in range(2))
        >>> (src / "a/logs/scalars/train").mkdir(parents=True)
        >>> _ = (src / "a/config.yaml").write_text("method: ppo\nseed: 0\n")
        >>> _ = (src / "a/logs/scalars/train/episode_return.csv").write_text("1,2.0\n")
        >>> collect_runs(load_runs(src), dst)
        2
        >>> collect_runs(load_runs(dst), dst)  # already collected: nothing to copy
        0
    """
    dest = Path(dest)
    copied = 0
    for run in runs:
        names = (CONFIG, SUMMARY, GIT_COMMIT, MACHINE)
        files = [run.path / n for n in names]
        files += [run.path / POLICY, run.path / POLICY_RECORD, run.path / TRAIN_LOG]
        files += sorted(RunFolder(run.path).scalars.rglob("*.csv"))
        for f in files:
            if f.exists() and f.stat().st_size <= max_file_bytes:
                target = dest / run.name / f.relative_to(run.path)
                if target.exists() and target.samefile(f):
                    continue  # the run already lives in ``dest`` (re-analysing collected runs)
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(f, target)
                copied += 1
    return copied


def _verdict(cmp: dict[str, Any], candidate: str, reference: str) -> dict[str, Any]:
    """Q1/Q4-style verdict: does ``candidate`` need fewer real steps than ``reference``?"""
    if not cmp.get("complete"):
        return {"verdict": "not run", "why": f"runs available: {cmp.get('available')}"}
    row = next(r for r in cmp["tables"]["all_steps"]["rows"] if r["label"] == candidate)
    rel = cmp["versus_reference"].get(candidate, "n/a")
    ci_c, ci_r = cmp["intervals"][candidate], cmp["intervals"][reference]
    step = cmp["common_step"]
    text = (
        f"at {step} real steps {candidate} IQM {ci_c['iqm']:.0f} [{ci_c['low']:.0f}, "
        f"{ci_c['high']:.0f}] vs {reference} {ci_r['iqm']:.0f} [{ci_r['low']:.0f}, "
        f"{ci_r['high']:.0f}] (95% bootstrap CIs, {ci_c['n']} vs {ci_r['n']} seeds: {rel}); "
    )
    best = f"{reference}'s best ({cmp['tables']['all_steps']['threshold']:.0f})"
    if row["step"] is None:
        text += f"{candidate} never reached {best}"
    else:
        text += (
            f"{candidate} reached {best} "
            f"at {row['step']} real steps, ratio {row['ratio']:.2f}{_ratio_text(row)} "
            f"({row['seeds_reached']}/{len(row['seeds'])} seeds on their own)"
        )
    if cmp.get("cut_short"):
        names = ", ".join(f"{k} at {v:,}" for k, v in cmp["cut_short"].items())
        return {
            "verdict": "partial",
            "why": f"compared at {step:,} of {cmp['intended_step']:,} real steps, since runs "
            f"have not finished ({names}): {text}",
        }
    seeds = min(ci_c["n"], ci_r["n"])
    if 2 <= seeds < SEEDS:
        return {
            "verdict": "partial",
            "why": f"{seeds} of the {SEEDS} seeds on a side (the others have not reached "
            f"this step): {text}",
        }
    table = cmp["tables"]["all_steps"]
    random_level = table.get("random_policy_return")
    if random_level is not None and table["threshold"] <= random_level:
        text += (
            f"; {best} is no better than the random policy's return ({random_level:.0f}), "
            "so reaching it says nothing"
        )
    verdict = _verdict_word(rel, row, table)
    return {"verdict": verdict, "why": text}


def _verdict_word(rel: str, row: dict[str, Any], table: dict[str, Any]) -> str:
    """The verdict of a comparison: ``supported``, ``not supported`` or ``inconclusive``.

    ``supported`` needs both: higher at the common step (the intervals apart) and the whole
    bootstrap interval of the steps ratio below 1, against a threshold above the random
    policy's return; ``not supported`` needs the candidate lower; anything else is
    inconclusive.
    """
    if rel == "lower":
        return "not supported"
    ci = row.get("ratio_ci") or {}
    random_level = table.get("random_policy_return")
    meaningful = random_level is None or table["threshold"] > random_level
    if rel == "higher" and meaningful and ci.get("high", float("inf")) < 1:
        return "supported"
    return "inconclusive"


#: Seeds of every configuration of the experiments (0, 1, 2, fixed before running): a verdict
#: waits for all of them.
SEEDS = 3


def _final_eval(run: Run) -> float | None:
    """The run's closing evaluation (``summary.json``); the last periodic one while it runs."""
    closing = (run.summary or {}).get("final_eval_return")
    if closing is not None:
        return float(closing)
    return (final_values([run], "eval/return") or [None])[0]


def _ratio_text(row: dict[str, Any]) -> str:
    ci = row.get("ratio_ci")
    if not ci:
        return ""
    return f" [{ci['low']:.2f}, {ci['high']:.2f}] (95% bootstrap over seeds)"


def analyze_experiments(
    run_roots: Sequence[str | Path],
    out_dir: str | Path,
    *,
    world_model_roots: Sequence[str | Path] = (),
    gait: bool = True,
    render: bool = True,
    gait_steps: int = 60,
    collect: bool = True,
    clip_seconds: float = 0.0,
) -> dict[str, Any]:
    """Analyses experiments 1-4 over the runs under ``run_roots`` and writes figures and JSON.

    Runs are grouped by (method, reward, horizon); seeds are aggregated with the IQM and 95%
    bootstrap intervals. Comparisons are made at the largest real-step count every compared run
    has reached, so that interrupted runs are compared fairly; tables count every real step
    (``all_steps``) and, as the thesis also reports, without the random-data steps.

    Args:
        run_roots: folders holding training run folders (searched recursively).
        out_dir: where ``analysis.json``, the PNG figures and (with ``collect``) the runs' raw
            files go.

    Keyword Args:
        world_model_roots: folders of ``recipes/fit_world_model.py`` runs, for tables 8 and 9.
        gait: run the gait analysis of one PPO-MPC policy per reward (the lowest seed among
            the finished runs). Defaults to ``True``.
        render: render gait frames offscreen (needs ``MUJOCO_GL=egl`` or ``osmesa`` without a
            display). Defaults to ``True``.
        gait_steps: steps of the gait rollout. Defaults to ``60`` (the thesis' figures).
        collect: copy each run's small files under ``out_dir/runs``. Defaults to ``True``.
        clip_seconds: with ``gait`` and ``render``, a video of that many seconds of each gait
            policy (``clip_<reward>.mp4``, :func:`~torchrl_mbmf.analysis.video.record_policy`;
            needs the video extra). Defaults to ``0`` (no clips).

    Returns:
        The analysis (also written to ``out_dir/analysis.json``).

    Examples:
        >>> from torchrl_mbmf.analysis.experiments import analyze_experiments
        >>> analysis = analyze_experiments(["outputs/short"], "results/short")  # doctest: +SKIP
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = load_runs(run_roots)
    if not runs:
        raise FileNotFoundError(f"no training run folders under {list(map(str, run_roots))}")
    superseded = [
        {"name": r.name, "last_step": r.last_step, "complete": r.complete}
        for r in load_runs(run_roots, dedupe=False)
        if not any(r.path == k.path for k in runs)
    ]
    groups = group_runs(runs)
    h = DEFAULT_HORIZON

    def sel(method: str, reward: str = "default", horizon: int = h, variant: str = "") -> list[Run]:
        return groups.get((method, reward, horizon, variant), [])

    analysis: dict[str, Any] = {
        "superseded_runs": superseded,
        "runs": [
            {
                "name": r.name,
                "method": r.method,
                "reward": r.reward,
                "horizon": r.horizon,
                "seed": r.seed,
                "variant": r.variant,
                "total_steps": r.total_steps,
                "last_step": r.last_step,
                "complete": r.complete,
                "random_steps": r.random_steps,
                "last10_mean_return": (final_values([r]) or [None])[0],
                "final_eval_return": _final_eval(r),
                "seconds": r.wall_seconds,
                "refit_seconds": r.refit_seconds,
                "commit": r.commit,
                "machine": r.machine,
            }
            for r in runs
        ],
    }

    # Experiment 1: planning horizon (figure 8).
    exp1 = {f"h={hh}": sel("ppo_mpc", horizon=hh) for hh in (5, 10, 25)}
    cmp1 = _comparison(exp1, "h=10")
    cmp1["figure"] = _curves_figure(
        exp1,
        out_dir / "exp1_horizon.png",
        title="Experiment 1: PPO-MPC planning horizon (figure 8)",
    )
    analysis["exp1"] = cmp1

    # Stable-Baselines3 references (default reward; their configs have no planner: horizon 0).
    references = {algo: sel(f"sb3_{algo}", horizon=0) for algo in SB3_REFERENCES}
    analysis["sb3"] = {
        algo: _comparison({f"sb3_{algo}": refs, algo: sel(algo)}, f"sb3_{algo}")
        for algo, refs in references.items()
    }

    def with_reference(named: dict[str, list[Run]], algo: str, reward: str) -> dict:
        """``named`` plus the SB3 reference curve (figures only: never in tables)."""
        if reward != "default" or not references[algo]:
            return named
        return {**named, SB3_REFERENCES[algo]: references[algo]}

    # Experiment 2 (figures 11a/11b, table 10) and 3 (figures 12, 13) per reward.
    exp3: dict[str, Any] = {}
    for reward in REWARDS:
        named = {m: sel(m, reward) for m in ("ppo", "mpc", "ppo_mpc")}
        planning = [r.switch_step for r in named["ppo_mpc"] if r.switch_step]
        budget = min(planning) if planning else None
        default = reward == "default"
        cmp = _comparison(
            named, "ppo", budget=budget, thesis_level=THESIS_LEVELS["planning"] if default else None
        )
        if cmp.get("complete"):
            cmp["figure"] = _curves_figure(
                with_reference(named, "ppo", reward),
                out_dir / f"exp2_{reward}_planning.png",
                title=f"PPO, MPC and PPO-MPC, {reward} reward, planning phase",
                hline=cmp["tables"]["all_steps"]["threshold"],
                hline_label="PPO maximum",
                end=cmp["common_step"],
            )
        finetuned = [r for r in named["ppo_mpc"] if r.switch_step and r.last_step > r.switch_step]
        if finetuned:
            ft = _comparison(
                {"ppo": named["ppo"], "ppo_mpc": finetuned},
                "ppo",
                thesis_level=THESIS_LEVELS["finetune"] if default else None,
            )
            cmp["finetune"] = ft
            # with the PPO-maximum line of figures 11b, 12b, 13b
            cmp["finetune_figure"] = _curves_figure(
                with_reference(
                    {"ppo": named["ppo"], "ppo_mpc (fine-tuned after the switch)": finetuned},
                    "ppo",
                    reward,
                ),
                out_dir / f"exp2_{reward}_finetune.png",
                title=f"PPO vs PPO-MPC with warm-start fine-tuning, {reward} reward",
                vlines={"switch to pure PPO": float(finetuned[0].switch_step)},
                hline=ft["tables"]["all_steps"]["threshold"] if ft.get("complete") else None,
                hline_label="PPO maximum",
            )
        else:
            cmp["finetune"] = {"complete": False, "why": "no PPO-MPC run went past its switch step"}
        exp3[reward] = cmp
    analysis["exp2"] = exp3["default"]
    analysis["exp3"] = {k: v for k, v in exp3.items() if k != "default"}

    log_std = {rw: sel("ppo_mpc", rw) for rw in REWARDS}
    analysis["log_std_figure"] = _log_std_figure(log_std, out_dir / "exp3_log_std.png")
    if gait:
        # One policy per reward: the lowest seed whose run finished (else got furthest).
        seed0 = {
            rw: sorted(
                (r for r in v if (r.path / POLICY).exists()),
                key=lambda r: (not r.complete, -r.last_step, r.seed),
            )[0]
            for rw, v in log_std.items()
            if any((r.path / POLICY).exists() for r in v)
        }
        analysis["gait"] = _gait(
            seed0, out_dir, steps=gait_steps, render=render, clip_seconds=clip_seconds
        )

    # Experiment 4: SAC vs SAC-MPC (figure 17).
    exp4 = {m: sel(m) for m in ("sac", "sac_mpc")}
    cmp4 = _comparison(exp4, "sac")
    if cmp4.get("complete"):
        cmp4["figure"] = _curves_figure(
            with_reference(exp4, "sac", "default"),
            out_dir / "exp4_sac.png",
            title="Experiment 4: SAC vs SAC-MPC (figure 17)",
            hline=cmp4["tables"]["all_steps"]["threshold"],
            hline_label="SAC maximum",
            end=cmp4["common_step"],
        )
    analysis["exp4"] = cmp4

    analysis["horizon_mse"] = _horizon(world_model_roots, out_dir) if world_model_roots else None
    # Tables 8 and 9 at every refit of the model-based runs (default reward, h = 10).
    analysis["refits"] = {m: refit_errors(sel(m)) for m in MODEL_BASED_METHODS if sel(m)}

    # Beyond the thesis: every variant of PPO-MPC and SAC-MPC against the thesis' planner.
    ablation: dict[str, Any] = {}
    for method in ("ppo_mpc", "sac_mpc"):
        named = {
            (k[3] or "thesis"): v
            for k, v in groups.items()
            if k[0] == method and k[1] == "default" and k[2] == h
        }
        if len(named) < 2 or "thesis" not in named:
            continue
        # Each variant against the thesis planner at the largest step both reached, so one
        # interrupted variant does not cut the comparison of all the others short.
        variants = {
            name: _comparison({"thesis": named["thesis"], name: runs}, "thesis")
            for name, runs in sorted(named.items())
            if name != "thesis"
        }
        for name, cmp in variants.items():
            if cmp.get("complete"):
                cmp["planner"] = _planner_statistics(named[name], cmp["common_step"])
        ablation[method] = {
            "variants": variants,
            "figure": _curves_figure(
                named,
                out_dir / f"ablation_{method}.png",
                title=f"{method}: thesis planner vs variants (default reward)",
            ),
        }
    analysis["ablation"] = ablation

    # Verdicts on the research questions (thesis section 1.1).
    q2 = {"verdict": "not run", "why": "needs PPO-MPC and MPC runs"}
    e2 = analysis["exp2"]
    mpc_seeds = min(
        (iv["n"] for k, iv in e2.get("intervals", {}).items() if k in ("mpc", "ppo_mpc") and iv),
        default=0,
    )
    if e2.get("complete") and e2.get("cut_short") and "mpc" in e2["intervals"]:
        q2 = {"verdict": "partial", "why": f"runs have not finished: {e2['cut_short']}"}
    elif e2.get("complete") and e2["intervals"].get("mpc") and mpc_seeds < SEEDS:
        q2 = {
            "verdict": "partial" if mpc_seeds >= 2 else "inconclusive",
            "why": f"{mpc_seeds} of the {SEEDS} seeds on a side at {e2['common_step']:,} steps",
        }
    elif e2.get("complete") and "mpc" in e2["intervals"] and e2["intervals"]["mpc"]:
        rel = compare_intervals(
            _as_interval(e2["intervals"]["ppo_mpc"]), _as_interval(e2["intervals"]["mpc"])
        )
        a, b = e2["intervals"]["ppo_mpc"], e2["intervals"]["mpc"]
        q2 = {
            "verdict": {"higher": "supported", "lower": "not supported"}.get(rel, "inconclusive"),
            "why": f"at {e2['common_step']} real steps PPO-MPC IQM {a['iqm']:.0f} "
            f"[{a['low']:.0f}, {a['high']:.0f}] vs MPC {b['iqm']:.0f} [{b['low']:.0f}, "
            f"{b['high']:.0f}] (95% bootstrap CIs): {rel}",
        }
    q3_parts = {
        rw: _verdict(exp3[rw], "ppo_mpc", "ppo") for rw in REWARDS if exp3[rw].get("complete")
    }
    words = [p["verdict"] for p in q3_parts.values()]
    if len(q3_parts) < 2:
        q3_verdict = "not run"  # no penalised reward compared yet
    elif len(q3_parts) < len(REWARDS) or "partial" in words:
        q3_verdict = "partial"
    elif all(w == "supported" for w in words):
        q3_verdict = "robust"
    elif "supported" in words and "not supported" in words:
        q3_verdict = "reward-sensitive"
    elif "supported" not in words and "not supported" in words:
        q3_verdict = "no advantage"
    else:
        q3_verdict = "inconclusive"
    q3 = {
        "verdict": q3_verdict,
        "per_reward": q3_parts,
        "gait": {
            k: analysis.get("gait", {}).get(k) for k in ("steadiest", "least_power", "furthest")
        },
    }
    q1 = _verdict(analysis["exp2"], "ppo_mpc", "ppo")
    finetune = analysis["exp2"].get("finetune", {})
    if finetune.get("complete"):
        after = _verdict(finetune, "ppo_mpc", "ppo")
        q1 = {**q1, "why": f"planning phase: {q1['why']}; after fine-tuning: {after['why']}"}
        q1["finetune_verdict"] = after["verdict"]
    analysis["verdicts"] = {
        "Q1": q1,
        "Q2": q2,
        "Q3": q3,
        "Q4": _verdict(analysis["exp4"], "sac_mpc", "sac"),
    }
    if collect:
        analysis["collected_files"] = collect_runs(runs, out_dir / "runs")
    (out_dir / "analysis.json").write_text(json.dumps(analysis, indent=2, default=_jsonable))
    return analysis


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"cannot serialise {type(x).__name__}")


__all__ = ["analyze_experiments", "collect_runs"]
