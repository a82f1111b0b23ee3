"""Videos of a run's exported policy: offscreen MuJoCo rendering to an ``.mp4``.

The policy acts in the run's own env (env id, reward, seed from its ``config.yaml``, rebuilt
by :func:`~torchrl_mbmf.runs.export.load_policy`, weights only), each step rendered by
gymnasium's MuJoCo renderer through torchrl's :class:`~torchrl.record.PixelRenderTransform`,
and the frames are encoded with ``imageio-ffmpeg`` (a wheel that ships its own ``ffmpeg``).

Without a display MuJoCo renders through EGL (a GPU driver, or Mesa's ``libegl-mesa0``) or
OSMesa (Mesa's CPU renderer, Debian/Ubuntu ``apt-get install libosmesa6``). The backend is
chosen before MuJoCo is imported (:func:`~torchrl_mbmf.offscreen.choose_gl_backend`):
``MUJOCO_GL`` if set, else the first of EGL and OSMesa that renders a frame in a fresh process.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_mbmf.offscreen import choose_gl_backend

__all__ = [
    "record_policy",
    "render_policy",
    "write_mp4",
]


#: The camera of the gymnasium MuJoCo locomotion models that follows the body from the side.
TRACKING_CAMERA = "track"


def _run_planner(
    run_dir: Path, cfg: Any, env: EnvBase, actor: TensorDictModuleBase, seed: int
) -> TensorDictModuleBase:
    """The run's MPC planner over its last world-model fit, for :func:`render_policy`."""
    from torchrl_mbmf.envs import LearnedDynamicsEnv
    from torchrl_mbmf.modules import (
        DeltaDynamicsModel,
        PolicyGuidedMPCPlanner,
        RandomShootingMPCPlanner,
    )
    from torchrl_mbmf.world_model.snapshots import fit_snapshots, load_fit_snapshot

    if cfg.method not in ("mpc", "ppo_mpc", "sac_mpc"):
        raise ValueError(f"{run_dir} is a {cfg.method} run: it has no planner to record")
    wm, pl = cfg.world_model, cfg.planner
    if int(wm.get("ensemble_size", 1) or 1) > 1 or pl.get("terminal_value", False):
        raise ValueError(
            f"{run_dir} planned with an ensemble or a terminal value; recording its planner "
            "needs a single world model and the policy alone"
        )
    snapshots = fit_snapshots(run_dir)
    if not snapshots:
        raise ValueError(f"{run_dir} kept no world-model fit (world_models/fit-*) to plan with")
    state_dim = env.observation_spec["state"].shape[-1]
    model = DeltaDynamicsModel(
        state_dim, env.action_spec.shape[-1], hidden_sizes=tuple(int(h) for h in wm.hidden_sizes)
    )
    load_fit_snapshot(model, snapshots[-1][1])
    model_env = LearnedDynamicsEnv(model.eval(), env)
    common = {
        "num_candidates": int(pl.num_candidates),
        "horizon": int(pl.horizon),
        "discount": float(pl.discount),
    }
    torch.manual_seed(seed)  # the planner's candidates
    if cfg.method == "mpc":
        return RandomShootingMPCPlanner(model_env, actor=actor, **common)
    refinement = {}
    if pl.get("refinement"):
        refinement = {
            k: pl[k]
            for k in ("iterations", "num_elites", "policy_fraction", "temperature", "min_std")
        }
    return PolicyGuidedMPCPlanner(
        model_env, actor, refinement=pl.get("refinement"), **refinement, **common
    )


