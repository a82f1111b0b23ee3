"""The documentation site: it builds strictly, and its tutorial's script runs as shown."""

from __future__ import annotations

import importlib.util
import math
import os
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_mkdocs_build_strict(tmp_path):
    missing = [m for m in ("mkdocs", "material", "mkdocstrings") if not importlib.util.find_spec(m)]
    if missing:
        pytest.skip(
            f'the docs extra is not installed ({", ".join(missing)}): pip install -e ".[docs]"'
        )
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    site = tmp_path / "site"
    # the API pages are generated from the docstrings, the report's figures are served
    assert "PolicyGuidedMPCPlanner" in (site / "api/modules/index.html").read_text()
    assert (site / "results/thesis/exp1_horizon.png").is_file()
    report = (site / "results/REPORT/index.html").read_text()
    assert 'src="../thesis/exp1_horizon.png"' in report


def test_tutorial_script_runs(monkeypatch, capsys):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    out = runpy.run_path(str(ROOT / "docs/snippets/pendulum_mbmf.py"), run_name="__main__")
    # 1000 random steps, then three batches of 200 planned steps, all in the model's dataset
    assert len(out["data"]) == 1000 + 3 * 200
    assert min(out["history"].val_loss) < out["history"].val_loss[0]
    printed = capsys.readouterr().out
    assert printed.count("batch ") == 3 and "nan" not in printed
    assert all(math.isfinite(p.detach().sum().item()) for p in out["actor"].parameters())
