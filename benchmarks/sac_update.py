"""SAC update and replay sampling costs at one thread: stock SACLoss vs the fused updates.

    .venv/bin/python benchmarks/sac_update.py            # ~2 minutes
    .venv/bin/python benchmarks/sac_update.py --rounds 4 # quicker

One SAC update at the training sizes (batch 256, 256x256 ReLU actor and two Q-networks,
HalfCheetah's 17-d observations and 6-d actions, SoftUpdate, Adam): the stock ``SACLoss`` step,
the autograd fused step (``FusedSACUpdate.losses`` + one backward, the previous fused update),
and ``FusedSACUpdate`` (hand-written Q backward), each with torch's default (for-loop) Adam and
with ``Adam(fused=True)``. The variants run alternately in the same process, ``rounds`` times
``number`` updates each; a row is the median over rounds of the main thread's CPU time per
update (``time.thread_time``: on a shared machine it leaves out the time spent waiting for a
core; wall time is reported too). A same-process GEMM rate gives the FLOP floor of an update.

Writes benchmarks/results/sac_update.json (sac_update_keep_freed_memory.json with
--keep-freed-memory, which first calls ``keep_freed_memory()``) and prints a table.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import SoftUpdate

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _common import print_table, write
from rl_helpers import make_test_sac_loss

from torchrl_mbmf.data import ReplaySampler
from torchrl_mbmf.device import keep_freed_memory
from torchrl_mbmf.objectives.fused_sac import FusedSACUpdate, sac_update_step

OBS, ACT, HIDDEN, BATCH = 17, 6, 256, 256


def _autograd_fused(step: FusedSACUpdate) -> Callable[[TensorDict], object]:
    """The previous fused update: ``losses`` (batched-matmul Q, autograd) and one backward."""

    def run(batch: TensorDict) -> object:
        obs, action, reward, next_obs, terminated = (batch.get(k) for k in step.batch_keys)
        actor, qvalue, alpha, _ = step.losses(
            obs, action, reward.squeeze(-1), next_obs, terminated.squeeze(-1)
        )
        step.optimizer.zero_grad(set_to_none=True)
        (actor + qvalue + alpha).backward()
        step.optimizer.step()
        step.target_updater.step()
        return qvalue.detach()

    return run


def _variant(kind: str, adam: str) -> tuple[Callable[[TensorDict], object], TensorDict]:
    torch.manual_seed(0)
    loss, batch = make_test_sac_loss(
        batch_size=BATCH, obs_dim=OBS, action_dim=ACT, hidden=HIDDEN, activation=nn.ReLU
    )
    kwargs = {"fused": True} if adam == "fused" else {}
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4, **kwargs)
    updater = SoftUpdate(loss, tau=0.005)
    if kind == "stock SACLoss":
        return sac_update_step(loss, optim, updater), batch
    fused = FusedSACUpdate(loss, optim, updater)
    if kind == "fused, autograd (old)":
        return _autograd_fused(fused), batch
    return fused, batch


def update_flops() -> float:
    """Multiply-add FLOPs of one update (matmuls only)."""
    q = OBS + ACT
    q_fwd = 2 * BATCH * (q * HIDDEN + HIDDEN * HIDDEN + HIDDEN)  # one Q-network, B rows
    a_fwd = 2 * BATCH * (OBS * HIDDEN + HIDDEN * HIDDEN + HIDDEN * 2 * ACT)
    forward = 2 * 3 * q_fwd + 2 * a_fwd  # target, replayed and new-action Q; two actor passes
    # Q loss: weight gradients and hidden input gradients; actor: dQ/d(action) only
    q_bwd = 2 * (2 * q_fwd - 2 * BATCH * q * HIDDEN) + 2 * (q_fwd - 2 * BATCH * OBS * HIDDEN)
    a_bwd = 2 * a_fwd - 2 * BATCH * OBS * HIDDEN
    return float(forward + q_bwd + a_bwd)


def gemm_rate(repeats: int = 7) -> float:
    """FLOP/s of a 256x256x256 matmul on this thread (best of ``repeats``)."""
    a, b = torch.randn(BATCH, HIDDEN), torch.randn(HIDDEN, HIDDEN)
    best = float("inf")
    for _ in range(repeats):
        start = time.thread_time()
        for _ in range(50):
            torch.mm(a, b)
        best = min(best, (time.thread_time() - start) / 50)
    return 2 * BATCH * HIDDEN * HIDDEN / best


def alternate(
    fns: dict[str, Callable[[], object]], rounds: int, number: int
) -> dict[str, dict[str, float]]:
    """Median CPU and wall ms per call of each function, run in alternating rounds."""
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    wall: dict[str, list[float]] = {k: [] for k in fns}
    for fn in fns.values():
        for _ in range(max(3, number // 5)):
            fn()
    for _ in range(rounds):
        for name, fn in fns.items():
            t_cpu, t_wall = time.thread_time(), time.perf_counter()
            for _ in range(number):
                fn()
            cpu[name].append((time.thread_time() - t_cpu) / number * 1e3)
            wall[name].append((time.perf_counter() - t_wall) / number * 1e3)
    return {
        k: {
            "cpu": statistics.median(cpu[k]),
            "wall": statistics.median(wall[k]),
            "min": min(cpu[k]),
        }
        for k in fns
    }


def bench_updates(rounds: int, number: int) -> list[dict[str, object]]:
    fns = {}
    for kind in ("stock SACLoss", "fused, autograd (old)", "fused"):
        for adam in ("default", "fused"):
            step, batch = _variant(kind, adam)
            fns[f"SAC update: {kind}, Adam {adam}"] = lambda s=step, b=batch: s(b)
    times = alternate(fns, rounds, number)
    ref = times["SAC update: stock SACLoss, Adam default"]["cpu"]
    rows = []
    for name, t in times.items():
        rows.append(
            {
                "what": name,
                "value": t["cpu"],
                "unit": "ms (cpu)",
                "min": t["min"],
                "wall": t["wall"],
                "vs stock": ref / t["cpu"],
            }
        )
    return rows


def bench_sampling(rounds: int, number: int) -> list[dict[str, object]]:
    torch.manual_seed(0)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(1_000_000), batch_size=BATCH)
    _, chunk = make_test_sac_loss(batch_size=20_000, obs_dim=OBS, action_dim=ACT)
    buffer.extend(chunk)
    loss, _ = make_test_sac_loss(obs_dim=OBS, action_dim=ACT)
    keys = FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), SoftUpdate(loss, tau=0.1))
    sampler = ReplaySampler(buffer, keys.batch_keys)
    times = alternate(
        {
            "replay sample 256 (20k of 1e6 rows): TensorDictReplayBuffer.sample()": buffer.sample,
            "replay sample 256 (20k of 1e6 rows): ReplaySampler": sampler,
        },
        rounds,
        number,
    )
    ref = next(iter(times.values()))["cpu"]
    return [
        {
            "what": k,
            "value": t["cpu"],
            "unit": "ms (cpu)",
            "min": t["min"],
            "wall": t["wall"],
            "vs stock": ref / t["cpu"],
        }
        for k, t in times.items()
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rounds", type=int, default=8, help="alternating rounds (default 8)")
    parser.add_argument("--number", type=int, default=20, help="updates per round (default 20)")
    parser.add_argument(
        "--keep-freed-memory",
        action="store_true",
        help="call keep_freed_memory() first (process-wide malloc setting; separate JSON)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.keep_freed_memory and not keep_freed_memory():
        raise SystemExit("keep_freed_memory() could not apply the malloc settings here")
    rate = gemm_rate()
    rows = bench_updates(args.rounds, args.number)
    rows += bench_sampling(args.rounds, 10 * args.number)
    rate = max(rate, gemm_rate())
    floor = update_flops() / rate * 1e3
    rows.append(
        {"what": "GEMM rate 256^3, this thread (best)", "value": rate / 1e9, "unit": "GFLOP/s"}
    )
    rows.append({"what": "update FLOP floor at that rate", "value": floor, "unit": "ms"})
    for row in rows:
        if row["what"].startswith("SAC update"):
            row["x floor"] = row["value"] / floor
    note = (
        "One thread (torch.set_num_threads(1)); the machine (2 vCPU) was shared with other jobs: "
        "CPU time of the main thread is reported (waits for a core are left out, but a busy "
        "sibling core still slows the arithmetic), so compare the ratios ('vs stock', 'x floor') "
        "rather than the absolute numbers."
    )
    name = "sac_update_keep_freed_memory" if args.keep_freed_memory else "sac_update"
    extra = {"note": note, "rounds": args.rounds, "number": args.number}
    path = write(name, rows, {**extra, "keep_freed_memory": args.keep_freed_memory})
    print_table(rows)
    print(note)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
