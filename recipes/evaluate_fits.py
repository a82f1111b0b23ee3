"""Open-loop errors of every world-model fit a training run recorded (tables 8, 9 at each refit).

    python recipes/evaluate_fits.py run_dir=outputs/thesis/<run name>

Collects fresh random-policy episodes of the run's env and reward (seed: the run's seed +
``seed_offset``), evaluates each snapshot under ``run_dir/world_models/`` on the same start
states and writes ``run_dir/world_models/open_loop_errors.json``, beside the held-out errors on
the policy's own transitions that the run logged at each refit (``model/heldout_*``).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
import torch
import yaml
from omegaconf import DictConfig

from torchrl_mbmf.analysis.horizon import snapshot_open_loop_errors
from torchrl_mbmf.checks import check_recipe_overrides
from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import make_env
from torchrl_mbmf.runs.layout import FIT_ERRORS, RunFolder

log = logging.getLogger("evaluate_fits")


@hydra.main(config_path="../configs", config_name="evaluate_fits", version_base="1.3")
def main(cfg: DictConfig) -> None:
    check_recipe_overrides(cfg)  # a +key=... typo is refused, not ignored
    run_dir = Path(cfg.run_dir)
    config_path = run_dir / "config.yaml"
    if not config_path.exists():
        raise FileNotFoundError(f"run_dir={run_dir} has no config.yaml: not a training run")
    if int(cfg.eval_steps) < 1:
        raise ValueError(f"eval_steps={cfg.eval_steps}: expected a positive number of steps")
    torch.set_num_threads(int(cfg.threads))
    run = yaml.safe_load(config_path.read_text())
    seed = int(run["seed"]) + int(cfg.seed_offset)
    env = make_env(
        run["env"]["id"],
        reward=run["reward"]["name"],
        reward_kwargs=run["reward"].get("kwargs") or {},
        seed=seed,
    )
    data = collect_random_transitions(env, int(cfg.eval_steps), seed=seed)
    horizons = [int(h) for h in cfg.horizons]
    rows = snapshot_open_loop_errors(
        run_dir, data, horizons=horizons, num_starts=int(cfg.eval_starts), seed=seed
    )
    out = {
        "data": {"policy": "uniform random", "steps": len(data), "seed": seed},
        "horizons": horizons,
        "fits": rows,
    }
    path = RunFolder(run_dir).fits / FIT_ERRORS
    path.write_text(json.dumps(out, indent=2) + "\n")
    log.info("wrote %s (%d fits)", path, len(rows))


if __name__ == "__main__":
    main()
