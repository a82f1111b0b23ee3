"""Run-folder analysis: curves over seeds, the PPO-maximum table, verdicts, report recipes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from torchrl_mbmf.analysis.experiments import analyze_experiments
from torchrl_mbmf.analysis.report import write_report
from torchrl_mbmf.analysis.runs import aggregate_curve, load_runs, ppo_maximum_table

ROOT = Path(__file__).resolve().parents[2]


def make_run(
    root: Path,
    method: str,
    seed: int,
    values: list[float],
    *,
    step: int = 1000,
    reward: str = "default",
    horizon: int = 10,
    random_steps: int = 0,
    total_steps: int | None = None,
    spread: float = 10.0,
) -> Path:
    """A run folder whose last-10 mean return takes ``values`` at steps ``step, 2 step, ...``."""
    name = f"Env__{method}__{reward}__h{horizon}__seed{seed}"
    run = root / name
    scalars = run / "logs" / "scalars" / "train"
    scalars.mkdir(parents=True)
    steps = [random_steps + step * (i + 1) for i in range(len(values))]
    total = total_steps or steps[-1]
    config = {
        "method": method,
        "seed": seed,
        "reward": {"name": reward},
        "planner": {"horizon": horizon},
        "total_steps": total,
        "planning_updates": 1000,
        "world_model": {"random_steps": random_steps},
        "ppo": {"frames_per_batch": 1000},
    }
    (run / "config.yaml").write_text(yaml.safe_dump(config))

    def write(name: str, vals) -> None:
        rows = "".join(f"{s},{v}\n" for s, v in zip(steps, vals, strict=True))
        (scalars / f"{name}.csv").write_text(rows)

    write("return_last10_mean", values)
    write("return_last10_min", [v - spread for v in values])
    write("return_last10_max", [v + spread for v in values])
    write("episode_return", values)
    write("policy_log_std", [-0.01 * i for i in range(len(values))])
    if steps[-1] >= total:
        summary = {"real_steps": steps[-1], "random_steps": random_steps}
        (run / "summary.json").write_text(json.dumps(summary))
    return run


def test_aggregate_curve_iqm_interval_and_band(tmp_path):
    for seed, level in enumerate([0.0, 1.0, 2.0, 100.0]):
        make_run(tmp_path, "ppo", seed, [level, level])
    curve = aggregate_curve(load_runs(tmp_path), grid=[1000, 2000])
    # IQM of {0, 1, 2, 100}: the middle two.
    np.testing.assert_allclose(curve.iqm, [1.5, 1.5])
    assert np.all(curve.low <= curve.iqm) and np.all(curve.iqm <= curve.high)
    np.testing.assert_allclose(curve.band_min, [-10.0, -10.0])
    np.testing.assert_allclose(curve.band_max, [110.0, 110.0])


def test_interrupted_seed_stops_contributing_after_its_last_step(tmp_path):
    make_run(tmp_path, "ppo", 0, [1.0, 1.0, 1.0])
    make_run(tmp_path, "ppo", 1, [5.0], total_steps=3000)
    runs = load_runs(tmp_path)
    assert [r.complete for r in runs] == [True, False]
    assert runs[1].last_step == 1000
    curve = aggregate_curve(runs, grid=[1000, 3000])
    np.testing.assert_allclose(curve.iqm, [3.0, 1.0])
    np.testing.assert_allclose(curve.per_seed[1], [5.0, np.nan])


@pytest.mark.parametrize(
    ("method", "expected"),
    [("mpc", 300), ("ppo_mpc", 300), ("sac_mpc", 300), ("sac_mbpo", 300), ("ppo", 0), ("sac", 0)],
)
def test_an_unfinished_run_counts_the_random_steps_of_its_world_model(tmp_path, method, expected):
    # without a summary the random steps come from the config, for the methods that fit a model
    make_run(tmp_path, method, 0, [1.0], random_steps=300, total_steps=5000)
    (run,) = load_runs(tmp_path)
    assert not run.complete and run.random_steps == expected


def test_ppo_maximum_table_with_and_without_random_steps(tmp_path):
    # PPO peaks at 40 at step 4000. PPO-MPC (500 random steps, then 200-step episodes) passes
    # 40 with its 11th episode of its own policy, at 500 + 11 * 200 = 2700 real steps.
    make_run(tmp_path, "ppo", 0, [10.0, 20.0, 30.0, 40.0])
    make_run(tmp_path, "ppo_mpc", 0, [20.0] * 10 + [45.0, 50.0], step=200, random_steps=500)
    runs = load_runs(tmp_path)
    groups = {r.method: [r] for r in runs}
    table = ppo_maximum_table(groups, "ppo", budget=4000, points=40)
    rows = {r["label"]: r for r in table["rows"]}
    assert table["threshold"] == 40.0 and table["grid_spacing"] == 100.0
    assert rows["ppo"]["step"] == 4000
    assert rows["ppo_mpc"]["step"] == 2700 and rows["ppo_mpc"]["ratio"] == 2700 / 4000
    table = ppo_maximum_table(groups, "ppo", budget=4000, exclude_random=True, points=40)
    rows = {r["label"]: r for r in table["rows"]}
    assert rows["ppo_mpc"]["step"] == 2200 and rows["ppo_mpc"]["ratio"] == 2200 / 4000
    with pytest.raises(KeyError, match="sac"):
        ppo_maximum_table(groups, "sac")


def test_ppo_maximum_table_reads_every_run_up_to_the_budget_and_needs_every_seed(tmp_path):
    # Without random steps, PPO-MPC's shifted curve would run 1000 steps past the budget; it
    # reaches PPO's best (30) only there, so within the budget it never does.
    make_run(tmp_path, "ppo", 0, [10.0, 20.0, 30.0])
    for seed in (0, 1):
        make_run(tmp_path, "ppo_mpc", seed, [0.0] * 11 + [50.0], step=250, random_steps=1000)
    groups = {}
    for r in load_runs(tmp_path):
        groups.setdefault(r.method, []).append(r)
    table = ppo_maximum_table(groups, "ppo", budget=3000, exclude_random=True, points=30)
    rows = {r["label"]: r for r in table["rows"]}
    assert rows["ppo_mpc"]["step"] is None
    # one of two seeds stops early: the aggregate ends there instead of becoming that seed alone
    short = load_runs(tmp_path)
    curve = aggregate_curve(
        [r for r in short if r.method == "ppo_mpc"], grid=[3500, 4000], min_seeds=2
    )
    np.testing.assert_allclose(curve.iqm, [0.0, 50.0])
    (tmp_path / "Env__ppo_mpc__default__h10__seed1/logs/scalars/train").joinpath(
        "return_last10_mean.csv"
    ).write_text("1250,0.0\n3500,0.0\n")
    curve = aggregate_curve(
        [r for r in load_runs(tmp_path) if r.method == "ppo_mpc"], grid=[3500, 4000], min_seeds=2
    )
    np.testing.assert_allclose(curve.iqm, [0.0, np.nan])
    with pytest.raises(ValueError, match="min_seeds must be an integer >= 1, got 0"):
        aggregate_curve(short, grid=[1000], min_seeds=0)


def test_ppo_maximum_table_calibrates_the_ratio_against_the_reference_itself(tmp_path):
    for seed, noise in enumerate([0.0, 3.0, -2.0]):
        make_run(tmp_path, "ppo", seed, [10.0, 20.0 + noise, 25.0 - noise, 30.0 + noise])
        make_run(tmp_path, "ppo_mpc", seed, [0.0] * 10 + [-280.0], step=100, random_steps=50)
        csv = tmp_path / f"Env__ppo_mpc__default__h10__seed{seed}/logs/scalars/train"
        rows = (csv / "episode_return.csv").read_text()
        (csv / "episode_return.csv").write_text("25,-250.0\n50,-300.0\n" + rows)
    groups = {}
    for r in load_runs(tmp_path):
        groups.setdefault(r.method, []).append(r)
    table = ppo_maximum_table(groups, "ppo", points=8)
    self_ci = table["reference_self"]
    assert set(self_ci) == {"low", "high", "reached"} and 0 < self_ci["reached"] <= 1
    assert self_ci["low"] <= 1.0
    assert table["random_policy_return"] == pytest.approx(-275.0)


@pytest.mark.parametrize("better", [True, False])
def test_verdicts_follow_the_intervals(tmp_path, better):
    runs = tmp_path / "runs"
    good, bad = np.linspace(0, 100, 8), np.linspace(0, 40, 8)
    for seed in range(3):
        jitter = seed * 1.0
        make_run(runs, "ppo", seed, list(bad + jitter))
        make_run(runs, "mpc", seed, list(bad / 2 + jitter), random_steps=0)
        make_run(runs, "ppo_mpc", seed, list((good if better else bad / 4) + jitter))
        make_run(runs, "sac", seed, list(bad + jitter))
        make_run(runs, "sac_mpc", seed, list((good if better else bad / 4) + jitter))
    out = tmp_path / "out"
    analysis = analyze_experiments([runs], out, gait=False)
    verdicts = {q: v["verdict"] for q, v in analysis["verdicts"].items()}
    expected = "supported" if better else "not supported"
    assert verdicts["Q1"] == verdicts["Q2"] == verdicts["Q4"] == expected
    assert verdicts["Q3"] == "not run"  # no HeadPen / ShinPen runs
    assert analysis["exp2"]["common_step"] == 8000
    assert (out / "exp2_default_planning.png").exists() and (out / "exp4_sac.png").exists()
    assert (out / "exp3_log_std.png").exists()
    assert json.loads((out / "analysis.json").read_text())["verdicts"]["Q1"]["verdict"] == expected
    copied = sorted(p.name for p in (out / "runs" / "Env__ppo__default__h10__seed0").rglob("*"))
    assert "config.yaml" in copied and "return_last10_mean.csv" in copied


def test_analyze_and_report_recipes(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(2):
        make_run(runs, "ppo", seed, [1.0, 2.0, 3.0 + seed])
        make_run(runs, "ppo_mpc", seed, [2.0, 4.0, 6.0 + seed], random_steps=100)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}

    def recipe(name: str, *overrides: str) -> None:
        proc = subprocess.run(
            [sys.executable, str(ROOT / "recipes" / f"{name}.py"), *overrides],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]

    recipe("analyze", f"runs=[{runs}]", f"out_dir={tmp_path / 'short'}", "world_models=[]")
    notes = tmp_path / "NOTES.md"
    notes.write_text("Our discussion.")
    appendix = tmp_path / "beyond.md"
    appendix.write_text("## Beyond the thesis\n\nA study of our own.")
    recipe(
        "report",
        f"analyses=[{tmp_path / 'short'}]",
        f"out={tmp_path / 'REPORT.md'}",
        f"notes={notes}",
        f"appendices=[{appendix}]",
    )
    report = (tmp_path / "REPORT.md").read_text()
    assert "Our discussion." in report and "## Budget `short`" in report
    assert report.endswith("## Beyond the thesis\n\nA study of our own.\n")
    assert "| Q1 |" in report and "Env__ppo_mpc__default__h10__seed1" in report
    assert "(short/exp2_default_planning.png)" in report


def test_report_refuses_a_missing_analysis(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "report.py"), f"analyses=[{tmp_path}]"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0 and f"no analysis.json for ['{tmp_path}']" in proc.stderr


def test_a_run_found_under_two_roots_counts_once_the_longest(tmp_path):
    make_run(tmp_path / "a", "ppo", 0, [1.0, 2.0], total_steps=5000)  # interrupted copy
    make_run(tmp_path / "b", "ppo", 0, [1.0, 2.0, 3.0, 4.0, 5.0])  # finished
    runs = load_runs([tmp_path / "a", tmp_path / "b"])
    assert len(runs) == 1 and runs[0].complete and runs[0].last_step == 5000
    assert len(load_runs([tmp_path / "a", tmp_path / "b"], dedupe=False)) == 2
    analysis = analyze_experiments([tmp_path / "a", tmp_path / "b"], tmp_path / "out", gait=False)
    assert analysis["superseded_runs"] == [
        {"name": "Env__ppo__default__h10__seed0", "last_step": 2000, "complete": False}
    ]


def test_ablation_never_reads_a_single_seed_as_a_difference(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo_mpc", seed, [1.0, 2.0, 3.0 + seed])
    # one seed of the CEM variant, far above the thesis planner's interval
    cem = make_run(tmp_path / "cem", "ppo_mpc", 0, [10.0, 20.0, 30.0])
    cem = cem.rename(runs / cem.name.replace("__seed0", "__cem__seed0"))
    config = yaml.safe_load((cem / "config.yaml").read_text())
    config["planner"]["refinement"] = "cem"
    (cem / "config.yaml").write_text(yaml.safe_dump(config))
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False)
    cem = analysis["ablation"]["ppo_mpc"]["variants"]["cem"]
    assert set(cem["intervals"]) == {"thesis", "cem"}
    assert cem["intervals"]["cem"]["n"] == 1
    assert cem["versus_reference"] == {"cem": "one seed"}


def test_each_ablation_variant_is_compared_at_its_own_common_step(tmp_path):
    runs = tmp_path / "runs"

    def variant(name: str, seed: int, values: list[float], **planner) -> None:
        run = make_run(tmp_path / name, "ppo_mpc", seed, values, total_steps=4000)
        run = run.rename(runs / run.name.replace("__seed", f"__{name}__seed"))
        config = yaml.safe_load((run / "config.yaml").read_text())
        config["planner"].update(planner)
        (run / "config.yaml").write_text(yaml.safe_dump(config))

    for seed in range(3):
        make_run(runs, "ppo_mpc", seed, [1.0, 2.0, 3.0, 4.0 + seed])
        variant("cem", seed, [5.0, 6.0, 7.0, 9.0 + seed], refinement="cem")
        # the terminal-value variant stopped after 2 of its 4 evaluations
        variant("value", seed, [0.0, 1.0 + seed], terminal_value=True)
    for seed in range(3):  # the CEM runs log an effective horizon: 4 + seed, then 6 + seed
        planner = runs / f"Env__ppo_mpc__default__h10__cem__seed{seed}" / "logs/scalars/planner"
        planner.mkdir()
        (planner / "effective_horizon.csv").write_text(f"1000,{4 + seed}\n3000,{6 + seed}\n")
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False)
    variants = analysis["ablation"]["ppo_mpc"]["variants"]
    assert variants["cem"]["planner"]["effective_horizon"]["values"] == [5.0, 6.0, 7.0]
    assert variants["value"]["planner"] == {}
    assert variants["cem"]["common_step"] == 4000
    assert variants["cem"]["versus_reference"] == {"cem": "higher"}
    assert variants["cem"]["intervals"]["thesis"]["values"] == [4.0, 5.0, 6.0]
    assert variants["value"]["common_step"] == 2000
    assert variants["value"]["intervals"]["thesis"]["values"] == [2.0, 2.0, 2.0]
    assert sorted(variants["value"]["partial_runs"]) == [
        f"Env__ppo_mpc__default__h10__value__seed{s}" for s in range(3)
    ]
    report = write_report({"short": tmp_path / "out"}, tmp_path / "REPORT.md")
    assert "| cem | 4,000 |" in report and "| value | 2,000 |" in report
    assert "| cem | 6.0 [5.0, 7.0] (n=3) | - |" in report


def test_sb3_references_are_compared_with_ours_and_kept_out_of_the_thesis_tables(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo", seed, [0.0, 10.0, 20.0 + seed])
        make_run(runs, "ppo_mpc", seed, [5.0, 15.0, 25.0 + seed])
        make_run(runs, "sb3_ppo", seed, [0.0, 40.0, 60.0 + seed], horizon=0)
        make_run(runs, "sac", seed, [0.0, 50.0, 90.0 + seed])
        make_run(runs, "sac_mpc", seed, [0.0, 50.0, 95.0 + seed])
        make_run(runs, "sb3_sac", seed, [0.0, 50.0, 91.0 + seed], horizon=0)
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False)
    ppo = analysis["sb3"]["ppo"]
    assert ppo["complete"] and ppo["versus_reference"] == {"ppo": "lower"}
    (row,) = [r for r in ppo["tables"]["all_steps"]["rows"] if r["label"] == "ppo"]
    assert row["step"] is None  # our PPO never reached SB3's best here
    assert analysis["sb3"]["sac"]["versus_reference"] == {"sac": "overlapping"}
    # the thesis' comparisons hold only the thesis' methods
    assert sorted(analysis["exp2"]["intervals"]) == ["ppo", "ppo_mpc"]
    assert sorted(analysis["exp4"]["intervals"]) == ["sac", "sac_mpc"]
    text = write_report({"thesis": tmp_path / "out"}, tmp_path / "REPORT.md")
    assert "### Our baselines vs Stable-Baselines3" in text
    assert "| sb3_sac | " in text


def _loop_ratio_interval(reference, candidate, grid, n_resamples, seed):
    """ratio_interval written out one resample at a time with scipy's trim_mean."""
    from scipy.stats import trim_mean

    rng = np.random.default_rng(seed)
    ref_idx = rng.integers(0, len(reference), (n_resamples, len(reference)))
    cand_idx = rng.integers(0, len(candidate), (n_resamples, len(candidate)))
    ratios = []
    for b in range(n_resamples):
        ref = trim_mean(reference[ref_idx[b]], 0.25, axis=0)
        cand = trim_mean(candidate[cand_idx[b]], 0.25, axis=0)
        threshold = ref.max()
        ref_step = grid[np.nonzero(ref >= threshold)[0][0]]
        hit = np.nonzero(cand >= threshold)[0]
        ratios.append(grid[hit[0]] / ref_step if hit.size else np.inf)
    return np.percentile(ratios, [2.5, 97.5], method="lower"), np.isfinite(ratios).mean()


