"""Planner speed: ms per plan, FLOP floor, CEMPlanner reference, PPO-MPC collection frames/s.

python benchmarks/planner.py               # 2 torch threads -> results/planner.json
python benchmarks/planner.py --threads 1   # -> results/planner_threads1.json

The FLOP floor divides the plan's multiply-add count by the higher of two float32 matmul peaks
measured in the same run: ``torch.mm`` and the oneDNN linear with pre-packed weights that the
planner's model step uses (the second is the faster kernel on recent x86 CPUs). The 1-minute
load average is recorded: on a shared 2-core machine, two torch threads stall badly when other
processes compete for the cores, so compare runs only at similar load.
"""

from __future__ import annotations

import argparse
import os
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


def packed_linear_peak_gflops(size: int = 1024) -> float:
    """Float32 GFLOP/s of oneDNN's linear with pre-packed weights (0 when unavailable)."""
    if (
        not hasattr(torch.ops.mkldnn, "_linear_pointwise")
        or not torch.backends.mkldnn.is_available()
    ):
        return 0.0
    x, w, b = torch.randn(size, size), torch.randn(size, size), torch.zeros(size)
    packed = torch.ops.mkldnn._reorder_linear_weight(w, None)
    sec = time_call(
        lambda: torch.ops.mkldnn._linear_pointwise(x, packed, b, "none", [], ""),
        repeats=5,
        number=10,
    )
    return 2 * size**3 / sec / 1e9


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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load_before = os.getloadavg()[0]
    mm_peak = matmul_peak_gflops()
    packed_peak = packed_linear_peak_gflops()
    peak = max(mm_peak, packed_peak)
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
    load_after = os.getloadavg()[0]
    print(
        f"matmul peak: torch.mm {mm_peak:.1f}, packed oneDNN linear {packed_peak:.1f} GFLOP/s; "
        f"plan cost {flops / 1e6:.1f} MFLOP per state; load average {load_before:.1f} -> "
        f"{load_after:.1f} on {os.cpu_count()} cores"
    )
    print_table(rows)
    targets = {
        "ms_per_plan_1_state": 2.0,
        "frames_per_s_1_env": 300,
        "frames_per_s_8_envs": 1500,
        "prototype_ms_per_plan": [7, 15],
        "prototype_frames_per_s": 65,
    }
    path = write(
        "planner" if args.threads == 2 else f"planner_threads{args.threads}",
        rows,
        {
            "matmul_peak_gflops": peak,
            "torch_mm_peak_gflops": mm_peak,
            "packed_linear_peak_gflops": packed_peak,
            "load_average_1min": [load_before, load_after],
            "plan_mflop_per_state": flops / 1e6,
            "m": M,
            "h": H,
            "targets": targets,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
