"""Gait analysis of a HalfCheetah policy (thesis section 6.2.3, eq. 20, figures 14-16, 18-21)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.envs.keys import ACTUATOR_TORQUES_KEY, JOINT_VELOCITIES_KEY, STATE_KEY
from torchrl_mbmf.envs.physics_info import HALF_CHEETAH_JOINTS, quiet_mujoco_warnings


@dataclass
class GaitMetrics:
    """Gait statistics of one rollout.

    Attributes:
        joints: joint names, in action order.
        average_power: mean of torque x angular velocity per joint over the rollout (W, thesis
            eq. 20); negative values mean the joint absorbs energy on average.
        average_abs_power: mean of ``|torque x angular velocity|`` per joint (W).
        torso_height: torso z along the rollout (m), the vertical displacement of figure 15.
        x_position: torso x along the rollout (m), figure 16.
        distance: x travelled over the rollout (m).
        height_std: standard deviation of the torso height (m): lower is a steadier gait.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.analysis.gait import gait_metrics
        >>> nxt = TensorDict(state=torch.zeros(4, 18), actuator_torques=torch.ones(4, 6),
        ...                  joint_velocities=2 * torch.ones(4, 6), batch_size=[4])
        >>> td = TensorDict(state=torch.zeros(4, 18), next=nxt, batch_size=[4])
        >>> gait_metrics(td).average_power
        [2.0, 2.0, 2.0, 2.0, 2.0, 2.0]
    """

    joints: list[str]
    average_power: list[float]
    average_abs_power: list[float]
    torso_height: list[float]
    x_position: list[float]
    distance: float
    height_std: float

    def to_dict(self) -> dict[str, object]:
        """The metrics as a JSON-serialisable dict."""
        return asdict(self)


def gait_metrics(
    rollout: TensorDictBase,
    *,
    joints: Sequence[str] = HALF_CHEETAH_JOINTS,
    state_key: str = STATE_KEY,
    x_index: int = 0,
    height_index: int = 1,
) -> GaitMetrics:
    """Computes per-joint power and torso trajectory from a rollout of the real env.

    Args:
        rollout: a ``[T]`` rollout of :func:`~torchrl_mbmf.envs.make_half_cheetah_env` (it
            carries ``("next", "actuator_torques")`` and ``("next", "joint_velocities")``).

    Keyword Args:
        joints: joint names for the report. Defaults to HalfCheetah's six actuated joints.
        state_key: state key. Defaults to ``"state"``.
        x_index: index of the torso x in the state. Defaults to ``0``.
        height_index: index of the torso z in the state. Defaults to ``1``.

    Returns:
        The :class:`GaitMetrics`.

    Raises:
        ValueError: if the rollout is batched or lacks the physics entries.

    Examples:
        >>> from torchrl_mbmf.analysis.gait import gait_metrics
        >>> from torchrl_mbmf.envs import make_half_cheetah_env
        >>> metrics = gait_metrics(make_half_cheetah_env(seed=0).rollout(20))
        >>> len(metrics.average_power), len(metrics.torso_height)
        (6, 20)
    """
    if rollout.batch_dims != 1:
        raise ValueError(
            f"gait_metrics expects a [T] rollout, got batch size {tuple(rollout.batch_size)}"
        )
    nxt = rollout.get("next")
    for key in (ACTUATOR_TORQUES_KEY, JOINT_VELOCITIES_KEY, state_key):
        if key not in nxt:
            raise ValueError(f"the rollout has no ('next', {key!r}) entry")
    torque = nxt.get(ACTUATOR_TORQUES_KEY).double()
    omega = nxt.get(JOINT_VELOCITIES_KEY).double()
    power = torque * omega
    state = nxt.get(state_key).double()
    height = state[:, height_index]
    x = state[:, x_index]
    start_x = rollout.get(state_key)[0, x_index].double()
    return GaitMetrics(
        joints=list(joints),
        average_power=power.mean(0).tolist(),
        average_abs_power=power.abs().mean(0).tolist(),
        torso_height=height.tolist(),
        x_position=x.tolist(),
        distance=float(x[-1] - start_x),
        height_std=float(height.std()) if height.numel() > 1 else 0.0,
    )


def record_gait(
    env: EnvBase,
    policy: torch.nn.Module,
    *,
    steps: int = 60,
    exploration: ExplorationType = ExplorationType.DETERMINISTIC,
) -> TensorDictBase:
    """Runs ``policy`` for ``steps`` steps in the real env (deterministic by default).

    Args:
        env: the real env (unbatched).
        policy: a TorchRL policy reading the env's keys.

    Keyword Args:
        steps: number of steps (the thesis plots 60). Defaults to ``60``.
        exploration: exploration type of the rollout. Defaults to deterministic.

    Returns:
        The ``[steps]`` rollout.

    Examples:
        >>> from torchrl_mbmf.analysis.gait import record_gait
        >>> from torchrl_mbmf.envs import make_half_cheetah_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> env = make_half_cheetah_env(seed=0)
        >>> actor, _ = make_ppo_actor_critic(env)
        >>> record_gait(env, actor, steps=5).batch_size
        torch.Size([5])
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if env.batch_size != ():
        raise ValueError(f"record_gait needs an unbatched env, got batch {tuple(env.batch_size)}")
    with torch.no_grad(), set_exploration_type(exploration):
        return env.rollout(steps, policy, break_when_any_done=False)


