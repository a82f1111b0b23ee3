"""Every recipe refuses unknown settings added with ``+`` and bad counts before any work."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _fails(tmp_path: Path, recipe: str, *overrides: str) -> str:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / f"{recipe}.py"), *overrides],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode != 0, proc.stdout[-2000:]
    return proc.stderr


@pytest.mark.parametrize(
    ("recipe", "overrides", "message"),
    [
        (
            "fit_world_model",
            ["+world_model.hiden_sizes=[8]"],
            "unknown setting 'world_model.hiden_sizes' (added with +); did you mean "
            "'world_model.hidden_sizes'?",
        ),
        ("analyze", ["+unknwon=1"], "unknown setting 'unknwon' (added with +)"),
        ("report", ["+note=x.md"], "did you mean 'notes'?"),
        ("evaluate_fits", ["run_dir=x", "+eval_step=3"], "did you mean 'eval_steps'?"),
        ("sb3_reference", ["+sed=1"], "did you mean 'seed'?"),
        ("fit_world_model", ["env=pendulum", "eval_starts=-3"], "eval_starts must be an integer"),
        ("fit_world_model", ["env=pendulum", "plot_rollouts=-1"], "plot_rollouts must be an"),
        ("fit_world_model", ["env=pendulum", "eval_steps=0"], "eval_steps must be an integer"),
    ],
)
def test_recipes_refuse_bad_settings_first(tmp_path, recipe, overrides, message):
    stderr = _fails(tmp_path, recipe, *overrides, f"hydra.run.dir={tmp_path / 'out'}")
    assert message in stderr, stderr[-2000:]
    # nothing was collected or fitted: at most Hydra's own files
    out = tmp_path / "out"
    assert not out.exists() or {p.name for p in out.iterdir()} <= {".hydra", f"{recipe}.log"}
