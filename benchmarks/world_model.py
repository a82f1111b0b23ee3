"""World-model costs: fit throughput before/after, warm-refit epochs, learned-env step cost.

python benchmarks/world_model.py                          # 20k random HalfCheetah steps
python benchmarks/world_model.py --data DIR [DIR ...]     # saved TransitionDatasets, in order
python benchmarks/world_model.py --data ... --sizes 100000 200000 400000 --warm-refits

Fit throughput ("fit" rows, ``results/world_model_fit.json``): seconds per epoch and
samples/s of the thesis fit (24 -> 500 -> 500 -> 19, Adam lr 1e-4, batch 512) at each size,
measured in one process, alternating the variants, in CPU seconds of the process
(``time.process_time``: on a shared, overloaded machine the wall time mostly measures the
waits for a core; both are written). The variants: ``before`` is the fit loop as it was
before the speed work (a per-minibatch index gather, the stock ``net(x)``, the stock Adam;
kept below as :func:`reference_fit`); ``autograd step`` is :func:`fit_dynamics` with its
minibatch loss through autograd (the loop before ``FusedMSEGradient``); ``fused step`` is
:func:`fit_dynamics` as it stands (bit-identical to both, checked here); ``+ fused Adam`` adds
``dynamics_optimizer(fused_adam=True)`` (opt-in: float rounding differs); ``2 threads`` is
the fused step with ``torch.set_num_threads(2)`` (compare its wall time, on an idle machine
only). The step rows time one minibatch step of each, and ``matmuls only``: the step's eight
matrix products alone, the floor of any loop that keeps them. Each timed fit runs
``--epochs`` full epochs without early stopping; its time includes the fit's setup (split,
scaler, scaling) and the held-out evaluations, amortised over those epochs.

Warm refits (``--warm-refits``): the PPO-MPC run's schedule in miniature: a first fit on the
first ``--initial`` transitions (the random-policy data), then a refit at each size that
continues from the current weights and Adam state, each with the thesis' early stopping
(patience 10, up to 200 epochs). Reported: epochs until early stopping, best epoch, held-out
loss, and what a cap of K refit epochs would have kept: a capped refit is exactly the first K
epochs of the uncapped one (same split, same minibatch order), so its kept held-out loss is
the best of those K epochs.

With fewer stored transitions than a size, the set is grown with copies of the data whose
states (and next states, by the same offset) are perturbed by 1% of each state dimension's
standard deviation: real-looking transitions, but not new experience.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import matmul_peak_gflops, print_table, time_call, write

import torchrl_mbmf.world_model.fit as fit_module
from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
from torchrl_mbmf.envs import LearnedDynamicsEnv, make_half_cheetah_env
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives import DynamicsLoss
from torchrl_mbmf.world_model import fit_dynamics
from torchrl_mbmf.world_model.fit import dynamics_optimizer
from torchrl_mbmf.world_model.fused_step import FusedMSEGradient

NOTE = (
    "2 shared vCPUs with other jobs running at the same time (load average far above 2): "
    "absolute times are noisy and slow, compare the ratios of rows measured in alternation"
)
#: fwd + bwd + Adam FLOP of one sample of the thesis network (3 matmuls per layer but the
#: input gradient of the first).
FLOP_PER_SAMPLE = 2 * (24 * 500 * 2 + 500 * 500 * 3 + 500 * 19 * 3)


def load_transitions(paths: list[str]) -> TensorDict:
    """The transitions of saved datasets, concatenated in order, as one ``[N]`` TensorDict."""
    parts = []
    for path in paths:
        td = TransitionDataset.load(path).tensors()
        parts.append(
            TensorDict(
                state=td["state"].clone(),
                action=td["action"].clone(),
                next=TensorDict(
                    state=td["next", "state"].clone(),
                    reward=td["next", "reward"].clone(),
                    done=td["next", "done"].clone(),
                    batch_size=td.batch_size,
                ),
                batch_size=td.batch_size,
            )
        )
    return torch.cat(parts)


def grow(data: TensorDict, size: int, seed: int = 0) -> TensorDict:
    """The first ``size`` transitions, extended with perturbed copies if there are fewer."""
    if size <= data.shape[0]:
        return data[:size]
    g = torch.Generator().manual_seed(seed)
    std = data["state"].std(0)
    parts, have = [data], data.shape[0]
    while have < size:
        offset = 0.01 * std * torch.randn(data.shape[0], std.shape[0], generator=g)
        extra = data.clone()
        extra["state"] += offset
        extra["next", "state"] += offset
        parts.append(extra)
        have += data.shape[0]
    return torch.cat(parts)[:size]


class _NoFusedStep:
    """Stands in for ``FusedMSEGradient`` in :func:`autograd_step`: no network is fused."""

    @staticmethod
    def for_net(net: torch.nn.Module) -> None:
        return None


@contextlib.contextmanager
def autograd_step():
    """:func:`fit_dynamics` with its minibatch loss through autograd (before the fused step)."""
    fit_module.FusedMSEGradient = _NoFusedStep
    try:
        yield
    finally:
        fit_module.FusedMSEGradient = FusedMSEGradient


def reference_fit(
    model: DeltaDynamicsModel,
    data: TensorDictBase,
    optimizer: torch.optim.Optimizer,
    *,
    max_epochs: int,
    seed: int,
    batch_size: int = 512,
    patience: int = 10,
) -> list[float]:
    """The fit loop before the speed work (one-step, early stopping on the held-out MSE)."""
    s, a = data["state"].float(), data["action"].float()
    nxt, r = data["next", "state"].float(), data["next", "reward"].float().reshape(-1, 1)
    for value in (s, a, nxt, r):  # fit_dynamics' NaN check
        if not torch.isfinite(value).all():
            raise ValueError("non-finite transitions")
    n = s.shape[0]
    n_val = max(1, round(n * 0.1))
    gen = torch.Generator().manual_seed(seed)
    perm = torch.randperm(n, generator=gen)
    val_idx, train_idx = perm[:n_val], perm[n_val:]
    model.fit_normalizer(s[train_idx], a[train_idx], nxt[train_idx], r[train_idx])
    loss_module = DynamicsLoss(model)
    with torch.no_grad():
        x, y = loss_module.scaled_pairs(s, a, nxt, r)
    train_x, train_y, val_x, val_y = x[train_idx], y[train_idx], x[val_idx], y[val_idx]

    def val_loss() -> float:
        with torch.no_grad():
            return float(F.mse_loss(model.net(val_x), val_y))

    best, best_state, bad, losses = val_loss(), copy.deepcopy(model.state_dict()), 0, []
    n_train = train_x.shape[0]
    for _ in range(max_epochs):
        order = torch.randperm(n_train, generator=gen)
        total = torch.zeros(())
        for i in range(0, n_train, batch_size):
            idx = order[i : i + batch_size]
            loss = F.mse_loss(model.net(train_x[idx]), train_y[idx])
            total += loss.detach() * idx.numel()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        current = val_loss()
        losses.append(current)
        if current < best:
            best, bad, best_state = current, 0, copy.deepcopy(model.state_dict())
        else:
            bad += 1
            if bad >= patience:
                break
    model.load_state_dict(best_state)
    return losses


STEP_VARIANTS = ("before", "autograd step", "fused step", "fused step + fused Adam", "matmuls only")
FIT_VARIANTS = ("before", "autograd step", "fused step", "fused step + fused Adam", "2 threads")


def matmuls(x: torch.Tensor, weights: list[torch.Tensor]) -> None:
    """The eight matrix products of one step of the 3-layer network (forward and backward)."""
    w1, b1, w2, b2, w3, b3 = weights
    h1 = torch.addmm(b1, x, w1.t())
    h2 = torch.addmm(b2, h1, w2.t())
    out = torch.addmm(b3, h2, w3.t())
    g2 = out.mm(w3)
    torch.mm(out.t(), h2)
    torch.mm(g2.t(), h1)
    torch.mm(g2.mm(w2).t(), x)


def step_rows(data: TensorDict, rounds: int, block: int) -> list[dict]:
    """One minibatch step (batch 512) of each fit loop, alternated in blocks of ``block`` steps.

    The rows give CPU time (see the module docstring) and the wall time.

    Finer-grained than whole fits, so slow drifts of a shared machine's load hit the variants
    alike; the ratio of each round's block times is taken before the median.
    """
    torch.manual_seed(0)
    base = DeltaDynamicsModel(18, 6)
    s, a = data["state"], data["action"]
    nxt, r = data["next", "state"], data["next", "reward"].reshape(-1, 1)
    base.fit_normalizer(s, a, nxt, r)
    x, y = DynamicsLoss(base).scaled_pairs(s, a, nxt, r)
    n = (x.shape[0] // 512) * 512
    order = torch.randperm(x.shape[0])[:n]
    xs, ys = x[order], y[order]
    steps = {}
    for what in STEP_VARIANTS:
        model = copy.deepcopy(base)
        loss_module = DynamicsLoss(model)
        optimizer = dynamics_optimizer(model, fused_adam=what.endswith("fused Adam"))
        fused = FusedMSEGradient.for_net(model.net)
        weights = [p.detach() for p in model.net.parameters()]

        def step(
            i,
            what=what,
            model=model,
            loss_module=loss_module,
            optimizer=optimizer,
            fused=fused,
            weights=weights,
        ):
            j = (i * 512) % n
            if what == "before":
                idx = order[j : j + 512]
                loss = F.mse_loss(model.net(x[idx]), y[idx])
            elif what.startswith("fused"):
                fused.loss_and_grad(xs[j : j + 512], ys[j : j + 512])
                optimizer.step()
                return
            elif what == "matmuls only":
                matmuls(xs[j : j + 512], weights)
                return
            else:
                loss = loss_module.scaled_loss(xs[j : j + 512], ys[j : j + 512])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        steps[what] = step
    times: dict[str, list[float]] = {k: [] for k in steps}
    walls: dict[str, list[float]] = {k: [] for k in steps}
    for r_ in range(rounds + 1):
        for what, step in steps.items():
            start, wall = time.process_time(), time.perf_counter()
            for i in range(block):
                step(r_ * block + i)
            if r_ > 0:  # round 0 warms up
                times[what].append((time.process_time() - start) / block)
                walls[what].append((time.perf_counter() - wall) / block)
    rows = []
    for what, values in times.items():
        ratio = statistics.median(b / v for b, v in zip(times["before"], values, strict=True))
        sec = statistics.median(values)
        rows.append(
            {
                "what": f"step: {what}",
                "batch": 512,
                "cpu_ms": sec * 1e3,
                "wall_ms": statistics.median(walls[what]) * 1e3,
                "cpu_us_per_sample": sec / 512 * 1e6,
                "speedup": ratio,
                "GFLOP_per_cpu_s": 512 * FLOP_PER_SAMPLE / sec / 1e9,
                "runs": len(values),
            }
        )
    print_table(rows)
    return rows


def fit_rows(data: TensorDict, sizes: list[int], epochs: int, repeats: int) -> list[dict]:
    """Seconds per epoch of each of :data:`FIT_VARIANTS`, alternated, at each size."""
    rows = []
    torch.manual_seed(0)
    base = DeltaDynamicsModel(18, 6)
    threads = torch.get_num_threads()
    for size in sizes:
        subset = grow(data, size)
        n_train = size - max(1, round(size * 0.1))
        times: dict[str, list[float]] = {k: [] for k in FIT_VARIANTS}
        walls: dict[str, list[float]] = {k: [] for k in times}
        identical = dict.fromkeys(times, True)
        for rep in range(repeats):
            weights = {}
            for what in times:
                model = copy.deepcopy(base)
                optimizer = dynamics_optimizer(model, fused_adam=what.endswith("fused Adam"))
                torch.set_num_threads(2 if what == "2 threads" else threads)
                start, wall = time.process_time(), time.perf_counter()
                if what == "before":
                    reference_fit(model, subset, optimizer, max_epochs=epochs, seed=rep)
                else:
                    kwargs = {"optimizer": optimizer, "max_epochs": epochs, "patience": epochs}
                    with autograd_step() if what == "autograd step" else contextlib.nullcontext():
                        fit_dynamics(model, subset, seed=rep, **kwargs)
                times[what].append((time.process_time() - start) / epochs)
                walls[what].append((time.perf_counter() - wall) / epochs)
                torch.set_num_threads(threads)
                weights[what] = model.state_dict()
            for what, state in weights.items():
                identical[what] &= all(
                    torch.equal(weights["before"][k], v) for k, v in state.items()
                )
        before = statistics.median(times["before"])
        before_wall = statistics.median(walls["before"])
        for what, values in times.items():
            sec = statistics.median(values)
            rows.append(
                {
                    "what": what,
                    "transitions": size,
                    "cpu_s_per_epoch": sec,
                    "wall_s_per_epoch": statistics.median(walls[what]),
                    "cpu_us_per_transition": sec / n_train * 1e6,
                    "wall_us_per_transition": statistics.median(walls[what]) / n_train * 1e6,
                    "speedup": before / sec,
                    "wall_speedup": before_wall / statistics.median(walls[what]),
                    "GFLOP_per_cpu_s": n_train * FLOP_PER_SAMPLE / sec / 1e9,
                    "bit_identical_to_before": identical[what],
                    "runs": len(values),
                }
            )
        print_table(rows[-len(times) :])
    return rows


def warm_refits(data: TensorDict, initial: int, sizes: list[int], initial_epochs: int) -> dict:
    """Epochs to early stopping of refits that continue from the previous fit."""
    torch.manual_seed(0)
    model = DeltaDynamicsModel(18, 6)
    optimizer = dynamics_optimizer(model)
    out = {"initial": initial, "initial_epochs": initial_epochs, "refits": []}
    first = fit_dynamics(
        model, data[:initial], optimizer=optimizer, max_epochs=initial_epochs, seed=0
    )
    out["initial_fit"] = {"epochs": first.epochs, "best_val_loss": first.best_val_loss}
    print(f"initial fit on {initial}: {first.epochs} epochs, val {first.best_val_loss:.4f}")
    for i, size in enumerate(sizes):
        history = fit_dynamics(model, grow(data, size), optimizer=optimizer, seed=i + 1)
        caps = {str(k): min(history.val_loss[:k]) for k in (5, 10, 20, 50) if k < history.epochs}
        row = {
            "transitions": size,
            "epochs": history.epochs,
            "best_epoch": history.best_epoch,
            "stopped_early": history.stopped_early,
            "best_val_loss": history.best_val_loss,
            "first_epoch_val_loss": history.val_loss[0],
            "capped_best_val_loss": caps,
            "seconds": history.seconds,
            "s_per_epoch": history.seconds / history.epochs,
            "val_loss": history.val_loss,
        }
        out["refits"].append(row)
        print({k: v for k, v in row.items() if k != "val_loss"}, flush=True)
        write(
            "world_model_warm_refits",
            out["refits"],
            {k: v for k, v in out.items() if k != "refits"},
        )
    return out


def env_rows(model: DeltaDynamicsModel) -> list[dict]:
    """Learned-env step cost at batch 1/15/120 (tensordict step, tensor predict, fused)."""
    real = make_half_cheetah_env(seed=0)
    env = LearnedDynamicsEnv(model, real)
    fused = env.fast_predictor()
    rows = []
    for batch in (1, 15, 120):
        td = env.reset(real.reset().expand(batch).clone())
        td["action"] = torch.rand(batch, 6) * 2 - 1
        state, action = td["state"], td["action"]
        with torch.no_grad():
            t_env = time_call(lambda td=td: env.step(td.clone()), repeats=5, number=100)
            t_pred = time_call(lambda s=state, a=action: env.predict(s, a), repeats=5, number=200)
            t_fused = time_call(lambda s=state, a=action: fused(s, a), repeats=5, number=200)
        for what, sec in (
            ("LearnedDynamicsEnv.step (tensordict)", t_env),
            ("LearnedDynamicsEnv.predict (tensors)", t_pred),
            ("fast_predictor (folded scaling)", t_fused),
        ):
            rows.append(
                {"what": what, "batch": batch, "ms": sec * 1e3, "samples_per_s": batch / sec}
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="*", default=[], help="saved TransitionDataset folders")
    parser.add_argument("--sizes", nargs="*", type=int, default=[20_000])
    parser.add_argument("--epochs", type=int, default=2, help="timed epochs per fit")
    parser.add_argument("--repeats", type=int, default=2, help="A B C rounds per size")
    parser.add_argument("--step-rounds", type=int, default=10, help="A B C rounds of steps")
    parser.add_argument("--step-block", type=int, default=10, help="steps per block")
    parser.add_argument("--warm-refits", action="store_true")
    parser.add_argument("--initial", type=int, default=10_000)
    parser.add_argument("--initial-epochs", type=int, default=200)
    parser.add_argument("--skip-fit-rows", action="store_true")
    parser.add_argument("--skip-env", action="store_true")
    parser.add_argument("--out", default="world_model_fit", help="JSON name of the fit rows")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.data:
        data = load_transitions(args.data)
    else:
        env = make_half_cheetah_env(seed=0)
        ds = collect_random_transitions(env, max([*args.sizes, args.initial]), seed=0)
        with tempfile.TemporaryDirectory() as tmp:
            data = load_transitions([str(ds.save(Path(tmp) / "data"))])
    extra = {
        "model": "18+6 -> 500 -> 500 -> 19, batch 512, Adam lr 1e-4",
        "note": NOTE,
        "data": [Path(p).name for p in args.data] or ["random"],
        "stored_transitions": data.shape[0],
        "flop_per_sample": FLOP_PER_SAMPLE,
    }
    if not args.skip_fit_rows:
        extra["matmul_peak_gflops_before"] = matmul_peak_gflops()
        rows = step_rows(data, args.step_rounds, args.step_block)
        rows += fit_rows(data, args.sizes, args.epochs, args.repeats)
        extra["matmul_peak_gflops_after"] = matmul_peak_gflops()
        print_table(rows)
        print(f"wrote {write(args.out, rows, extra)}")
    if args.warm_refits:
        warm_refits(data, args.initial, args.sizes, args.initial_epochs)
    if not args.skip_env:
        model = DeltaDynamicsModel(18, 6)
        model.fit_normalizer(
            data["state"], data["action"], data["next", "state"], data["next", "reward"]
        )
        rows = env_rows(model)
        print_table(rows)
        print(f"wrote {write('world_model', rows, {'model': extra['model'], 'note': NOTE})}")


if __name__ == "__main__":
    main()
