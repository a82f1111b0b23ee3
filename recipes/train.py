"""Trains PPO, MPC, PPO-MPC, SAC or SAC-MPC (thesis sections 5, 6.3), or MBPO-style SAC.

    python recipes/train.py                                  # PPO-MPC, thesis settings
    python recipes/train.py method=sac_mpc reward=shin_pen seed=1
    python recipes/train.py env=hopper method=sac_mpc       # any task of configs/env
    python recipes/train.py experiment=hybrid_mbpo          # method=sac_mbpo, its preset
    python recipes/train.py -m method=ppo,ppo_mpc seed=0,1,2
Rerunning with the same run_dir resumes from its latest checkpoint; SIGTERM or Ctrl-C stops the
run after its next checkpoint (a second one stops at once). A finished run is not trained over
unless restart=true (its files are moved aside).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from torchrl_mbmf.device import keep_freed_memory
from torchrl_mbmf.runs import FinishedRunError
from torchrl_mbmf.runs.summary_text import end_of_run_message
from torchrl_mbmf.trainers import Trainer

log = logging.getLogger("train")


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    # one process, one run: keep freed memory for reuse instead of paying page faults for it
    # at every update (changes no numbers; see keep_freed_memory)
    keep_freed_memory()
    # cfg.run_dir and Hydra's output folder coincide unless run_dir is overridden; the run
    # folder is always cfg.run_dir so that a restarted job finds its checkpoints.
    try:
        trainer = Trainer(cfg, Path(cfg.run_dir))
    except FinishedRunError as done:  # a sweep restarted over finished runs: nothing to do
        log.info("%s", done)
        return
    summary = trainer.train()
    if "stopped_by" in summary:
        log.info(
            "stopped by %s after the checkpoint at %d real steps; rerun the same command to resume",
            summary["stopped_by"],
            summary["real_steps"],
        )
        return
    log.info("summary: %s", json.dumps(summary))
    print(end_of_run_message(summary, trainer.run_dir))


if __name__ == "__main__":
    main()