def render_states(
    states: torch.Tensor,
    *,
    env_id: str = "HalfCheetah-v5",
    width: int = 320,
    height: int = 240,
    distance: float = 4.0,
) -> np.ndarray:
    """Renders HalfCheetah states offscreen (set ``MUJOCO_GL=egl`` on a machine without display).

    The state is the thesis state ``[x, qpos[1:], qvel]``, so ``qpos = state[:nq]`` and
    ``qvel = state[nq:]``; each frame is rendered from a camera tracking the torso.

    Args:
        states: ``[T, state_dim]`` states.

    Keyword Args:
        env_id: gymnasium id whose MuJoCo model is rendered. Defaults to ``"HalfCheetah-v5"``.
        width: frame width in pixels. Defaults to ``320``.
        height: frame height in pixels. Defaults to ``240``.
        distance: camera distance (m). Defaults to ``4.0`` (gymnasium's default for the cheetah).

    Returns:
        ``uint8`` frames ``[T, height, width, 3]``.

    Examples:
        >>> import os, torch  # doctest: +SKIP
        >>> os.environ["MUJOCO_GL"] = "egl"  # doctest: +SKIP
        >>> from torchrl_mbmf.analysis.gait import render_states  # doctest: +SKIP
        >>> render_states(torch.zeros(2, 18)).shape  # doctest: +SKIP
        (2, 240, 320, 3)
    """
    import gymnasium as gym

    with quiet_mujoco_warnings():
        model = gym.make(env_id).unwrapped.model
    nq, nv = model.nq, model.nv
    if states.ndim != 2 or states.shape[-1] != nq + nv:
        raise ValueError(
            f"states must be [T, {nq + nv}] (qpos then qvel), got {tuple(states.shape)}"
        )
    data = mujoco.MjData(model)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    camera.trackbodyid = model.body("torso").id
    camera.distance = distance
    camera.elevation = -10.0
    camera.azimuth = 90.0
    frames = []
    with mujoco.Renderer(model, height, width) as renderer:
        for s in states.double().cpu().numpy():
            data.qpos[:] = s[:nq]
            data.qvel[:] = s[nq:]
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=camera)
            frames.append(renderer.render().copy())
    return np.stack(frames)


def frame_strip(frames: np.ndarray, *, num: int = 8) -> np.ndarray:
    """Tiles ``num`` evenly spaced frames side by side (the thesis' gait-cycle figures).

    Args:
        frames: ``[T, H, W, 3]`` frames.

    Keyword Args:
        num: frames in the strip. Defaults to ``8``.

    Returns:
        One ``[H, num * W, 3]`` image.

    Examples:
        >>> import numpy as np
        >>> from torchrl_mbmf.analysis.gait import frame_strip
        >>> frame_strip(np.zeros((20, 4, 5, 3), dtype=np.uint8), num=4).shape
        (4, 20, 3)
    """
    if frames.ndim != 4:
        raise ValueError(f"frames must be [T, H, W, C], got shape {frames.shape}")
    num = max(1, min(num, frames.shape[0]))
    idx = np.linspace(0, frames.shape[0] - 1, num).round().astype(int)
    return np.concatenate(list(frames[idx]), axis=1)


def plot_gait(metrics: GaitMetrics, path: str, *, title: str = "") -> None:
    """Saves the power-per-joint, torso height and x-position plots (figures 14-16) as one PNG.

    Args:
        metrics: the gait metrics.
        path: PNG file to write.

    Keyword Args:
        title: figure title. Defaults to none.

    Examples:
        >>> import tempfile, os
        >>> from torchrl_mbmf.analysis.gait import GaitMetrics, plot_gait
        >>> m = GaitMetrics(["a", "b"], [1.0, -1.0], [1.0, 1.0], [0.1, 0.2], [0.0, 0.1], 0.1, 0.05)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     plot_gait(m, os.path.join(d, "gait.png"))
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].bar(metrics.joints, metrics.average_power)
    axes[0].set_xlabel("joint")
    axes[0].set_ylabel("average power (W)")
    axes[0].set_title("power per joint (eq. 20)")
    t = np.arange(1, len(metrics.torso_height) + 1)
    axes[1].plot(t, metrics.torso_height)
    axes[1].set_xlabel("time step (0.05 s)")
    axes[1].set_ylabel("torso height (m)")
    axes[1].set_title(f"vertical displacement (std {metrics.height_std:.3f} m)")
    axes[2].plot(t, metrics.x_position)
    axes[2].set_xlabel("time step (0.05 s)")
    axes[2].set_ylabel("torso x (m)")
    axes[2].set_title(f"horizontal displacement ({metrics.distance:.2f} m)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
