"""Training-loop costs: PPO iteration, SAC update (stock vs fused), end-to-end real steps/s.

    .venv/bin/python benchmarks/training.py            # full (a few minutes)
    .venv/bin/python benchmarks/training.py --quick    # smaller end-to-end runs

Writes benchmarks/results/training.json (training_threads<N>.json with --threads N) and prints a
table. Threads: torch.set_num_threads(2) unless --threads says otherwise.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from torchrl.collectors import Collector
from torchrl.objectives import ClipPPOLoss, SoftUpdate
from torchrl.objectives.value import GAE

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _common import print_table, time_call, write
from rl_helpers import make_test_sac_loss

from torchrl_mbmf.envs import make_env
from torchrl_mbmf.modules import make_ppo_actor_critic
from torchrl_mbmf.objectives.fused_ppo import ppo_update
from torchrl_mbmf.objectives.fused_sac import (
    FusedSACUpdate,
    sac_update_step,
)
from torchrl_mbmf.trainers import Trainer

ROOT = Path(__file__).resolve().parents[1]
ENV = "HalfCheetah-v5"


def bench_ppo(repeats: int) -> list[dict[str, object]]:
    """Seconds per thesis PPO iteration (2048 frames, 4 epochs, minibatch 32, 64x64 nets)."""
    torch.manual_seed(0)
    env = make_env(ENV, seed=0)
    actor, critic = make_ppo_actor_critic(env, hidden_sizes=(64, 64))
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=1e-4, critic_coeff=0.5)
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
    collector = Collector(
        env, actor, frames_per_batch=2048, total_frames=-1, auto_register_policy_transforms=False
    )
    start = time.perf_counter()
    batch = next(iter(collector))
    collect_s = time.perf_counter() - start
    collector.shutdown()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        ppo_update(loss, gae, optim, batch.clone(), epochs=4, minibatch_size=32)
        times.append(time.perf_counter() - start)
    times.sort()
    return [
        {
            "what": "PPO update (2048 frames, 4 ep x mb 32)",
            "value": times[len(times) // 2],
            "unit": "s/iter",
        },
        {"what": "PPO collect 2048 frames (actor, Collector)", "value": collect_s, "unit": "s"},
    ]


def bench_sac(number: int) -> list[dict[str, object]]:
    """Milliseconds per SAC update (batch 256, 256x256 ReLU, HalfCheetah sizes), stock vs fused.

    Adam as the training loop builds it; benchmarks/sac_update.py has the finer comparison.
    """
    rows = []
    for name in ("stock", "fused"):
        torch.manual_seed(0)
        loss, batch = make_test_sac_loss(
            batch_size=256, obs_dim=17, action_dim=6, hidden=256, activation=torch.nn.ReLU
        )
        optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
        updater = SoftUpdate(loss, tau=0.005)
        if name == "stock":
            step = sac_update_step(loss, optim, updater)
        else:
            step = FusedSACUpdate(loss, optim, updater)
        sec = time_call(lambda step=step, batch=batch: step(batch), repeats=5, number=number)
        rows.append({"what": f"SAC update, {name}", "value": sec * 1e3, "unit": "ms"})
    return rows


def _cfg(method: str, quick: bool):
    steps = 3000 if quick else 6000
    overrides = [
        f"method={method}",
        f"total_steps={steps}",
        "world_model.random_steps=1000",
        "world_model.max_epochs=5",
        "planning_updates=1" if quick else "planning_updates=2",
        "ppo.frames_per_batch=1024",
        "sac.init_random_frames=1000",
        f"sac.refit_every_steps={steps}",
        "eval_every=1000000",
        "checkpoint.every_steps=1000000",
        "logger.backend=",
        "progress=false",
    ]
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose("train", overrides=overrides)


def bench_end_to_end(quick: bool) -> list[dict[str, object]]:
    """Real steps per second of each method on HalfCheetah, world-model fits included."""
    rows = []
    for method in ("ppo", "sac", "mpc", "ppo_mpc", "sac_mpc"):
        cfg = _cfg(method, quick)
        with tempfile.TemporaryDirectory() as run_dir:
            summary = Trainer(cfg, Path(run_dir)).train()
        rows.append(
            {
                "what": f"{method} end to end ({summary['real_steps']} steps)",
                "value": summary["real_steps"] / summary["seconds"],
                "unit": "real steps/s",
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="smaller end-to-end runs")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--skip-end-to-end", action="store_true", help="only PPO and SAC")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    note = (
        "The machine (2 vCPU) was shared with other jobs while this ran: treat the numbers as "
        "upper bounds on cost. End-to-end runs: HalfCheetah-v5, world_model.random_steps=1000 "
        "(counted), world_model.max_epochs=5, ppo.frames_per_batch=1024, "
        "sac.init_random_frames=1000, utd 1, no logger; the rate includes env stepping, "
        "planning, updates and model fits."
    )
    name = "training" if args.threads == 2 else f"training_threads{args.threads}"
    extra = {"note": note, "quick": args.quick, "threads": args.threads}
    rows = bench_ppo(repeats=2 if args.quick else 3)
    rows += bench_sac(number=20 if args.quick else 50)
    path = write(name, rows, extra)  # partial results survive an interrupted end-to-end part
    if not args.skip_end_to_end:
        rows += bench_end_to_end(args.quick)
        path = write(name, rows, extra)
    print_table(rows)
    print(note)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