@pytest.mark.parametrize("seeds", [(3, 3), (4, 2), (5, 3)])
def test_ratio_interval_equals_a_resample_by_resample_loop(seeds):
    from torchrl_mbmf.analysis.runs import ratio_interval

    rng = np.random.default_rng(1)
    grid = np.arange(1, 41) * 1000
    trend = np.linspace(0, 100, grid.size)
    reference = trend + rng.normal(0, 15, (seeds[0], grid.size))
    candidate = 1.3 * trend + rng.normal(0, 25, (seeds[1], grid.size))
    out = ratio_interval(reference, candidate, grid, n_resamples=300, seed=4)
    (low, high), reached = _loop_ratio_interval(reference, candidate, grid, 300, 4)
    assert (out["low"], out["high"]) == (low, high)
    assert out["reached"] == pytest.approx(reached)


def test_ratio_interval_of_a_clearly_faster_and_a_never_reaching_candidate():
    from torchrl_mbmf.analysis.runs import ratio_interval

    grid = np.arange(1, 11) * 100
    reference = np.stack([np.linspace(0, 10, 10) + s for s in range(3)])
    faster = np.minimum(reference * 3, 50.0)
    out = ratio_interval(reference, faster, grid)
    assert out["high"] < 1 and out["reached"] == 1.0
    never = reference - 100
    out = ratio_interval(reference, never, grid)
    assert out == {"low": np.inf, "high": np.inf, "reached": 0.0}
    with pytest.raises(ValueError, match=r"candidate curves have shape \(10,\)"):
        ratio_interval(reference, never[0], grid)


