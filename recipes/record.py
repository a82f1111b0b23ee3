"""Renders a run's exported policy offscreen to an .mp4 in its folder.

python recipes/record.py run_dir=outputs/short/HalfCheetah-v5__ppo_mpc__default__h10__seed0
python recipes/record.py run_dir=... seconds=5 width=480 height=320 out=cheetah.mp4
python recipes/record.py run_dir=... planner=true    # the run's planner acting: planner.mp4
The policy (policy.pt, weights only) acts deterministically in the run's env; MuJoCo renders
through EGL or OSMesa, chosen before it is imported (MUJOCO_GL if set).
"""

from __future__ import annotations

import logging
import sys

import hydra
from omegaconf import DictConfig

from torchrl_mbmf.offscreen import RenderBackendError, choose_gl_backend

log = logging.getLogger("record")


@hydra.main(config_path="../configs", config_name="record", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        backend = choose_gl_backend()
    except RenderBackendError as err:
        log.error("%s", err)
        sys.exit(2)
    # MuJoCo is imported from here on, with the backend chosen above
    from torchrl_mbmf.analysis.video import record_policy

    path, info = record_policy(
        cfg.run_dir,
        cfg.out,
        seconds=float(cfg.seconds),
        width=int(cfg.width),
        height=int(cfg.height),
        seed=None if cfg.seed is None else int(cfg.seed),
        planner=bool(cfg.planner),
    )
    log.info(
        "%s: %.0f s of the %s trained on %d real steps (return %.1f), MUJOCO_GL=%s, %d KB",
        path,
        cfg.seconds,
        "planner with the policy" if cfg.planner else "policy",
        info["real_steps"],
        info["return"],
        backend,
        path.stat().st_size // 1024,
    )


if __name__ == "__main__":
    main()
