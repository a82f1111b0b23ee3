"""scripts/hybrid_final.py: the final per-task table, the ratio to SB3's SAC and the figures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from run_folders import fake_run

from torchrl_mbmf.analysis.stats import iqm, iqm_ratio_ci

ROOT = Path(__file__).resolve().parents[2]


def test_final_table_per_task_with_ratio_to_sb3_and_figures(tmp_path):
    root = tmp_path / "runs"
    hybrid = "HalfCheetah-v5__hybrid_mbpo__H1-r0.05-utd5__seed{}"
    sb3 = "HalfCheetah-v5__sb3_sac__default__1e5__seed{}"
    for seed, (at_5e4, at_1e5) in enumerate([(3_000.0, 6_000.0), (2_500.0, 6_400.0)]):
        fake_run(root, hybrid.format(seed), seed, {50_000: at_5e4, 100_000: at_1e5})
    fake_run(root, hybrid.format(2), 2, {50_000: 4_000.0, 80_000: 5_000.0})  # stopped at 80,000
    for seed, value in enumerate([5_000.0, 5_500.0, 4_500.0]):
        fake_run(root, sb3.format(seed), seed, {50_000: value / 2, 100_000: value})
    fake_run(root, "HalfCheetah-v5__hybrid_mbpo__H1-r0.05-utd5__5e4__seed0", 0, {50_000: 3_000.0})
    fake_run(root, "Hopper-v5__sb3_sac__default__1e5__seed0", 0, {50_000: 900.0})
    out = tmp_path / "final.json"
    cmd = [sys.executable, str(ROOT / "scripts/hybrid_final.py"), "--runs", str(root)]
    cmd += ["--out", str(out), "--figures", str(tmp_path)]
    printed = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    result = json.loads(out.read_text())

    cheetah = result["HalfCheetah-v5"]
    assert cheetah["steps"] == [50_000, 100_000]  # no run reached 2e5: no such column
    rows = cheetah["methods"]["hybrid_mbpo (final)"]
    assert rows["seeds"] == [0, 1, 2] and rows["last_step"] == [100_000, 100_000, 80_000]
    assert rows["eval@50000"]["values"] == [3_000.0, 2_500.0, 4_000.0]
    assert rows["eval@100000"]["values"] == [6_000.0, 6_400.0]  # seed 2 never got there
    assert set(cheetah["methods"]) == {
        "SB3 SAC, 1e5 runs",
        "(b) MBPO-style, 5 updates, ablation",
        "hybrid_mbpo (final)",
    }
    ratio = cheetah["ratios"]["hybrid / SB3 SAC, 1e5 runs"]["eval@100000"]
    expected = iqm_ratio_ci([6_000.0, 6_400.0], [5_000.0, 5_500.0, 4_500.0])
    assert ratio["ratio"] == pytest.approx(float(iqm([6_000.0, 6_400.0])) / 5_000.0)
    assert ratio["ci95"] == pytest.approx([expected.low, expected.high])
    assert "1.24x" in printed
    assert cheetah["figure"]["curves"] == ["SB3 SAC, 1e5 runs", "hybrid_mbpo (final)"]
    assert (tmp_path / "final_HalfCheetah-v5.png").stat().st_size > 0
    assert "MBPO" in cheetah["anchors"]

    hopper = result["Hopper-v5"]
    assert hopper["steps"] == [50_000] and hopper["ratios"] == {}  # no hybrid run yet
    assert "Walker2d-v5" not in result  # no runs: no table
