"""Analyses training runs: the thesis' experiments 1-4 as figures, tables and verdicts.

python recipes/analyze.py                                   # outputs/short -> results/short
python recipes/analyze.py runs=[outputs/thesis] out_dir=results/thesis gait=false
"""

from __future__ import annotations

import logging
import os

# Offscreen rendering on machines without a display; set before MuJoCo is imported.
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import hydra
from omegaconf import DictConfig

from torchrl_mbmf.analysis.experiments import analyze_experiments
from torchrl_mbmf.checks import check_number, check_output_path, check_recipe_overrides

log = logging.getLogger("analyze")


@hydra.main(config_path="../configs", config_name="analyze", version_base="1.3")
def main(cfg: DictConfig) -> None:
    check_recipe_overrides(cfg)  # a +key=... typo is refused, not ignored
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    # Settings checked before any work.
    out_dir = check_output_path(cfg.out_dir, "out_dir", folder=True)
    gait_steps = check_number(cfg.gait_steps, "gait_steps", minimum=1, integer=True)
    world_models = [p for p in (cfg.world_models or []) if os.path.isdir(p)]
    analysis = analyze_experiments(
        list(cfg.runs),
        out_dir,
        world_model_roots=world_models,
        gait=bool(cfg.gait),
        render=bool(cfg.render),
        gait_steps=gait_steps,
        collect=bool(cfg.collect),
        clip_seconds=float(cfg.get("clip_seconds", 0)),
    )
    log.info("%d runs analysed into %s", len(analysis["runs"]), cfg.out_dir)
    for q, v in analysis["verdicts"].items():
        log.info("%s: %s", q, v["verdict"])


if __name__ == "__main__":
    main()
