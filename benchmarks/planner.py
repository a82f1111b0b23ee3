"""Planner speed: ms per plan, FLOP floor, CEMPlanner reference, PPO-MPC collection frames/s.

python benchmarks/planner.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.modules.planners import CEMPlanner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import itertools

from _common import matmul_peak_gflops, print_table, time_call, write

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_half_cheetah_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
    make_ppo_actor_critic,
)

M, H = 15, 10


def plan_flops(model: DeltaDynamicsModel, actor_cells=(64, 64), obs_dim=17, act_dim=6) -> int:
    """Multiply-add FLOPs of one plan (model + policy MLPs, m x h forward passes)."""
    dims = [model.state_dim + model.action_dim, *model.hidden_sizes, model.state_dim + 1]
    model_f = sum(2 * a * b for a, b in itertools.pairwise(dims))
    adims = [obs_dim, *actor_cells, act_dim]
    actor_f = sum(2 * a * b for a, b in itertools.pairwise(adims))
    return M * H * (model_f + actor_f)


def collection_fps(num_envs: int, frames: int) -> float:
    real = make_half_cheetah_env(num_envs=num_envs, seed=0)
    actor, _ = make_ppo_actor_critic(real)
    env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6), real)
    planner = PolicyGuidedMPCPlanner(env, actor, num_candidates=M, horizon=H)
    collector = Collector(
        real,
        planner,
        frames_per_batch=frames,
        total_frames=-1,
        auto_register_policy_transforms=False,
    )
    it = iter(collector)
    next(it)  # warm-up batch
    rates = []
    for _ in range(3):
        start = time.perf_counter()
        batch = next(it)
        rates.append(batch.numel() / (time.perf_counter() - start))
    collector.shutdown()
    return sorted(rates)[1]


def main() -> None:
    torch.set_num_threads(2)
    torch.manual_seed(0)
    peak = matmul_peak_gflops()
    real = make_half_cheetah_env(seed=0)
    actor, _ = make_ppo_actor_critic(real)
    model = DeltaDynamicsModel(18, 6)
    env = LearnedDynamicsEnv(model, real)
    flops = plan_flops(model)
    rows = []
    for batch in (1, 8):
        td = make_half_cheetah_env(num_envs=batch, seed=0).reset() if batch > 1 else real.reset()
        planners = {
            "PolicyGuidedMPCPlanner": PolicyGuidedMPCPlanner(
                env, actor, num_candidates=M, horizon=H
            ),
            "RandomShootingMPCPlanner": RandomShootingMPCPlanner(env, num_candidates=M, horizon=H),
            "RandomShootingMPCPlanner(actor)": RandomShootingMPCPlanner(
                env, num_candidates=M, horizon=H, actor=actor
            ),
            "torchrl CEMPlanner(optim_steps=1, top_k=1)": CEMPlanner(
                env, planning_horizon=H, optim_steps=1, num_candidates=M, top_k=1
            ),
        }
        for name, planner in planners.items():
            if name.startswith("torchrl") and batch > 1:
                # CEMPlanner's dims assume an unbatched env spec; plan each state in turn
                def call(planner=planner, td=td, batch=batch):
                    for i in range(batch):
                        planner(td[i].clone())
            else:

                def call(planner=planner, td=td):
                    planner(td.clone())

            with torch.no_grad():
                sec = time_call(call, repeats=5, number=40)
            floor = batch * flops / (peak * 1e9)
            rows.append(
                {
                    "planner": name,
                    "states": batch,
                    "ms_per_plan": sec * 1e3,
                    "floor_ms": floor * 1e3,
                    "x_floor": sec / floor,
                }
            )
    fps = {n: collection_fps(n, 1024 if n > 1 else 512) for n in (1, 8)}
    for n, v in fps.items():
        rows.append({"planner": f"PPO-MPC Collector, {n} env(s)", "states": n, "frames_per_s": v})
    print(f"matmul peak: {peak:.1f} GFLOP/s; plan cost {flops / 1e6:.1f} MFLOP per state")
    print_table(rows)
    targets = {
        "ms_per_plan_1_state": 2.0,
        "frames_per_s_1_env": 300,
        "frames_per_s_8_envs": 1500,
        "prototype_ms_per_plan": [7, 15],
        "prototype_frames_per_s": 65,
    }
    path = write(
        "planner",
        rows,
        {
            "matmul_peak_gflops": peak,
            "plan_mflop_per_state": flops / 1e6,
            "m": M,
            "h": H,
            "targets": targets,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
