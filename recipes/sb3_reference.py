"""Stable-Baselines3 reference runs: SB3's PPO and SAC with our settings, in our run layout.

    pip install -e ".[bench]"
    python recipes/sb3_reference.py method=ppo seed=0      # thesis table-6 PPO to 1e6 real steps
    python recipes/sb3_reference.py method=sac seed=1      # SAC (SB3 defaults = ours) to 2e5
    python recipes/sb3_reference.py -m method=ppo,sac seed=0,1,2

The run folder holds ``config.yaml``, ``git_commit.txt``, ``machine.json``,
``logs/scalars/{train,eval}/*.csv`` (the series our trainer logs per episode and evaluation) and,
once finished, ``summary.json``, so ``recipes/analyze.py`` puts these curves beside ours. SB3
runs do not resume: an interrupted one starts again from scratch with ``restart=true``.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import gymnasium as gym
import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from stable_baselines3 import __version__ as sb3v
from torchrl.record.loggers import CSVLogger

from torchrl_mbmf.baselines.sb3 import (
    SB3_ALGOS,
    RunFolderCallback,
    make_sb3_model,
    sb3_grad_steps,
)
from torchrl_mbmf.checks import check_recipe_overrides
from torchrl_mbmf.runs.layout import write_run_record

log = logging.getLogger("sb3_reference")

#: The thesis' budgets of the reference runs (experiments 2 and 4).
THESIS_STEPS = {"ppo": 1_000_000, "sac": 200_000}


def _check(cfg: DictConfig, run_dir: Path) -> int:
    if cfg.method not in SB3_ALGOS:
        raise ValueError(f"method={cfg.method!r}: expected one of {list(SB3_ALGOS)}")
    steps = THESIS_STEPS[cfg.method] if cfg.total_steps is None else int(cfg.total_steps)
    if steps < 1:
        raise ValueError(f"total_steps={cfg.total_steps}: expected a positive number of steps")
    if int(cfg.threads) < 1:
        raise ValueError(f"threads={cfg.threads}: expected a positive number of threads")
    started = [p for p in ("logs", "summary.json") if (run_dir / p).exists()]
    if started and not cfg.restart:
        raise FileExistsError(
            f"run_dir={run_dir} already holds a run ({', '.join(started)}); SB3 runs do not "
            "resume: pass restart=true to delete it and train again from scratch"
        )
    return steps


@hydra.main(config_path="../configs", config_name="sb3_reference", version_base="1.3")
def main(cfg: DictConfig) -> None:
    check_recipe_overrides(cfg)  # a +key=... typo is refused, not ignored
    run_dir = Path(cfg.run_dir)
    steps = _check(cfg, run_dir)
    for stale in ("logs", "summary.json"):
        path = run_dir / stale
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
    torch.set_num_threads(int(cfg.threads))
    settings = OmegaConf.to_container(cfg[cfg.method], resolve=True)
    record = {
        "method": f"sb3_{cfg.method}",
        "env": {"id": cfg.env_id},
        "reward": {"name": "default"},  # gymnasium's own reward = our DefaultReward
        "seed": int(cfg.seed),
        "total_steps": steps,
        cfg.method: settings,
        **{k: cfg[k] for k in ("eval_every", "eval_episodes", "threads", "run_name")},
        "run_dir": str(cfg.run_dir),
    }
    run_dir.mkdir(parents=True, exist_ok=True)
    write_run_record(run_dir, OmegaConf.create(record))
    machine = {**json.loads((run_dir / "machine.json").read_text()), "stable_baselines3": sb3v}
    (run_dir / "machine.json").write_text(json.dumps(machine, indent=2) + "\n")

    model = make_sb3_model(cfg.method, gym.make(cfg.env_id), settings, seed=int(cfg.seed))
    callback = RunFolderCallback(
        CSVLogger(exp_name="logs", log_dir=str(run_dir)),
        gym.make(cfg.env_id),
        seed=int(cfg.seed),
        eval_every=int(cfg.eval_every),
        eval_episodes=int(cfg.eval_episodes),
    )
    start = time.perf_counter()
    model.learn(total_timesteps=steps, callback=callback)
    seconds = time.perf_counter() - start
    real_steps = int(model.num_timesteps)
    last = list(callback.last_returns)
    summary = {
        "method": record["method"],
        "env": cfg.env_id,
        "reward": "default",
        "seed": int(cfg.seed),
        "real_steps": real_steps,
        "random_steps": min(real_steps, int(settings["init_random_frames"]))
        if cfg.method == "sac"
        else 0,
        "grad_steps": sb3_grad_steps(model),
        "episodes": callback.episodes,
        "last10_mean_return": sum(last) / len(last) if last else None,
        "final_eval_return": callback.evaluate() if int(cfg.eval_episodes) > 0 else None,
        "seconds": seconds,
        "resumed": False,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    log.info("summary: %s", json.dumps(summary))


if __name__ == "__main__":
    main()
