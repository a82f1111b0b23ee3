"""benchmarks/peers.py --quick runs ours and SB3's PPO side by side.

Skipped without stable-baselines3 (the ``bench`` extra) and marked slow: two fresh training
processes take 30-40 s on an idle 2-vCPU machine, two minutes on a busy one.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_quick_ppo_side_by_side(tmp_path):
    out = tmp_path / "peers.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "peers.py"),
            "--quick",
            "--methods",
            "ppo",
            "--repeats",
            "1",
            "--out",
            str(out),
        ],
        cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "ours/sb3" in proc.stdout
    doc = json.loads(out.read_text())
    runs = doc["runs"]
    assert [(r["method"], r["impl"]) for r in runs] == [("ppo", "ours"), ("ppo", "sb3")]
    for run in runs:
        assert run["steps"] == 2048
        assert run["steps_per_s"] > 0
        assert run["threads"] == 1
        assert run["torch_threads"] == 1
        assert run["grad_steps"] == 4 * 2048 // 32  # one PPO iteration: 4 epochs x 64 minibatches
    (summary,) = doc["summary"]
    assert summary["ours/sb3"] == pytest.approx(runs[0]["steps_per_s"] / runs[1]["steps_per_s"])