def render_policy(
    run_dir: str | Path,
    *,
    seconds: float = 10.0,
    width: int = 320,
    height: int = 240,
    seed: int | None = None,
    planner: bool = False,
) -> tuple[np.ndarray, dict[str, float]]:
    """Runs a run's exported policy (deterministic) in its env and renders every step.

    With ``planner=True`` the run's MPC planner acts instead: the run's settings
    (``planner.*``) over its last world-model fit (``world_models/fit-*``), with the policy
    as the planner's prior (random shooting for ``mpc``).

    The rollout lasts ``seconds`` of simulated time (``seconds x fps`` env steps, ``fps`` the
    env's real-time rate, e.g. 20 for HalfCheetah's 0.05 s step).

    Args:
        run_dir: a run folder with ``config.yaml`` and ``policy.pt``.

    Keyword Args:
        seconds: simulated seconds. Defaults to ``10``.
        width: frame width in pixels. Defaults to ``320``.
        height: frame height in pixels. Defaults to ``240``.
        seed: env seed; by default the run's evaluation seed (``seed + 1000``).
        planner: the planner acts instead of the policy. Defaults to ``False``.

    The camera is the model's ``track`` camera (the gymnasium locomotion tasks' side view that
    follows the body) where it has one.

    Returns:
        ``uint8`` frames ``[steps, height, width, 3]`` and ``info``: the episode's ``return``,
        ``real_steps`` the policy was trained on, and the env's ``fps`` (real time).

    Raises:
        ValueError: ``seconds``, ``width`` or ``height`` not positive, or a non-MuJoCo env;
            with ``planner``, a run without a planner, a fit snapshot, or with planner options
            that need more than the policy and one model (ensemble, terminal value).

    Examples:
        >>> from torchrl_mbmf.analysis.video import render_policy
        >>> frames, info = render_policy("outputs/short/run", seconds=1)  # doctest: +SKIP
    """
    import gymnasium as gym
    from omegaconf import OmegaConf
    from torchrl.envs.utils import ExplorationType, set_exploration_type
    from torchrl.record import PixelRenderTransform

    from torchrl_mbmf.envs import make_env
    from torchrl_mbmf.runs.export import load_policy
    from torchrl_mbmf.runs.layout import CONFIG

    for name, value in (("seconds", seconds), ("width", width), ("height", height)):
        if not value > 0:
            raise ValueError(f"{name} must be > 0, got {value}")
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG).exists():
        raise FileNotFoundError(f"{run_dir} has no {CONFIG}; is it a training run folder?")
    cfg = OmegaConf.load(run_dir / CONFIG)
    if "mujoco" not in str(gym.spec(cfg.env.id).entry_point):
        raise ValueError(f"{cfg.env.id} is not a MuJoCo task; only MuJoCo tasks are rendered")
    seed = int(cfg.seed) + 1000 if seed is None else int(seed)
    env = make_env(
        cfg.env.id,
        reward=cfg.reward.name,
        reward_kwargs=dict(cfg.reward.kwargs or {}),
        seed=seed,
        render_mode="rgb_array",
        width=int(width),
        height=int(height),
        camera_name=TRACKING_CAMERA,
    )
    fps = float(env.base_env._env.unwrapped.metadata.get("render_fps") or 30)
    actor, env, info = load_policy(run_dir, env=env)
    policy = _run_planner(run_dir, cfg, env, actor, seed) if planner else actor
    env.append_transform(PixelRenderTransform(preproc=lambda a: torch.from_numpy(a.copy())))
    # The transform's spec is found by resetting the env and rendering: compute it now, not in
    # the middle of the rollout, then start from the seed's first reset (as the plain env does).
    env.observation_spec  # noqa: B018
    env.set_seed(seed)
    start = env.reset()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(
            max(1, round(seconds * fps)),
            policy,
            tensordict=start,
            auto_reset=False,
            break_when_any_done=False,
        )
    frames = rollout.get("pixels").numpy()
    env.close()
    return frames, {
        "return": float(rollout.get(("next", "reward")).sum()),
        "real_steps": float(info["real_steps"]),
        "fps": fps,
    }


def write_mp4(frames: np.ndarray, path: str | Path, *, fps: float = 30.0) -> Path:
    """Encodes ``uint8`` frames ``[T, H, W, 3]`` as an H.264 ``.mp4`` (``imageio-ffmpeg``).

    Args:
        frames: the frames (``H`` and ``W`` even).
        path: the file to write.

    Keyword Args:
        fps: frames per second. Defaults to ``30``.

    Returns:
        The path written.

    Raises:
        ImportError: ``imageio-ffmpeg`` is not installed (``pip install -e ".[video]"``).
        ValueError: frames of another shape or dtype, or odd sizes.

    Examples:
        >>> import numpy as np, tempfile, os
        >>> from torchrl_mbmf.analysis.video import write_mp4
        >>> with tempfile.TemporaryDirectory() as d:
        ...     path = write_mp4(np.zeros((5, 32, 48, 3), np.uint8), os.path.join(d, "a.mp4"))
        ...     path.stat().st_size > 0
        True
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(
            f"frames must be uint8 [T, H, W, 3], got {frames.dtype} {tuple(frames.shape)}"
        )
    height, width = frames.shape[1:3]
    if height % 2 or width % 2:
        raise ValueError(f"H.264 needs even frame sizes, got {width}x{height}")
    try:
        import imageio_ffmpeg
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ImportError('writing .mp4 needs imageio-ffmpeg: pip install -e ".[video]"') from err
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (width, height),
        fps=float(fps),
        codec="libx264",
        pix_fmt_out="yuv420p",
        macro_block_size=2,
        output_params=["-crf", "28", "-preset", "slow", "-movflags", "+faststart"],
    )
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame))
    writer.close()
    return path


def record_policy(
    run_dir: str | Path,
    out: str | Path | None = None,
    *,
    seconds: float = 10.0,
    width: int = 320,
    height: int = 240,
    seed: int | None = None,
    planner: bool = False,
) -> tuple[Path, dict[str, float]]:
    """Renders a run's exported policy to ``run_dir/policy.mp4`` (or ``out``), in real time.

    With ``planner=True`` the run's planner acts (:func:`render_policy`), by default into
    ``run_dir/planner.mp4``.

    Args:
        run_dir: a run folder with ``config.yaml`` and ``policy.pt``.
        out: the video file. Defaults to ``run_dir/policy.mp4`` (``planner.mp4``).

    Keyword Args:
        seconds: video length at the env's real-time frame rate. Defaults to ``10``.
        width: frame width in pixels. Defaults to ``320``.
        height: frame height in pixels. Defaults to ``240``.
        seed: env seed; by default the run's evaluation seed.
        planner: the run's planner acts instead of the policy. Defaults to ``False``.

    Returns:
        The path written and :func:`render_policy`'s ``info``.

    Examples:
        >>> from torchrl_mbmf.analysis.video import record_policy
        >>> path, info = record_policy("outputs/short/run", seconds=2)  # doctest: +SKIP
    """
    choose_gl_backend()
    frames, info = render_policy(
        run_dir, seconds=seconds, width=width, height=height, seed=seed, planner=planner
    )
    default = Path(run_dir) / ("planner.mp4" if planner else "policy.mp4")
    path = write_mp4(frames, default if out is None else out, fps=info["fps"])
    return path, info
