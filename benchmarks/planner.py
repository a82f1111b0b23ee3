"""Planner speed: ms per 15x10 plan, ours vs the previous implementation vs torchrl's CEMPlanner.

python benchmarks/planner.py               # 1 torch thread -> results/planner.json
python benchmarks/planner.py --threads 2   # -> results/planner_threads2.json
python benchmarks/planner.py --horizon 25 --previous COMMIT --batches 1 --no-collection
                                           # -> results/planner_h25.json
python benchmarks/planner.py --batches 1 --no-collection --rounds 31
                                           # the 1-state plan only -> results/planner_b1.json

Every planner plans from the same real states on the same thesis-sized model (24-500-500-19)
and PPO actor (17-64-64-6; ``--distribution``: ``normal``, the recipes' Gaussian with a tanh of
the MLP as its mean, or ``tanh_normal``, the library's default), in one process, in
alternating rounds (A B C A B C ...), so drift of a shared machine hits all of them alike;
the table gives the median over rounds of the ms per plan and the median of the per-round
ratios. Rows:

- ``ours``: ``PolicyGuidedMPCPlanner`` with its fused rollout (the default).
- ``step loop``: the same planner with ``fused_rollout = False`` (the per-step loop it is
  tested against; bit-identical results).
- ``previous (COMMIT)``: ``PolicyGuidedMPCPlanner`` of each commit of ``--previous`` (default:
  the last one before the fused rollout, and the last one before the shared MLP helper and
  the reused noise buffer), imported from git under a private package name (every file of
  the planners' package at that commit). Skipped outside a git checkout. The speedup column
  is against the last of them.
- ``torchrl CEMPlanner(optim_steps=1, top_k=1)`` on the same learned env (per state in turn
  for ``B > 1``: its dims assume an unbatched env).

The FLOP floor divides a plan's multiply-add count by the higher of two float32 matmul peaks
measured in the same run (``torch.mm`` and oneDNN's linear with pre-packed weights). The
1-minute load average is recorded: on a shared machine compare runs only at similar load.
"""

from __future__ import annotations

import argparse
import importlib
import itertools
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.modules.planners import CEMPlanner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import matmul_peak_gflops, print_table, time_call, write

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_half_cheetah_env
from torchrl_mbmf.modules import DeltaDynamicsModel, PolicyGuidedMPCPlanner, make_ppo_actor_critic

M, H = 15, 10
PREVIOUS = ("1848f94", "c0ad5c2")  # before the fused rollout; before the MLP helper
ROOT = Path(__file__).resolve().parents[1]
PLANNERS = "torchrl_mbmf/modules/planners"


def plan_flops(
    model: DeltaDynamicsModel, actor_cells=(64, 64), obs_dim=17, act_dim=6, horizon: int = H
) -> int:
    """Multiply-add FLOPs of one plan (model + policy MLPs, m x h forward passes)."""
    dims = [model.state_dim + model.action_dim, *model.hidden_sizes, model.state_dim + 1]
    model_f = sum(2 * a * b for a, b in itertools.pairwise(dims))
    adims = [obs_dim, *actor_cells, act_dim]
    actor_f = sum(2 * a * b for a, b in itertools.pairwise(adims))
    return M * horizon * (model_f + actor_f)


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


