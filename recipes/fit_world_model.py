"""Collects random-policy data, fits the thesis world model and evaluates its h-step errors.

python recipes/fit_world_model.py                      # HalfCheetah-v5, default reward
python recipes/fit_world_model.py reward=head_pen seed=1
python recipes/fit_world_model.py env=pendulum world_model.random_steps=2000
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from torchrl_mbmf.analysis.world_model_job import run_fit_world_model
from torchrl_mbmf.checks import check_recipe_overrides

log = logging.getLogger("fit_world_model")


@hydra.main(config_path="../configs", config_name="fit_world_model", version_base="1.3")
def main(cfg: DictConfig) -> None:
    check_recipe_overrides(cfg)  # a +key=... typo is refused, not ignored
    # torchrl logs each replay storage's creation at INFO on stdout; keep the output readable.
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    summary = run_fit_world_model(cfg, out_dir)
    log.info(
        "fitted on %d random steps (%d epochs, best val loss %.4f); run folder %s",
        summary["random_steps"],
        summary["epochs"],
        summary["best_val_loss"],
        out_dir,
    )
    print(summary["horizon_table"])


if __name__ == "__main__":
    main()