def test_ppo_maximum_table_gives_each_ratio_its_interval(tmp_path):
    for seed in range(3):
        make_run(tmp_path, "ppo", seed, [10.0 + seed, 20.0, 30.0, 40.0 + seed])
        make_run(tmp_path, "ppo_mpc", seed, [20.0, 45.0 + seed, 50.0, 50.0])
    groups = {}
    for r in load_runs(tmp_path):
        groups.setdefault(r.method, []).append(r)
    rows = {r["label"]: r for r in ppo_maximum_table(groups, "ppo", points=8)["rows"]}
    assert rows["ppo"]["ratio_ci"] is None
    ci = rows["ppo_mpc"]["ratio_ci"]
    assert ci["low"] <= rows["ppo_mpc"]["ratio"] <= ci["high"] < 1


def test_wall_seconds_add_each_segment_up_to_the_step_the_next_resumed_from(tmp_path):
    run_dir = make_run(tmp_path, "ppo_mpc", 0, [1.0, 2.0, 3.0, 4.0], random_steps=0)
    timing = run_dir / "logs" / "scalars" / "time"
    timing.mkdir()
    # segment 1 logs 1000 and 2000 at 10 steps/s; it resumed from 1000 (its row at 2000 was
    # redone); segment 2 logs 2000..4000 at 20 steps/s since its start at 1000
    (timing / "steps_per_s.csv").write_text("1000,10\n2000,20\n3000,20\n4000,20\n")
    (timing / "model_fit_s.csv").write_text("1000,7.5\n3000,2.5\n")
    resume = [{"event": "resume", "real_steps": 1000, "checkpoint": "checkpoint-1000"}]
    (run_dir / "resume_log.json").write_text(json.dumps(resume))
    (run,) = load_runs(tmp_path)
    assert run.wall_seconds == pytest.approx(1000 / 10 + 3000 / 20)
    assert run.refit_seconds == 10.0
    (run_dir / "resume_log.json").unlink()
    (run,) = load_runs(tmp_path)
    assert run.wall_seconds == pytest.approx(4000 / 20)


