"""Real-step collection cost: torchrl's Collector vs this package's LeanCollector.

    .venv/bin/python benchmarks/collection.py            # 2,048-step batches, 3 rounds
    .venv/bin/python benchmarks/collection.py --quick    # 512-step batches, 2 rounds

Both collectors run the same env (HalfCheetah-v5, thesis state, default reward) and the same
policies (the 64x64 PPO actor, a random policy, the policy-guided planner on the thesis model),
alternating stock / lean in one process, on one thread unless --threads says otherwise. Prints ms
per real step and writes benchmarks/results/collection.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import RandomPolicy

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, write

from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.envs import LearnedDynamicsEnv, make_env
from torchrl_mbmf.modules import DeltaDynamicsModel, PolicyGuidedMPCPlanner, make_ppo_actor_critic


def _seconds_per_step(make, frames: int) -> float:
    collector = make()
    start = time.perf_counter()
    batch = next(iter(collector))
    seconds = time.perf_counter() - start
    collector.shutdown()
    assert batch.numel() == frames
    return seconds / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    frames = 512 if args.quick else 2048
    rounds = args.rounds or (2 if args.quick else 3)
    torch.manual_seed(0)
    env = make_env("HalfCheetah-v5", seed=0)
    actor, _ = make_ppo_actor_critic(env)
    planner = PolicyGuidedMPCPlanner(LearnedDynamicsEnv(DeltaDynamicsModel(18, 6), env), actor)
    policies = {
        "ppo actor": actor,
        "random": RandomPolicy(env.full_action_spec),
        "planner (m=15, h=10)": planner,
    }
    makers = {
        "stock Collector": lambda p: Collector(
            env, p, frames_per_batch=frames, total_frames=-1, auto_register_policy_transforms=False
        ),
        "LeanCollector": lambda p: LeanCollector(env, p, frames_per_batch=frames),
    }
    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(rounds):
        for pname, policy in policies.items():
            for cname, make in makers.items():  # alternating stock / lean
                sec = _seconds_per_step(lambda make=make, policy=policy: make(policy), frames)
                times.setdefault((pname, cname), []).append(sec)
    rows = []
    for pname in policies:
        stock = min(times[(pname, "stock Collector")])
        lean = min(times[(pname, "LeanCollector")])
        rows.append(
            {
                "policy": pname,
                "stock ms/step": stock * 1e3,
                "lean ms/step": lean * 1e3,
                "speed-up": stock / lean,
                "lean steps/s": 1 / lean,
            }
        )
    print_table(rows)
    path = write(
        "collection",
        rows,
        {
            "frames_per_batch": frames,
            "rounds": rounds,
            "statistic": "best of the rounds, one batch each",
            "all_seconds_per_step": {f"{p} / {c}": v for (p, c), v in times.items()},
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
