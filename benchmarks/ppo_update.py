"""Seconds per thesis PPO iteration: stock ``ppo_update`` vs :class:`FusedPPOUpdate`.

    .venv/bin/python benchmarks/ppo_update.py              # HalfCheetah batch, 5 rounds
    .venv/bin/python benchmarks/ppo_update.py --synthetic  # random batch, no MuJoCo

One 2048-frame batch (collected once with the PPO actor, or random with ``--synthetic``),
4 epochs x minibatch 32, 64x64 networks, Adam 3e-4, grad clip 0.5, ``torch.set_num_threads(1)``.
The three updates run alternately (stock, fused autograd, fused manual, stock, ...) on the same
modules and batch; the table gives the median seconds per iteration and the ratio to stock,
plus where the fused (manual) iteration spends its time, each part timed on its own. Writes
benchmarks/results/ppo_update.json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _common import print_table, write
from rl_helpers import make_test_ppo

from torchrl_mbmf.objectives.fused_ppo import FusedPPOUpdate, ppo_update

ENV = "HalfCheetah-v5"


def _setup(synthetic: bool):
    torch.manual_seed(0)
    if synthetic:
        loss, gae, batch = make_test_ppo(frames=2048, obs_dim=17, action_dim=6, hidden=64)
        return loss, gae, batch, "synthetic [2048] batch (5% terminations, 5% truncations)"
    from torchrl.collectors import Collector

    from torchrl_mbmf.envs import make_env
    from torchrl_mbmf.modules import make_ppo_actor_critic

    env = make_env(ENV, seed=0)
    actor, critic = make_ppo_actor_critic(env, hidden_sizes=(64, 64))
    loss = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=0.2,
        entropy_coeff=1e-4,
        critic_coeff=0.5,
        normalize_advantage=True,
    )
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    collector = Collector(
        env, actor, frames_per_batch=2048, total_frames=-1, auto_register_policy_transforms=False
    )
    batch = next(iter(collector))
    collector.shutdown()
    return loss, gae, batch, f"{ENV} batch of the initial actor, {tuple(batch.batch_size)}"


def _breakdown(fused: FusedPPOUpdate, batch, repeats: int) -> list[dict[str, object]]:
    """Seconds per iteration of each part of the fused (manual) iteration, timed on its own."""
    steps = fused.epochs * -(-batch.numel() // fused.minibatch_size)
    data = fused._prepare(batch, True)
    flat = fused._flat_adam()
    grads = {id(p): flat.views["grad"][i] for i, p in enumerate(fused.params)}
    scalars = fused.grads.scalars()
    mb = {k: v[: fused.minibatch_size] for k, v in data.items()}
    mb["advantage"] = mb["advantage"].squeeze(-1)
    state = [p.detach().clone() for p in fused.params]

    def per_iter(fn, calls: int) -> float:
        runs = []
        for _ in range(repeats):
            start = time.perf_counter()
            for _ in range(calls):
                fn()
            runs.append((time.perf_counter() - start) / calls)
        return statistics.median(runs) * steps if calls > 1 else statistics.median(runs)

    def shuffle():
        perm = torch.randperm(data["obs"].shape[0])
        return {k: v[perm] for k, v in data.items()}

    rows = [
        (
            "GAE (critic on obs and next obs + torchrl GAE recursion)",
            per_iter(lambda: fused.advantage(batch), 1),
        ),
        (
            "prepare (GAE + pre-tanh actions, once)",
            per_iter(lambda: fused._prepare(batch, True), 1),
        ),
        ("per-epoch gather (x epochs)", per_iter(shuffle, 1) * fused.epochs),
        (
            "losses + hand-written gradients (x steps)",
            per_iter(lambda: fused.grads.manual(mb, grads, scalars), 50),
        ),
        (
            "grad clip + Adam on the flat buffer (x steps)",
            per_iter(lambda: flat.step(0.5, per_tensor_norms=False), 50),
        ),
    ]
    with torch.no_grad():
        for p, s in zip(fused.params, state, strict=True):
            p.copy_(s)
    return [{"part": name, "value": sec, "unit": "s/iter"} for name, sec in rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--synthetic", action="store_true", help="random batch, no MuJoCo")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds (default 5)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    loss, gae, batch, what = _setup(args.synthetic)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
    updates = {
        "stock ppo_update (ClipPPOLoss + GAE)": lambda b: ppo_update(loss, gae, optim, b),
        "FusedPPOUpdate(gradients='autograd') (bit-identical)": FusedPPOUpdate(
            loss, gae, optim, gradients="autograd"
        ),
        "FusedPPOUpdate() (hand-written gradients)": FusedPPOUpdate(loss, gae, optim),
    }
    times: dict[str, list[float]] = {name: [] for name in updates}
    for fn in updates.values():  # warm-up (builds the flat buffers)
        fn(batch.clone())
    for _ in range(args.rounds):
        for name, fn in updates.items():
            b = batch.clone()
            start = time.perf_counter()
            fn(b)
            times[name].append(time.perf_counter() - start)
    stock = statistics.median(next(iter(times.values())))
    rows = []
    for name, ts in times.items():
        med = statistics.median(ts)
        rows.append(
            {
                "what": name,
                "s/iter (median)": med,
                "min": min(ts),
                "max": max(ts),
                "speed-up vs stock": stock / med,
            }
        )
    print(f"{what}; 4 epochs x minibatch 32, 1 thread, {args.rounds} alternating rounds")
    print_table(rows)
    parts = _breakdown(updates["FusedPPOUpdate() (hand-written gradients)"], batch, 3)
    print("\nFusedPPOUpdate() iteration, part by part:")
    print_table(parts)
    path = write(
        "ppo_update",
        rows,
        {
            "batch": what,
            "rounds": args.rounds,
            "breakdown": parts,
            "note": "alternating in one process; ratios are the claim, absolute times drift "
            "with machine load",
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