def test_refit_errors_pair_each_held_out_score_with_the_fit_it_scored(tmp_path):
    from torchrl_mbmf.analysis.refits import refit_errors

    for seed in range(2):
        run_dir = make_run(tmp_path, "ppo_mpc", seed, [1.0, 2.0, 3.0], random_steps=100)
        model = run_dir / "logs" / "scalars" / "model"
        model.mkdir()
        (model / "transitions.csv").write_text("100,100\n2100,2100\n")
        (model / "heldout_x_mse_h5.csv").write_text(f"2100,{1.0 + seed}\n")
        (model / "heldout_reward_mse_h5.csv").write_text(f"2100,{10.0 + seed}\n")
        fits = [
            {"transitions": t, "errors": [{"horizon": 5, "x_mse": t / 100, "reward_mse": 0.5}]}
            for t in (100, 2100)
        ]
        (run_dir / "world_models").mkdir()
        (run_dir / "world_models" / "open_loop_errors.json").write_text(json.dumps({"fits": fits}))
    table = refit_errors(load_runs(tmp_path))
    rows = {(r["transitions"], r["source"]): r for r in table["rows"]}
    assert sorted(rows) == [(100, "policy"), (100, "random"), (2100, "random")]
    assert rows[(100, "policy")]["x_mse"]["values"] == [1.0, 2.0]
    assert rows[(100, "policy")]["reward_mse"]["iqm"] == 10.5
    assert rows[(2100, "random")]["x_mse"]["values"] == [21.0, 21.0]
    assert rows[(100, "random")]["thesis_x_mse"] == 2.359
    # a held-out score logged where no refit happened is an error, not a silent row
    (model / "heldout_x_mse_h5.csv").write_text("1500,1.0\n")
    (model / "heldout_reward_mse_h5.csv").write_text("1500,1.0\n")
    with pytest.raises(ValueError, match="step 1500 match no refit"):
        refit_errors(load_runs(tmp_path))


