"""Planner variants: terminal value, CEM/MPPI refinement, K=5 ensemble, adaptive horizon.

python benchmarks/planner_variants.py --threads 1   # -> results/planner_variants.json

One 15x10 policy-guided plan on HalfCheetah sizes (18-dim state, 6-dim action, 500x500 world
model members, 64x64 policy), from 1 and from 8 real states:

* ``PolicyGuidedMPCPlanner``: the thesis planner on one ``DeltaDynamicsModel``.
* ``+ terminal value``: the PPO critic's value of each candidate's last state added.
* ``+ CEM`` / ``+ MPPI``: two refinement rounds after the policy round (three rollouts).
* ``Ensemble K=5, full horizon``: ``EnsemblePolicyGuidedPlanner`` without threshold; it still
  writes the disagreement statistic, so every step runs all 5 members on all candidates.
* ``Ensemble K=5, full horizon, no stats``: same without ``stats_key``: each candidate goes
  through its own member only (grouped ``[m] -> [m/K, K]``), one model's FLOPs.
* ``Ensemble K=5, adaptive horizon``: threshold at the median disagreement of the start states
  (the cost does not depend on the threshold: every step is computed).

The FLOP floor divides each variant's multiply-add count by the float32 peak of the faster of
``torch.mm`` and oneDNN's packed linear, measured in the same run.
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import matmul_peak_gflops, print_table, time_call, write
from planner import packed_linear_peak_gflops

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_half_cheetah_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    EnsembleDeltaDynamicsModel,
    EnsemblePolicyGuidedPlanner,
    PolicyGuidedMPCPlanner,
    make_ppo_actor_critic,
)

M, H, K = 15, 10, 5


def mlp_flops(dims: list[int]) -> int:
    return sum(2 * a * b for a, b in itertools.pairwise(dims))


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
    actor, critic = make_ppo_actor_critic(real)
    single = DeltaDynamicsModel(18, 6)
    ensemble = EnsembleDeltaDynamicsModel(18, 6, num_members=K)
    model_f = mlp_flops([24, 500, 500, 19])
    actor_f = mlp_flops([17, 64, 64, 6])
    rows = []
    for batch in (1, 8):
        td = make_half_cheetah_env(num_envs=batch, seed=0).reset() if batch > 1 else real.reset()
        s = td["state"].expand(64, *td["state"].shape).reshape(-1, 18)
        a = torch.rand(s.shape[0], 6) * 2 - 1
        with torch.no_grad():
            threshold = float(ensemble.disagreement(s, a).median())
        single_env = LearnedDynamicsEnv(single, real)
        ens_env = LearnedDynamicsEnv(ensemble, real)
        variants = {
            "PolicyGuidedMPCPlanner (1 model)": (
                PolicyGuidedMPCPlanner(single_env, actor, num_candidates=M, horizon=H),
                model_f,
            ),
            "PolicyGuidedMPCPlanner + terminal value (critic)": (
                PolicyGuidedMPCPlanner(
                    single_env, actor, num_candidates=M, horizon=H, value_module=critic
                ),
                model_f,
            ),
            "PolicyGuidedMPCPlanner + CEM (2 rounds)": (
                PolicyGuidedMPCPlanner(
                    single_env, actor, num_candidates=M, horizon=H, refinement="cem"
                ),
                3 * model_f,
            ),
            "PolicyGuidedMPCPlanner + MPPI (2 rounds)": (
                PolicyGuidedMPCPlanner(
                    single_env, actor, num_candidates=M, horizon=H, refinement="mppi"
                ),
                3 * model_f,
            ),
            f"Ensemble K={K}, full horizon": (
                EnsemblePolicyGuidedPlanner(ens_env, actor, num_candidates=M, horizon=H),
                K * model_f,
            ),
            f"Ensemble K={K}, full horizon, no stats": (
                EnsemblePolicyGuidedPlanner(
                    ens_env, actor, num_candidates=M, horizon=H, stats_key=None
                ),
                model_f,
            ),
            f"Ensemble K={K}, adaptive horizon": (
                EnsemblePolicyGuidedPlanner(
                    ens_env,
                    actor,
                    num_candidates=M,
                    horizon=H,
                    disagreement_threshold=threshold,
                ),
                K * model_f,
            ),
        }
        for name, (planner, step_f) in variants.items():

            def call(planner=planner, td=td):
                return planner(td.clone())

            with torch.no_grad():
                sec = time_call(call, repeats=5, number=40)
                out = call()
            flops = batch * M * H * (step_f + actor_f)
            floor = flops / (peak * 1e9)
            row = {
                "planner": name,
                "states": batch,
                "ms_per_plan": sec * 1e3,
                "floor_ms": floor * 1e3,
                "x_floor": sec / floor,
                "mflop_per_plan": flops / 1e6,
            }
            if ("planner", "effective_horizon") in out.keys(True):
                row["mean_effective_horizon"] = float(out["planner", "effective_horizon"].mean())
            rows.append(row)
    load_after = os.getloadavg()[0]
    print(
        f"matmul peak: torch.mm {mm_peak:.1f}, packed oneDNN linear {packed_peak:.1f} GFLOP/s; "
        f"load average {load_before:.1f} -> {load_after:.1f} on {os.cpu_count()} cores"
    )
    print_table(rows)
    note = (
        f"Run with --threads {args.threads} on a 2-core machine whose cores were busy with "
        "other jobs while this ran (see load_average_1min): treat the times as upper bounds. "
        "The single model's middle layer runs as a pre-packed oneDNN linear (CachedModelStep); "
        "the ensemble's members run as torch.baddbmm over stacked weights [K, in, out] (no "
        "per-member loop, no packed kernel). With the disagreement (statistics or threshold) "
        "every step evaluates all K members on all candidates, K times one model's FLOPs."
    )
    path = write(
        "planner_variants",
        rows,
        {
            "note": note,
            "threads": args.threads,
            "matmul_peak_gflops": peak,
            "torch_mm_peak_gflops": mm_peak,
            "packed_linear_peak_gflops": packed_peak,
            "load_average_1min": [load_before, load_after],
            "m": M,
            "h": H,
            "num_members": K,
            "command": f"python benchmarks/planner_variants.py --threads {args.threads}",
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
