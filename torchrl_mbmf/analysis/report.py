"""Markdown report of the experiments next to the thesis' own numbers."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torchrl_mbmf.checks import check_input_file, check_output_path

# The thesis' numbers the report sets ours against (sections 7.1.1-7.1.4, 8).
THESIS = {
    "exp1": "h = 10 gave the highest returns, a maximum average return of 1908 within 4e5 steps; "
    "h = 5 led early (before ~1e5 steps), h = 25 lagged throughout.",
    "table10": [
        ("PPO", "1247", "393,216"),
        ("MPC", "-", "never reached"),
        ("PPO-MPC", "1265", "274,432"),
    ],
    "finetune": "PPO reaches ~3000 at 1e6 steps; fine-tuned PPO-MPC reaches it at ~7e5 steps "
    "(the thesis calls this a saving of 5e5 samples; its own figures give 1e6 - 7e5 = 3e5).",
    "exp3": "HeadPen and ShinPen: PPO-MPC falls behind PPO (HeadPen from ~2e5 steps); ShinPen "
    "gives the steadiest gait (least torso height variation), least joint power and the furthest "
    "distance in 60 steps; HeadPen the least stable gait; Default has the lowest policy log-std.",
    "exp4": "SAC-MPC reaches SAC's maximum at 1.25e5 steps, SAC at 2e5 (ratio 0.625).",
    "Q1": "yes: PPO-MPC reaches PPO's maximum ~1e5 steps earlier (table 10), and fine-tuned "
    "PPO-MPC reaches PPO's 1e6-step score at ~7e5 steps",
    "Q2": "yes: policy-guided planning always beat naive MPC",
    "Q3": "reward-sensitive: PPO-MPC's advantage holds for Default only; ShinPen has the most "
    "efficient gait",
    "Q4": "yes: SAC-MPC needs 7.5e4 fewer samples than SAC",
}


def _fmt(x: Any, digits: int = 0) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:,.{digits}f}"
    if isinstance(x, int):
        return f"{x:,}"
    return str(x)


def _ci(d: Mapping[str, Any] | None, digits: int = 0) -> str:
    if not d:
        return "-"
    return f"{d['iqm']:,.{digits}f} [{d['low']:,.{digits}f}, {d['high']:,.{digits}f}] (n={d['n']})"


def _per_seed_or_ci(d: Mapping[str, Any] | None, digits: int = 0) -> str:
    """The interval with three or more seeds, else each seed's value.

    A mean of two values can stand for neither (one diverged model and one good one).
    """
    if not d or d["n"] >= 3 or not d.get("values"):
        return _ci(d, digits)
    return ", ".join(f"{v:,.{digits}f}" for v in d["values"]) + f" (n={d['n']}, each seed)"


def _ratio_ci(ci: Mapping[str, float], number: str = ".2f") -> str:
    """``[low, high]``; an infinite bound is a share of resamples that never reached it.

    ``number`` formats the finite bounds (``",.0f"`` for real steps).
    """

    def bound(x: float) -> str:
        return "never" if x == float("inf") else f"{x:{number}}"

    text = f"[{bound(ci['low'])}, {bound(ci['high'])}]"
    if ci["reached"] < 1:
        text += f" (reached in {ci['reached']:.0%} of resamples)"
    return text


def _figure(rel: str, name: str | None, caption: str) -> list[str]:
    return [f"![{caption}]({rel}/{name})", f"*{caption}*", ""] if name else []


def _comparison_md(cmp: Mapping[str, Any], rel: str, caption: str, thesis: str | None) -> list[str]:
    if not cmp.get("complete"):
        return [f"Not run at this budget (runs available: {cmp.get('available', [])}).", ""]
    out = _figure(rel, cmp.get("figure"), caption)
    reference = cmp["tables"]["all_steps"]["reference"]
    out += [
        f"Compared at **{cmp['common_step']:,} real steps** (the largest count every compared "
        "run reached), IQM over seeds of the last-10-episode mean return with its 95% "
        "bootstrap interval:",
        "",
        f"| configuration | return at the common step | vs {reference} | seeds |",
        "|---|---|---|---|",
    ]
    versus = cmp.get("versus_reference", {})
    for label, iv in cmp["intervals"].items():
        relation = versus.get(label, "reference" if label == reference else "-")
        out.append(f"| {label} | {_ci(iv)} | {relation} | {', '.join(cmp['runs'][label])} |")
    out.append("")
    for key, title in (
        ("all_steps", "every real step counted (random-data steps included)"),
        ("without_random", "random-data steps not counted (the thesis' convention)"),
    ):
        t = cmp["tables"][key]
        out += [
            f"First step reaching the {t['reference']} maximum ({t['threshold']:,.0f}), {title}:",
            "",
            "| configuration | best IQM return | first step | ratio to reference [95% "
            "bootstrap interval over seeds] | seeds reaching it alone |",
            "|---|---|---|---|---|",
        ]
        for r in t["rows"]:
            ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}"
            if r.get("ratio_ci"):
                ratio += f" {_ratio_ci(r['ratio_ci'])}"
            out.append(
                f"| {r['label']} | {_fmt(r['best'])} | {_fmt(r['step'])} | {ratio} | "
                f"{r['seeds_reached']}/{len(r['seeds'])} |"
            )
        out.append("")
        out += _table_caveats(t)
    out += _fixed_tables_md(cmp.get("fixed_tables", {}))
    if cmp.get("partial_runs"):
        parts = ", ".join(f"{k} stopped at {v:,}" for k, v in cmp["partial_runs"].items())
        out += [f"Partial runs (interrupted before their budget): {parts}.", ""]
    if thesis:
        out += [f"Thesis: {thesis}", ""]
    return out


def _fixed_tables_md(tables: Mapping[str, Any]) -> list[str]:
    """The steps to levels fixed in advance, one row per configuration and level."""
    if not tables:
        return []
    spacing = next(iter(tables.values()))["grid_spacing"]
    out = [
        "Real steps to a level fixed in advance, every real step counted, each with its own "
        "95% bootstrap interval over its seeds (a resample's curve only where all its seeds "
        f"have a value; grid {spacing:,.0f} steps). The thesis' level is not read off any "
        "compared curve, so it favours no side. The reference's IQM at the step is the end "
        "point of the reference's own curve, which it reaches by construction at that step "
        "at the latest; unlike its maximum (the tables above), it is not the best point of "
        "its noise:",
        "",
        "| level | configuration | first step of the IQM curve | 95% bootstrap interval "
        "| seeds reaching it alone |",
        "|---|---|---|---|---|",
    ]
    for t in tables.values():
        for r in t["rows"]:
            step = "never" if r["step"] is None else f"{r['step']:,}"
            out.append(
                f"| {t['threshold']:,.0f}: {t['source']} | {r['label']} | {step} | "
                f"{_ratio_ci(r['step_ci'], ',.0f')} | {r['seeds_reached']}/{len(r['seeds'])} |"
            )
    return [*out, ""]


def _table_caveats(t: Mapping[str, Any]) -> list[str]:
    """What a steps-to-the-maximum table cannot say, from its own numbers."""
    notes = []
    if t.get("reference_self"):
        notes.append(
            f"The threshold is the maximum of the {t['reference']} curve itself, which it "
            "reaches by construction: the ratio is biased upwards. Calibration: "
            f"{t['reference']} against itself (both sides resampled from its seeds) gives "
            f"{_ratio_ci(t['reference_self'])}; a ratio interval like that is what two "
            "identical methods show."
        )
    if t.get("grid_spacing"):
        notes.append(
            f"First steps are read on a grid {t['grid_spacing']:,.0f} real steps apart; "
            "curves count a run once its last-10 window holds only its own policy's episodes, "
            "and only where every seed has a value."
        )
    random_level = t.get("random_policy_return")
    if random_level is not None and t["threshold"] <= random_level:
        notes.append(
            f"**The threshold ({t['threshold']:,.0f}) is no better than the random policy's "
            f"return ({random_level:,.0f}, the random-data episodes): reaching it says nothing.**"
        )
    return [" ".join(notes), ""] if notes else []


def _ablation_md(ablation: Mapping[str, Any], rel: str, caption: str) -> list[str]:
    """One row per variant, each compared with the thesis planner at their own common step."""
    out = _figure(rel, ablation.get("figure"), caption)
    out += [
        "Each variant against the thesis planner at the largest step both reached; IQM over "
        "seeds of the last-10-episode mean return with its 95% bootstrap interval; the step at "
        "which the variant's IQM curve first reaches the thesis planner's best, every real step "
        "counted, with its ratio to the thesis planner's step (below 1: fewer steps).",
        "",
        "| variant | compared at | variant | thesis planner | variant vs thesis "
        "| first step at the thesis' best (ratio) | seeds |",
        "|---|---|---|---|---|---|---|",
    ]
    partial: dict[str, int] = {}
    for name, cmp in ablation["variants"].items():
        if not cmp.get("complete"):
            continue
        row = next(r for r in cmp["tables"]["all_steps"]["rows"] if r["label"] == name)
        ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2f}"
        reached = "never" if row["step"] is None else f"{row['step']:,} ({ratio})"
        out.append(
            f"| {name} | {cmp['common_step']:,} | {_ci(cmp['intervals'][name])} | "
            f"{_ci(cmp['intervals']['thesis'])} | {cmp['versus_reference'].get(name, '-')} | "
            f"{reached} | {', '.join(cmp['runs'][name])} |"
        )
        partial.update(cmp.get("partial_runs", {}))
    out.append("")
    stats = {
        name: cmp["planner"]
        for name, cmp in ablation["variants"].items()
        if cmp.get("complete") and cmp.get("planner")
    }
    if stats:
        out += [
            "Planner statistics over training (each run's mean up to the compared step, IQM "
            "over seeds): the effective horizon is the mean number of trusted imagined steps per "
            "candidate, the disagreement the members' mean normalised-delta standard deviation.",
            "",
            "| variant | effective horizon | disagreement |",
            "|---|---|---|",
        ]
        for name, st in stats.items():
            h, d = st.get("effective_horizon"), st.get("disagreement")
            out.append(f"| {name} | {_ci(h, 1)} | {_ci(d, 3)} |")
        out.append("")
    if partial:
        parts = ", ".join(f"{k} stopped at {v:,}" for k, v in sorted(partial.items()))
        out += [f"Partial runs (interrupted before their budget): {parts}.", ""]
    return out


def _refits_md(refits: Mapping[str, Any]) -> list[str]:
    """Tables 8 and 9 at every refit of each model-based configuration."""
    out: list[str] = []
    for method, table in refits.items():
        if not table["rows"]:
            continue
        out += [
            f"World model of the {method} runs (h = 10, default reward) at each refit, open loop "
            "(tables 8 and 9): on the real transitions the policy collected after the fit "
            "(`policy`, scored by the run before its next refit) and on fresh random-policy "
            "episodes (`random`, `recipes/evaluate_fits.py`); IQM over seeds with the 95% "
            "bootstrap interval (with fewer than three seeds, each seed's value); the thesis' "
            "numbers are for a model fitted on random data:",
            "",
            "| fitted on (transitions) | held-out data | h | x-position MSE (m^2) | thesis "
            "table 8 | reward MSE | thesis table 9 |",
            "|---|---|---|---|---|---|---|",
        ]
        for row in table["rows"]:
            out.append(
                f"| {row['transitions']:,} | {row['source']} | {row['horizon']} | "
                f"{_per_seed_or_ci(row['x_mse'], 4)} | {_fmt(row['thesis_x_mse'], 4)} | "
                f"{_per_seed_or_ci(row['reward_mse'], 4)} | {_fmt(row['thesis_reward_mse'], 4)} |"
            )
        out.append("")
    return out


def _section(name: str, analysis: Mapping[str, Any], rel: str) -> list[str]:
    out = [f"## Budget `{name}`", ""]
    runs = analysis["runs"]
    out += [
        "### Runs",
        "",
        "| run | steps reached / budget | random-data steps | last-10 mean return "
        "| eval return | wall hours (work kept) | model-refit hours | commit | machine |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        done = "" if r["complete"] else " (partial)"
        hours = "-" if r["seconds"] is None else f"{r['seconds'] / 3600:.2f}"
        refits = f"{r.get('refit_seconds', 0.0) / 3600:.2f}" if r.get("refit_seconds") else "-"
        m = r.get("machine") or {}
        machine = f"{m['cpu_count']} CPUs, Python {m['python']}, torch {m['torch']}" if m else "-"
        if m and m.get("cpu"):
            machine = f"{m['cpu']} ({m.get('cpu_capability', '?')}), {machine}"
        out.append(
            f"| {r['name']} | {r['last_step']:,} / {r['total_steps']:,}{done} | "
            f"{r['random_steps']:,} | {_fmt(r['last10_mean_return'])} | "
            f"{_fmt(r['final_eval_return'])} | {hours} | {refits} | `{r.get('commit', '-')[:7]}` | "
            f"{machine} |"
        )
    if analysis.get("superseded_runs"):
        names = ", ".join(
            f"{s['name']} ({s['last_step']:,} steps)" for s in analysis["superseded_runs"]
        )
        out += [
            "",
            "Runs found more than once (an interrupted copy beside a longer one) count once, "
            f"the longest; left out: {names}.",
        ]
    out.append("")
    out += ["### Experiment 1: planning horizon (figure 8)", ""]
    out += _comparison_md(analysis["exp1"], rel, "PPO-MPC with h = 5, 10, 25", THESIS["exp1"])
    hm = analysis.get("horizon_mse")
    if hm and hm["rows"]:
        out += [
            "World-model open-loop errors (tables 8 and 9), model fitted on the random-policy "
            f"data, evaluated on held-out random episodes; IQM over {len(hm['folders'])} "
            "seeds with 95% bootstrap interval:",
            "",
            "| h | x-position MSE (m^2) | thesis table 8 | reward MSE | thesis table 9 |",
            "|---|---|---|---|---|",
        ]
        for row in hm["rows"]:
            out.append(
                f"| {row['horizon']} | {_ci(row['x_mse'], 4)} | {_fmt(row['thesis_x_mse'], 4)} | "
                f"{_ci(row['reward_mse'], 4)} | {_fmt(row['thesis_reward_mse'], 4)} |"
            )
        out.append("")
        figures = hm.get("figures", {})
        out += _figure(rel, figures.get("x"), "open-loop x-position predictions (figure 9)")
        out += _figure(rel, figures.get("reward"), "open-loop reward predictions (figure 10)")
    out += _refits_md(analysis.get("refits") or {})
    out += ["### Experiment 2: PPO vs MPC vs PPO-MPC (figures 11a/11b, table 10)", ""]
    table10 = "; ".join(f"{a}: {b} at {c}" for a, b, c in THESIS["table10"])
    out += _comparison_md(
        analysis["exp2"],
        rel,
        "Default reward, planning phase",
        f"table 10 — {table10}; ratio PPO-MPC / PPO = 274,432 / 393,216 = 0.70 (steps without the "
        "random-data steps).",
    )
    ft = analysis["exp2"].get("finetune", {})
    if ft.get("complete"):
        out += ["Fine-tuning continuation (figure 11b):", ""]
        out += _comparison_md(ft, rel, "fine-tuning", THESIS["finetune"])
        out += _figure(rel, analysis["exp2"].get("finetune_figure"), "PPO vs fine-tuned PPO-MPC")
    else:
        out += [f"Fine-tuning continuation: not run at this budget ({ft.get('why', '')}).", ""]
    out += ["### Experiment 3: rewards (figures 12-16, 18-21)", ""]
    for reward, cmp in analysis["exp3"].items():
        out += [f"#### {reward}", ""]
        out += _comparison_md(cmp, rel, f"{reward} reward, planning phase", None)
    out += [f"Thesis: {THESIS['exp3']}", ""]
    out += _figure(
        rel, analysis.get("log_std_figure"), "PPO-MPC policy log-std per reward (figure 19)"
    )
    gait = analysis.get("gait") or {}
    if gait.get("metrics"):
        out += [
            "Gait of one PPO-MPC policy per reward (the run named), 60 deterministic steps "
            "(equation 20, figures 14-16):",
            "",
            "| reward | policy (run, real step) | sum of mean abs joint power (W) "
            "| torso height std (m) | distance in 60 steps (m) |",
            "|---|---|---|---|---|",
        ]
        for label, m in gait["metrics"].items():
            p = gait["policies"][label]
            run = f"{p['run']}, " if p.get("run") else ""
            out.append(
                f"| {label} | {run}{p['real_steps']:,} | {m['total_abs_power_W']:.2f} | "
                f"{m['height_std_m']:.4f} | {m['distance_m']:.2f} |"
            )
        out += [
            "",
            f"Steadiest: {gait['steadiest']}; least power: {gait['least_power']}; furthest: "
            f"{gait['furthest']}.",
            "",
        ]
        out += _figure(rel, gait.get("figure"), "power per joint, torso height, torso x")
        for label, p in gait["policies"].items():
            out += _figure(
                rel, p.get("frames"), f"gait frames, {label} reward (figures 18, 20, 21)"
            )
            if p.get("clip"):
                out += [f"[Video: the {label} policy]({rel}/{p['clip']})", ""]
    out += ["### Experiment 4: SAC vs SAC-MPC (figure 17)", ""]
    out += _comparison_md(analysis["exp4"], rel, "SAC vs SAC-MPC", THESIS["exp4"])
    sb3 = analysis.get("sb3") or {}
    if any(c.get("complete") for c in sb3.values()):
        out += [
            "### Our baselines vs Stable-Baselines3",
            "",
            "The same settings (`configs/algo`), budgets and seeds through Stable-Baselines3 "
            "(`recipes/sb3_reference.py`); their curves are also on the experiment 2 and 4 "
            "figures. Reference: SB3; a ratio below 1 means ours reached SB3's best in fewer "
            "real steps.",
            "",
        ]
        for algo, cmp in sb3.items():
            if cmp.get("complete"):
                out += [f"#### {algo}", ""]
                out += _comparison_md(cmp, rel, f"{algo} vs Stable-Baselines3 {algo}", None)
    if analysis.get("ablation"):
        out += ["### Beyond the thesis: planner and model variants", ""]
        for method, abl in analysis["ablation"].items():
            out += [f"#### {method}", ""]
            out += _ablation_md(abl, rel, f"{method}: thesis planner vs variants")
    out += [
        "### Research questions",
        "",
        "| question | thesis | ours | evidence |",
        "|---|---|---|---|",
    ]
    for q in ("Q1", "Q2", "Q3", "Q4"):
        v = analysis["verdicts"][q]
        why = v.get("why", "")
        if q == "Q3":
            why = "; ".join(f"{k}: {p['verdict']} ({p['why']})" for k, p in v["per_reward"].items())
            g = v.get("gait") or {}
            if any(g.values()):
                why += f"; gait: steadiest {g['steadiest']}, least power {g['least_power']}"
        verdict = f"**{v['verdict']}**"
        if v.get("finetune_verdict"):
            verdict = (
                f"planning: **{v['verdict']}**; after fine-tuning: **{v['finetune_verdict']}**"
            )
        out.append(f"| {q} | {THESIS[q]} | {verdict} | {why} |")
    out.append("")
    return out


def _read_analysis(folder: Path) -> dict:
    """The ``analysis.json`` of an analysed folder; names the file when it is missing or bad."""
    file = folder / "analysis.json"
    if not file.is_file():
        raise FileNotFoundError(
            f"no analysis.json in {str(folder)!r}; run recipes/analyze.py first"
        )
    try:
        analysis = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{str(file)!r} is not valid JSON ({err})") from err
    if not isinstance(analysis, dict):
        raise ValueError(f"{str(file)!r} holds a {type(analysis).__name__}, expected an object")
    return analysis


def write_report(
    analyses: Mapping[str, str | Path],
    path: str | Path,
    *,
    notes: str | Path | None = None,
    commands: Sequence[str] = (),
    appendices: Sequence[str | Path] = (),
    version: str = "",
    commit: str = "",
) -> str:
    """Writes the Markdown report of one or more analysed budgets.

    Args:
        analyses: ``{budget name: folder holding analysis.json and its figures}``.
        path: the Markdown file to write (figures are linked relative to it).

    Keyword Args:
        notes: a Markdown file included after the header (the authors' discussion: where and
            why results agree or disagree with the thesis, what ran where).
        commands: the commands that produced the runs, listed in the report.
        appendices: Markdown files appended after the budgets' sections, in order (studies
            beyond the thesis, each written by its own script from its own runs).
        version: package version to state.
        commit: git commit to state.

    Returns:
        The report text.

    Raises:
        FileNotFoundError: when ``notes`` or an appendix is not a readable file, or an
            analysis folder lacks its ``analysis.json``.
        ValueError: when ``path`` cannot be written, or an ``analysis.json`` is not valid
            JSON (the file is named); all checked before anything is written.

    Examples:
        >>> from torchrl_mbmf.analysis.report import write_report
        >>> text = write_report({"short": "results/short"}, "results/REPORT.md")  # doctest: +SKIP
    """
    path = check_output_path(path, "path", folder=False)
    notes_text = None if notes is None else check_input_file(notes, "notes").read_text()
    appendix_texts = [check_input_file(a, "appendices").read_text() for a in appendices]
    loaded = {name: _read_analysis(Path(folder)) for name, folder in analyses.items()}
    lines = [
        "# torchrl_mbmf: experiments of the thesis, reproduced",
        "",
        f"Package version {version or '-'}, git commit `{commit or '-'}`. Generated by "
        "`recipes/report.py` from the analyses of `recipes/analyze.py`; every number below "
        "comes from the run folders under `results/*/runs`.",
        "",
        "Conventions: returns are the mean of the last 10 training episodes, aggregated over "
        "seeds with the interquartile mean (IQM) and a 95% percentile-bootstrap interval; "
        "unless a table says otherwise, step counts include every real environment step, the "
        "random-policy steps that fit the first world model among them. With three seeds or "
        "fewer the IQM trims nothing (it is the mean) and the bootstrap interval is the range "
        "of the seeds (3 seeds have 10 distinct resamples): two configurations are called "
        "`higher`/`lower` only when every seed of one is above every seed of the other, which "
        "two identical methods show one time in 20 (3 against 3 seeds, one direction).",
        "",
    ]
    if notes_text is not None:
        lines += [notes_text.strip(), ""]
    if commands:
        lines += ["## Commands", "", "```bash", *commands, "```", ""]
    for name, folder in analyses.items():
        rel = os.path.relpath(Path(folder), path.parent)
        lines += _section(name, loaded[name], rel)
    for appendix in appendix_texts:
        lines += [appendix.strip(), ""]
    text = "\n".join(lines).rstrip() + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


__all__ = ["write_report"]