def test_fine_tuning_is_compared_after_the_switch_and_enters_q1(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo", seed, [10.0 * i + seed for i in range(1, 9)])
        # plans for 2 updates of 1000 steps after 1000 random steps, then fine-tunes to 8000
        path = make_run(
            runs, "ppo_mpc", seed, [15.0 * i + seed for i in range(1, 8)], random_steps=1000
        )
        config = yaml.safe_load((path / "config.yaml").read_text())
        config["planning_updates"] = 2
        (path / "config.yaml").write_text(yaml.safe_dump(config))
        # 100-step episodes: the last-10 window holds only its own policy's from 2000 on
        episodes = "".join(f"{s},0.0\n" for s in range(1100, 8001, 100))
        (path / "logs/scalars/train/episode_return.csv").write_text(episodes)
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    e2 = analysis["exp2"]
    assert e2["common_step"] == 3000  # the planning phase ends at the switch
    ft = e2["finetune"]
    assert ft["complete"] and ft["common_step"] == 8000
    rows = {r["label"]: r for r in ft["tables"]["all_steps"]["rows"]}
    # PPO's best is 82 (at 8000); fine-tuned PPO-MPC reaches it at 7000 (1000 + 6 x 1000)
    assert ft["tables"]["all_steps"]["threshold"] == pytest.approx(81.0, abs=1.0)
    assert rows["ppo_mpc"]["step"] == 7000
    assert (tmp_path / "out" / e2["finetune_figure"]).exists()
    q1 = analysis["verdicts"]["Q1"]
    assert "after fine-tuning" in q1["why"] and q1["finetune_verdict"] == "supported"


def test_a_comparison_held_short_by_an_unfinished_run_gives_no_verdict(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo", seed, [10.0 * i + seed for i in range(1, 9)])
        # seed 2 of PPO-MPC stopped at 2,000 of its 8,000 steps; it leads while it runs
        values = [30.0 * i + seed for i in range(1, 9 if seed < 2 else 3)]
        make_run(runs, "ppo_mpc", seed, values, total_steps=8000)
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    assert analysis["exp2"]["common_step"] == 2000
    assert analysis["exp2"]["cut_short"] == {"Env__ppo_mpc__default__h10__seed2": 2000}
    q1 = analysis["verdicts"]["Q1"]
    assert q1["verdict"] == "partial" and "2,000 of 8,000 real steps" in q1["why"]


def test_a_single_seed_is_never_a_verdict(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo", seed, [10.0 * i + seed for i in range(1, 9)])
    make_run(runs, "ppo_mpc", 0, [1.0] * 8)  # far below PPO, but one seed
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    assert analysis["verdicts"]["Q1"]["verdict"] == "inconclusive"


def test_a_verdict_waits_for_every_seed(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo", seed, [10.0 * i + seed for i in range(1, 9)])
    for seed in range(2):  # seed 2 of PPO-MPC has not run
        make_run(runs, "ppo_mpc", seed, [30.0 * i + seed for i in range(1, 9)])
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    q1 = analysis["verdicts"]["Q1"]
    assert q1["verdict"] == "partial" and q1["why"].startswith("2 of the 3 seeds")


def test_random_data_episodes_do_not_reach_the_ppo_maximum(tmp_path):
    # PPO's best is -250, below a random-policy episode's last-10 mean of the PPO-MPC run (-200,
    # logged at step 500 of its 1000 random-data steps); its window holds only its own episodes
    # from its 10th policy episode (1000 + 10 * 100) on, and passes -250 at 1000 + 11 * 100.
    make_run(tmp_path, "ppo", 0, [-300.0, -280.0, -260.0, -250.0])
    mpc = make_run(tmp_path, "ppo_mpc", 0, [-200.0] * 10 + [-240.0], step=100, random_steps=1000)
    train = mpc / "logs" / "scalars" / "train"
    for name in ("return_last10_mean.csv", "episode_return.csv"):
        (train / name).write_text("500,-200.0\n1000,-260.0\n" + (train / name).read_text())
    groups = {r.method: [r] for r in load_runs(tmp_path)}
    every = aggregate_curve(groups["ppo_mpc"], grid=[500, 1500, 2000, 2100])
    np.testing.assert_allclose(every.iqm, [-200.0, -200.0, -200.0, -240.0])
    own = aggregate_curve(groups["ppo_mpc"], grid=[500, 1500, 2000, 2100], policy_only=True)
    np.testing.assert_allclose(own.iqm, [np.nan, np.nan, -200.0, -240.0])
    for exclude_random, step in ((False, 2000), (True, 1000)):
        table = ppo_maximum_table(
            groups, "ppo", budget=4000, exclude_random=exclude_random, points=40
        )
        rows = {r["label"]: r for r in table["rows"]}
        assert table["threshold"] == -250.0
        assert rows["ppo_mpc"]["step"] == step, (exclude_random, rows["ppo_mpc"])
        assert rows["ppo_mpc"]["per_seed_steps"] == [step]
        assert table["random_policy_return"] == pytest.approx(-230.0)


@pytest.mark.parametrize(
    ("head_pen_better", "shin_pen_better", "expected"),
    [(False, True, "reward-sensitive"), (True, True, "robust")],
)
def test_q3_names_how_the_advantage_depends_on_the_reward(
    tmp_path, head_pen_better, shin_pen_better, expected
):
    runs = tmp_path / "runs"
    good, bad = np.linspace(0, 100, 8), np.linspace(0, 40, 8)
    better = {"default": True, "head_pen": head_pen_better, "shin_pen": shin_pen_better}
    for reward, wins in better.items():
        for seed in range(3):
            make_run(runs, "ppo", seed, list(bad + seed), reward=reward)
            mpc = good if wins else bad / 4
            make_run(runs, "ppo_mpc", seed, list(mpc + seed), reward=reward)
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    q3 = analysis["verdicts"]["Q3"]
    words = {k: p["verdict"] for k, p in q3["per_reward"].items()}
    assert words == {k: "supported" if v else "not supported" for k, v in better.items()}
    assert q3["verdict"] == expected


def test_q3_without_an_advantage_anywhere_is_not_the_thesis_answer(tmp_path):
    runs = tmp_path / "runs"
    bad = np.linspace(0, 40, 8)
    for reward in ("default", "head_pen", "shin_pen"):
        for seed in range(3):
            make_run(runs, "ppo", seed, list(bad + seed), reward=reward)
            make_run(runs, "ppo_mpc", seed, list(bad / 4 + seed), reward=reward)
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    assert analysis["verdicts"]["Q3"]["verdict"] == "no advantage"


def test_a_run_read_up_to_a_step_holds_its_last_value_until_then(tmp_path):
    # logged every 2048 steps: read up to 5000, the value of 4096 holds through 5000
    make_run(tmp_path, "ppo", 0, [1.0, 2.0, 3.0], step=2048)
    curve = aggregate_curve(load_runs(tmp_path), grid=[4096, 5000, 6144], until=5000)
    np.testing.assert_allclose(curve.iqm, [2.0, 2.0, np.nan])


def test_steps_interval_equals_a_resample_by_resample_loop():
    from scipy.stats import trim_mean

    from torchrl_mbmf.analysis.runs import steps_interval

    rng = np.random.default_rng(2)
    grid = np.arange(1, 41) * 1000
    curves = np.linspace(0, 100, grid.size) + rng.normal(0, 20, (3, grid.size))
    out = steps_interval(curves, grid, 60.0, n_resamples=300, seed=5)
    draw = np.random.default_rng(5).integers(0, 3, (300, 3))
    steps = []
    for picks in draw:
        iqm = np.array([trim_mean(col, 0.25) for col in curves[picks].T])
        hit = np.nonzero(iqm >= 60.0)[0]
        steps.append(grid[hit[0]] if hit.size else np.inf)
    low, high = np.percentile(steps, [2.5, 97.5], method="lower")
    assert (out["low"], out["high"]) == (low, high)
    assert out["reached"] == pytest.approx(np.isfinite(steps).mean())
    assert steps_interval(curves, grid, 1e6) == {"low": np.inf, "high": np.inf, "reached": 0.0}
    with pytest.raises(ValueError, match=r"curves have shape \(40,\)"):
        steps_interval(curves[0], grid, 60.0)


def test_fixed_threshold_table_reads_a_level_given_in_advance(tmp_path):
    from torchrl_mbmf.analysis.runs import fixed_threshold_table

    for seed in range(3):
        make_run(tmp_path, "ppo", seed, [10.0, 20.0, 30.0 + seed, 40.0])
        make_run(tmp_path, "ppo_mpc", seed, [20.0, 45.0 + seed, 50.0, 50.0])
    groups = {}
    for r in load_runs(tmp_path):
        groups.setdefault(r.method, []).append(r)
    t = fixed_threshold_table(groups, 45.0, source="a level", points=4)
    rows = {r["label"]: r for r in t["rows"]}
    # PPO's best (40) is below the level: never, in every resample
    assert rows["ppo"]["step"] is None and rows["ppo"]["step_ci"]["high"] == np.inf
    assert rows["ppo"]["seeds_reached"] == 0
    assert rows["ppo_mpc"]["step"] == 2000 and rows["ppo_mpc"]["per_seed_steps"] == [2000] * 3
    assert rows["ppo_mpc"]["step_ci"] == {"low": 2000.0, "high": 2000.0, "reached": 1.0}
    assert (t["threshold"], t["source"], t["budget"]) == (45.0, "a level", 4000)
    with pytest.raises(ValueError, match="threshold must be a finite return, got nan"):
        fixed_threshold_table(groups, float("nan"), source="x")


def test_the_planning_comparison_has_the_thesis_level_and_the_report_shows_it(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(3):
        make_run(runs, "ppo", seed, [300.0 * i + seed for i in range(1, 6)])
        make_run(runs, "ppo_mpc", seed, [400.0 * i + seed for i in range(1, 6)])
    analysis = analyze_experiments([runs], tmp_path / "out", gait=False, collect=False)
    fixed = analysis["exp2"]["fixed_tables"]
    assert fixed["thesis"]["threshold"] == 1247.0
    rows = {r["label"]: r for r in fixed["thesis"]["rows"]}
    # PPO: 301, 601, ..., 1501 reaches 1247 at 5000; PPO-MPC (401, 801, 1201, 1601) at 4000
    assert (rows["ppo"]["step"], rows["ppo_mpc"]["step"]) == (5000, 4000)
    ref = fixed["reference_at_step"]
    assert ref["threshold"] == pytest.approx(1501.0)
    assert "ppo's IQM return at 5,000" in ref["source"]
    text = write_report({"thesis": tmp_path / "out"}, tmp_path / "REPORT.md")
    assert "Real steps to a level fixed in advance" in text
    assert "| 1,247: the thesis' PPO maximum within its planning budget" in text


def test_a_resampled_curve_exists_only_where_all_its_seeds_have_a_value():
    from torchrl_mbmf.analysis.runs import ratio_interval, steps_interval

    grid = np.array([100, 200, 300])
    # seed 0 has no value at 200 (its last-10 window not yet its own policy's), the others
    # reach the level there; every seed has reached it at 300
    curves = np.array([[0.0, np.nan, 9.0], [0.0, 6.0, 9.0], [0.0, 6.0, 9.0], [0.0, 6.0, 9.0]])
    out = steps_interval(curves, grid, 5.0, n_resamples=4000)
    # the resamples holding seed 0 (68% of them) have no curve at 200: they reach it at 300
    assert (out["low"], out["high"], out["reached"]) == (200.0, 300.0, 1.0)
    # the reference's maximum, 6, at 200: the same resamples reach it only at 300 (ratio 1.5)
    reference = np.array([[0.0, 6.0, 6.0]] * 4)
    ci = ratio_interval(reference, curves, grid, n_resamples=4000)
    assert (ci["low"], ci["high"]) == (1.0, 1.5)


def _recipe_fails(tmp_path, name, *overrides):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / f"{name}.py"), *overrides],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert proc.returncode != 0
    return proc.stderr


def test_report_refuses_missing_notes_and_unwritable_out_before_any_work(tmp_path):
    analysis = tmp_path / "short"
    analysis.mkdir()
    (analysis / "analysis.json").write_text("{}")
    err = _recipe_fails(tmp_path, "report", f"analyses=[{analysis}]", "notes=/nonexistent.md")
    assert "notes='/nonexistent.md' is not a file" in err
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where a folder should be")
    out = blocker / "REPORT.md"
    err = _recipe_fails(
        tmp_path, "report", f"analyses=[{analysis}]", "notes=null", "appendices=[]", f"out={out}"
    )
    assert f"out={str(out)!r} cannot be written" in err
    (analysis / "analysis.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"analysis\.json' is not valid JSON"):
        write_report({"short": analysis}, tmp_path / "REPORT.md")
    assert not (tmp_path / "REPORT.md").exists()


def test_report_appends_appendices_in_order_and_refuses_a_missing_one_before_writing(tmp_path):
    analysis = tmp_path / "short"
    analysis.mkdir()
    (analysis / "analysis.json").write_text("{}")
    first, second = tmp_path / "a.md", tmp_path / "b.md"
    first.write_text("## Beyond A\n\nfirst study\n")
    second.write_text("## Beyond B\n\nsecond study\n\n")
    text = write_report({}, tmp_path / "REPORT.md", appendices=[first, second])
    assert text.index("Conventions:") < text.index("## Beyond A") < text.index("## Beyond B")
    assert text.endswith("first study\n\n## Beyond B\n\nsecond study\n")
    with pytest.raises(FileNotFoundError, match=r"appendices='.*missing\.md' is not a file"):
        write_report(
            {"short": analysis}, tmp_path / "OTHER.md", appendices=[tmp_path / "missing.md"]
        )
    assert not (tmp_path / "OTHER.md").exists()
    err = _recipe_fails(
        tmp_path, "report", f"analyses=[{analysis}]", "notes=null", "appendices=[/nonexistent.md]"
    )
    assert "appendices='/nonexistent.md' is not a file" in err


@pytest.mark.parametrize(
    ("override", "message"),
    [("out_dir=FILE", "an existing file, expected a folder"), ("gait_steps=-5", "gait_steps")],
)
def test_analyze_refuses_bad_settings_before_any_work(tmp_path, override, message):
    runs = tmp_path / "runs"
    make_run(runs, "ppo", 0, [1.0, 2.0, 3.0])
    file = tmp_path / "a_file"
    file.write_text("")
    override = override.replace("FILE", str(file))
    err = _recipe_fails(tmp_path, "analyze", f"runs=[{runs}]", "world_models=[]", override)
    assert message in err
