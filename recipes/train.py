"""Trains PPO, MPC, PPO-MPC, SAC or SAC-MPC (thesis sections 5, 6.3).

    python recipes/train.py                                  # PPO-MPC, thesis settings
    python recipes/train.py method=sac_mpc reward=shin_pen seed=1
    python recipes/train.py -m method=ppo,ppo_mpc seed=0,1,2
Rerunning with the same run_dir resumes from its latest checkpoint.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from torchrl_mbmf.trainers import Trainer
from torchrl_mbmf.trainers.device import keep_freed_memory

log = logging.getLogger("train")


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    # one process, one run: keep freed memory for reuse instead of paying page faults for it
    # at every update (changes no numbers; see keep_freed_memory)
    keep_freed_memory()
    # cfg.run_dir and Hydra's output folder coincide unless run_dir is overridden; the run
    # folder is always cfg.run_dir so that a restarted job finds its checkpoints.
    summary = Trainer(cfg, Path(cfg.run_dir)).train()
    log.info("summary: %s", json.dumps(summary))


if __name__ == "__main__":
    main()
