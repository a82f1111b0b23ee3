"""scripts/hybrid_ablation.py: the per-step IQM table over the run folders it is given."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from run_folders import fake_run

from torchrl_mbmf.analysis.stats import iqm

ROOT = Path(__file__).resolve().parents[2]


def test_table_takes_each_seeds_latest_value_and_leaves_out_seeds_short_of_the_step(tmp_path):
    root = tmp_path / "runs"
    name = "HalfCheetah-v5__hybrid_mbpo__H1-r0.05-utd5__5e4__seed{}"
    fake_run(root, name.format(0), 0, {5_000: 0.0, 10_000: 1.0, 20_000: 5.0}, done=True)
    fake_run(root, name.format(1), 1, {10_000: 2.0, 20_000: 7.0}, done=True)
    fake_run(root, name.format(2), 2, {10_000: 4.0, 16_000: 3.0}, done=False)  # stopped at 16,000
    out = tmp_path / "table.json"
    cmd = [sys.executable, str(ROOT / "scripts/hybrid_ablation.py"), "--runs", str(root)]
    cmd += ["--steps", "15000", "20000", "--out", str(out)]
    printed = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    rows = json.loads(out.read_text())["(b) MBPO-style learning (hybrid_mbpo)"]
    assert rows["seeds"] == [0, 1, 2]
    # the latest at or before 15,000 (seed 2's 16,000 is past it)
    assert rows["eval@15000"]["values"] == [1.0, 2.0, 4.0]
    assert rows["eval@15000"]["iqm"] == pytest.approx(float(iqm([1.0, 2.0, 4.0])))
    assert rows["eval@20000"]["values"] == [5.0, 7.0]  # seed 2 never reached 20,000
    assert rows["compute"]["runs"] == 2
    assert rows["compute"]["segment_ms_per_real_step"]["update_s"] == pytest.approx(0.4)
    assert "(2)" in printed and "(a) LOOP" not in printed  # no LOOP runs given: no row
