"""The analysis' optional video clip per reward variant, linked from the report."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from torchrl_mbmf.offscreen import _probe

ROOT = Path(__file__).resolve().parents[2]
RUN = ROOT / "results/thesis/runs/HalfCheetah-v5__ppo_mpc__head_pen__h10__seed0"


def test_gait_clip_per_reward_in_analysis_and_report(tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason='needs the video extra: pip install -e ".[video]"')
    if not RUN.is_dir():
        pytest.skip(f"the committed campaign run {RUN.name} is not here")
    backend = os.environ.get("MUJOCO_GL")
    if backend is None or _probe(backend, 60.0) is not None:
        pytest.skip(f"MUJOCO_GL={backend} does not render here")
    import imageio_ffmpeg

    from torchrl_mbmf.analysis import analyze_experiments, write_report

    shutil.copytree(RUN, tmp_path / "runs" / RUN.name)
    out = tmp_path / "analysis"
    analysis = analyze_experiments(
        [tmp_path / "runs"],
        out,
        gait=True,
        render=True,
        gait_steps=5,
        collect=False,
        clip_seconds=0.5,
    )
    policy = analysis["gait"]["policies"]["head_pen"]
    assert policy["clip"] == "clip_head_pen.mp4"
    reader = imageio_ffmpeg.read_frames(str(out / policy["clip"]))
    next(reader)
    assert sum(1 for _ in reader) == 10  # 0.5 s of HalfCheetah's 20 steps per second
    write_report({"thesis": out}, tmp_path / "REPORT.md")
    assert (
        "[Video: the head_pen policy](analysis/clip_head_pen.mp4)"
        in (tmp_path / "REPORT.md").read_text()
    )