def previous_planner_class(commit: str) -> type | None:
    """``PolicyGuidedMPCPlanner`` as of ``commit``, imported under a private package name."""
    package = f"planners_at_{commit}"
    tmp = Path(tempfile.mkdtemp())
    try:
        listing = subprocess.run(
            ["git", "-C", str(ROOT), "ls-tree", "--name-only", commit, PLANNERS + "/"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()
        names = [Path(f).stem for f in listing if f.endswith(".py") and not f.endswith("__.py")]
        (tmp / package).mkdir()
        (tmp / package / "__init__.py").write_text("")
        for name in names:
            src = subprocess.run(
                [
                    "git",
                    "-C",
                    str(ROOT),
                    "show",
                    f"{commit}:{PLANNERS}/{name}.py",
                ],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            src = src.replace("torchrl_mbmf.modules.planners.", f"{package}.")
            (tmp / package / f"{name}.py").write_text(src)
        sys.path.insert(0, str(tmp))
        try:
            return importlib.import_module(f"{package}.policy_guided").PolicyGuidedMPCPlanner
        finally:
            sys.path.remove(str(tmp))
    except (OSError, subprocess.CalledProcessError) as err:
        print(f"previous implementation {commit} not available ({err}); skipped")
        return None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def alternate(calls: dict[str, object], *, rounds: int, number: int) -> dict[str, list[float]]:
    """Seconds per call of each function, ``rounds`` times in turn (``number`` calls each)."""
    for fn in calls.values():
        for _ in range(max(3, number // 4)):
            fn()
    times = {name: [] for name in calls}
    for _ in range(rounds):
        for name, fn in calls.items():
            start = time.perf_counter()
            for _ in range(number):
                fn()
            times[name].append((time.perf_counter() - start) / number)
    return times


def collection_fps(num_envs: int, frames: int, distribution: str, horizon: int) -> float:
    real = make_half_cheetah_env(num_envs=num_envs, seed=0)
    actor, _ = make_ppo_actor_critic(real, distribution=distribution)
    env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6), real)
    planner = PolicyGuidedMPCPlanner(env, actor, num_candidates=M, horizon=horizon)
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
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument(
        "--previous", nargs="*", default=list(PREVIOUS), help="commits of previous planners"
    )
    parser.add_argument("--rounds", type=int, default=15, help="alternating rounds")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--no-collection", action="store_true", help="skip the Collector rows")
    parser.add_argument("--horizon", type=int, default=H, help=f"plan horizon (default {H})")
    parser.add_argument(
        "--distribution",
        choices=("normal", "tanh_normal"),
        default="normal",
        help="the PPO actor's distribution (default: normal, the recipes' actor)",
    )
    args = parser.parse_args()
    h = args.horizon
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load_before = os.getloadavg()[0]
    mm_peak = matmul_peak_gflops()
    packed_peak = packed_linear_peak_gflops()
    peak = max(mm_peak, packed_peak)
    real = make_half_cheetah_env(seed=0)
    actor, _ = make_ppo_actor_critic(real, distribution=args.distribution)
    model = DeltaDynamicsModel(18, 6)
    data = torch.randn(256, 18)
    model.fit_normalizer(
        data, torch.rand(256, 6) * 2 - 1, data + 0.1 * torch.randn(256, 18), torch.randn(256)
    )
    env = LearnedDynamicsEnv(model, real)
    flops = plan_flops(model, horizon=h)
    previous = {c: previous_planner_class(c) for c in args.previous}
    previous = {c: cls for c, cls in previous.items() if cls is not None}
    ours = PolicyGuidedMPCPlanner(env, actor, num_candidates=M, horizon=h)
    step_loop = PolicyGuidedMPCPlanner(env, actor, num_candidates=M, horizon=h)
    step_loop.fused_rollout = False
    planners: dict[str, object] = {"ours": ours, "step loop": step_loop}
    for commit, cls in previous.items():
        planners[f"previous ({commit})"] = cls(env, actor, num_candidates=M, horizon=h)
    cem = CEMPlanner(env, planning_horizon=h, optim_steps=1, num_candidates=M, top_k=1)
    rows = []
    for batch in args.batches:
        real_b = make_half_cheetah_env(num_envs=batch, seed=0) if batch > 1 else real
        td = real_b.rollout(3)[..., -1] if batch > 1 else real.rollout(3)[-1]
        calls = {name: (lambda p=p, td=td: p(td)) for name, p in planners.items()}
        if batch == 1:
            calls["torchrl CEMPlanner(optim_steps=1)"] = lambda td=td: cem(td)
        elif batch == max(args.batches):
            # CEMPlanner's dims assume an unbatched env spec: plan each state in turn
            parts = [td[i].clone() for i in range(batch)]
            calls["torchrl CEMPlanner(optim_steps=1)"] = lambda parts=parts: [cem(p) for p in parts]
        with torch.no_grad():
            times = alternate(calls, rounds=args.rounds, number=max(5, 40 // batch))
        olds = [n for n in times if n.startswith("previous")]
        ref = olds[-1] if olds else "step loop"
        floor = batch * flops / (peak * 1e9)
        for name, sec in times.items():
            ratio = [r / s for r, s in zip(times[ref], sec, strict=True)]
            ours_ratio = [s / o for s, o in zip(sec, times["ours"], strict=True)]
            rows.append(
                {
                    "planner": name,
                    "states": batch,
                    "ms_per_plan": statistics.median(sec) * 1e3,
                    "ms_min": min(sec) * 1e3,
                    f"speedup_vs_{ref.split()[0]}": statistics.median(ratio),
                    "x_ours": statistics.median(ours_ratio),
                    "floor_ms": floor * 1e3,
                    "x_floor": statistics.median(sec) / floor,
                }
            )
    if not args.no_collection:
        for n in (1, 8):
            fps = collection_fps(n, 1024 if n > 1 else 512, args.distribution, h)
            rows.append(
                {"planner": f"PPO-MPC Collector, {n} env(s)", "states": n, "frames_per_s": fps}
            )
    load_after = os.getloadavg()[0]
    print(
        f"matmul peak: torch.mm {mm_peak:.1f}, packed oneDNN linear {packed_peak:.1f} GFLOP/s; "
        f"plan cost {flops / 1e6:.1f} MFLOP per state; load average {load_before:.1f} -> "
        f"{load_after:.1f} on {os.cpu_count()} cores; {args.rounds} alternating rounds"
    )
    print_table(rows)
    name = "planner" + (f"_h{h}" if h != H else "")
    name += "_b1" if args.batches == [1] and args.no_collection and h == H else ""
    name += f"_threads{args.threads}" if args.threads != 1 else ""
    name += f"_{args.distribution}" if args.distribution != "normal" else ""
    path = write(
        name,
        rows,
        {
            "command": " ".join(["python benchmarks/planner.py", *sys.argv[1:]]),
            "actor_distribution": args.distribution,
            "previous_commits": list(previous),
            "speedup_reference": ref if args.batches else None,
            "matmul_peak_gflops": peak,
            "torch_mm_peak_gflops": mm_peak,
            "packed_linear_peak_gflops": packed_peak,
            "load_average_1min": [load_before, load_after],
            "plan_mflop_per_state": flops / 1e6,
            "m": M,
            "h": h,
            "rounds": args.rounds,
            "targets": {"ms_per_plan_1_state_1_thread": 1.5},
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
