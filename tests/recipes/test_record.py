"""recipes/record.py: a committed campaign policy rendered offscreen to an .mp4."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchrl_mbmf.offscreen import GL_BACKENDS, RenderBackendError, choose_gl_backend

ROOT = Path(__file__).resolve().parents[2]
RUN = ROOT / "results/thesis/runs/HalfCheetah-v5__ppo_mpc__default__h10__seed0"


def working_backend() -> str:
    """The backend this machine renders with, or a skip saying why there is none."""
    env_backup = os.environ.pop("MUJOCO_GL", None)
    try:
        return choose_gl_backend(set_env=False)
    except RenderBackendError as err:
        pytest.skip(f"no offscreen OpenGL here ({err})")
    finally:
        if env_backup is not None:
            os.environ["MUJOCO_GL"] = env_backup


def read_mp4(path: Path) -> tuple[dict, np.ndarray]:
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    width, height = meta["size"]
    frames = np.stack([np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader])
    return meta, frames


def test_choose_gl_backend_keeps_the_users_choice(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert choose_gl_backend() == "osmesa"


def test_no_working_backend_is_a_clear_error(monkeypatch):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    with pytest.raises(RenderBackendError, match=r"MUJOCO_GL=nogl: .*apt-get install libosmesa6"):
        choose_gl_backend(("nogl",), set_env=False)
    with pytest.raises(ValueError, match="candidates"):
        choose_gl_backend((), set_env=False)
    assert "egl" in GL_BACKENDS and "osmesa" in GL_BACKENDS


def test_record_recipe_writes_a_video_of_the_policy(tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason='needs the video extra: pip install -e ".[video]"')
    if not RUN.is_dir():
        pytest.skip(f"the committed campaign run {RUN.name} is not here")
    backend = working_backend()
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    env["OMP_NUM_THREADS"] = "1"
    out = tmp_path / "cheetah.mp4"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes/record.py"),
            f"run_dir={RUN}",
            f"out={out}",
            "seconds=1",
            "width=64",
            "height=48",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"MUJOCO_GL={backend}" in proc.stdout + proc.stderr
    meta, frames = read_mp4(out)
    # HalfCheetah steps 0.05 s: one second is 20 frames, played in real time
    assert frames.shape == (20, 48, 64, 3) and meta["fps"] == pytest.approx(20.0)
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 1.0  # it moves


def test_rendering_does_not_change_the_rollout():
    """The rendered episode's return is the one of the same policy in a plain env."""
    pytest.importorskip("imageio_ffmpeg", reason='needs the video extra: pip install -e ".[video]"')
    if not RUN.is_dir():
        pytest.skip(f"the committed campaign run {RUN.name} is not here")
    from torchrl_mbmf.offscreen import _probe

    backend = os.environ.get("MUJOCO_GL")
    if backend is None or _probe(backend, 60.0) is not None:
        pytest.skip(f"MUJOCO_GL={backend} does not render here")
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_mbmf.analysis.video import render_policy
    from torchrl_mbmf.envs import make_env
    from torchrl_mbmf.runs.export import load_policy

    frames, info = render_policy(RUN, seconds=1, width=32, height=32, seed=7)
    assert frames.shape == (20, 32, 32, 3) and frames.dtype == np.uint8
    actor, env, _ = load_policy(RUN, env=make_env("HalfCheetah-v5", seed=7))
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(20, actor, break_when_any_done=False)
    assert info["return"] == pytest.approx(float(rollout["next", "reward"].sum()), rel=1e-6)
    assert info["real_steps"] == 1001232


def test_non_mujoco_runs_are_refused(tmp_path):
    (tmp_path / "config.yaml").write_text(
        (RUN / "config.yaml").read_text().replace("id: HalfCheetah-v5", "id: Pendulum-v1")
    )
    from torchrl_mbmf.analysis.video import render_policy

    with pytest.raises(ValueError, match="Pendulum-v1 is not a MuJoCo task"):
        render_policy(tmp_path, seconds=1)


def test_planner_video_of_a_tiny_ppo_mpc_run(tmp_path):
    """The planner acts over the run's last fit: other actions than the policy's alone."""
    from torchrl_mbmf.offscreen import _probe

    backend = os.environ.get("MUJOCO_GL")
    if backend is None or _probe(backend, 60.0) is not None:
        pytest.skip(f"MUJOCO_GL={backend} does not render here")
    from hydra import compose, initialize_config_dir

    from torchrl_mbmf.analysis.video import render_policy
    from torchrl_mbmf.trainers import Trainer

    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                "method=ppo_mpc",
                "total_steps=264",
                "world_model.random_steps=200",
                "world_model.max_epochs=1",
                "planning_updates=1",
                "ppo.frames_per_batch=64",
                "planner.num_candidates=4",
                "planner.horizon=3",
                "eval_episodes=0",
                "progress=false",
                f"run_dir={tmp_path}",
            ],
        )
    Trainer(cfg, tmp_path).train()
    policy_frames, policy_info = render_policy(tmp_path, seconds=0.5, width=32, height=32)
    frames, info = render_policy(tmp_path, seconds=0.5, width=32, height=32, planner=True)
    assert frames.shape == policy_frames.shape == (10, 32, 32, 3)
    assert info["return"] != policy_info["return"]
    with pytest.raises(ValueError, match="is a ppo run: it has no planner"):
        (tmp_path / "config.yaml").write_text(
            (tmp_path / "config.yaml").read_text().replace("method: ppo_mpc", "method: ppo")
        )
        render_policy(tmp_path, seconds=0.5, planner=True)
