"""benchmarks/main_job.py splits a committed whole run as the run's own timers did."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
main_job = pytest.importorskip("main_job")


def test_committed_run_split_matches_its_time_breakdown():
    """The split from the per-batch logs agrees with the summary's timers (a separate record)."""
    run = main_job.run_breakdown(main_job.DEFAULT_RUN)
    rows = main_job.committed_rows(run)
    summary = json.loads((main_job.DEFAULT_RUN / "summary.json").read_text())
    timers = summary["time_breakdown"]
    assert rows["total"] == pytest.approx(summary["seconds"], rel=1e-3)
    assert rows["world-model fits"] == pytest.approx(timers["refit_s"], rel=1e-6)
    updates = rows["planning: PPO updates"] + rows["PPO-only: PPO updates"]
    assert updates == pytest.approx(timers["update_s"], rel=0.03)
    acting = rows["random phase"] + rows["planning: env + planner"]
    acting += rows["PPO-only: env + policy"]
    assert acting == pytest.approx(timers["env_s"] + timers["act_s"] + timers["other_s"], rel=0.01)
    assert [f["transitions"] for f in run["fits"]] == [10000, 112400, 214800, 317200]
    assert all(v >= 0 for v in rows.values())


def test_extrapolating_the_run_itself_gives_its_total():
    """The committed run's own unit costs on its own schedule give back its wall time."""
    run = main_job.run_breakdown(main_job.DEFAULT_RUN)
    total = main_job.extrapolate(run, run)["total"]
    # the one modelled term: every fit at the first fit's rate per transition-epoch
    rate = run["fits"][0]["us_per_transition_epoch"] * 1e-6
    modelled = sum(
        f["epochs"] * (f["transitions"] - round(f["transitions"] * 0.1)) for f in run["fits"]
    )
    fits = sum(f["seconds"] for f in run["fits"])
    assert total == pytest.approx(run["seconds"] - fits + modelled * rate, rel=0.01)
