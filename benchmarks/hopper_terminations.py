"""Hopper-v5: random-shooting MPC with termination-aware scoring against the same without it.

python benchmarks/hopper_terminations.py            # -> results/hopper_terminations.json

For each seed: ``--random-steps`` uniform-random real steps (10,000) fit one world model
(the thesis network 15-500-500-13 and fit: Adam 1e-4, batch 512, up to 200 epochs, early
stopping); then ``RandomShootingMPCPlanner`` (``m = 100`` candidates, ``h = 10``) runs
``--episodes`` real episodes (5, at most 1,000 steps each) twice on that same model, from the
same initial states: once with the learned env's default termination rule (Hopper's health
conditions: a candidate's score stops at its first predicted fall) and once with
``termination_fn`` never terminating (the score sums all ``h`` predicted rewards, as before
terminations were handled). The table gives, per variant, the mean over seeds of the mean
episode length and return (the real env's own return, healthy reward included), with the
standard deviation over seeds; the JSON keeps every episode. The state is the Gymnasium
observation with the x position first (``exclude_current_positions_from_observation=False``);
the planner reads the state, the model predicts its delta and the reward.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import print_table, write

from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
from torchrl_mbmf.envs.terminations import NeverTerminates
from torchrl_mbmf.modules import DeltaDynamicsModel, RandomShootingMPCPlanner
from torchrl_mbmf.world_model import fit_dynamics

ENV_ID = "Hopper-v5"
KWARGS = {"exclude_current_positions_from_observation": False}


def run_seed(seed: int, args: argparse.Namespace) -> dict[str, object]:
    torch.manual_seed(seed)
    real = make_gym_state_env(ENV_ID, seed=seed, **KWARGS)
    start = time.perf_counter()
    data = collect_random_transitions(real, args.random_steps, seed=seed)
    state_dim = real.full_observation_spec_unbatched["state"].shape[-1]
    action_dim = real.full_action_spec_unbatched["action"].shape[-1]
    model = DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=tuple(args.hidden))
    # the learned env adopts the env's action bounds before the fit sees any action
    envs = {
        "terminations": LearnedDynamicsEnv(model, real),
        "no terminations": LearnedDynamicsEnv(model, real, termination_fn=NeverTerminates()),
    }
    history = fit_dynamics(model, data, seed=seed, max_epochs=args.max_epochs)
    fit_s = time.perf_counter() - start
    out: dict[str, object] = {
        "seed": seed,
        "fit_seconds": fit_s,
        "best_val_loss": float(min(history.val_loss)),
        "epochs": len(history.val_loss),
        "episodes": {},
    }
    for name, model_env in envs.items():
        planner = RandomShootingMPCPlanner(
            model_env, num_candidates=args.candidates, horizon=args.horizon
        )
        episodes = []
        for ep in range(args.episodes):
            real.set_seed(1000 * seed + ep)  # same initial state for both variants
            torch.manual_seed(1000 * seed + ep)
            t0 = time.perf_counter()
            with set_exploration_type(ExplorationType.RANDOM):
                td = real.rollout(args.max_steps, planner, break_when_any_done=True)
            length = int(td.shape[0])
            ret = float(td["next", "reward"].sum())
            terminated = bool(td["next", "terminated"][-1])
            episodes.append(
                {
                    "length": length,
                    "return": ret,
                    "terminated": terminated,
                    "seconds": time.perf_counter() - t0,
                }
            )
            print(
                f"seed {seed} {name:>15} episode {ep}: length {length:4d} return {ret:8.1f}",
                flush=True,
            )
        out["episodes"][name] = episodes
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--candidates", type=int, default=100)
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--random-steps", type=int, default=10_000)
    parser.add_argument("--max-steps", type=int, default=1000)
    parser.add_argument("--max-epochs", type=int, default=200)
    parser.add_argument("--hidden", type=int, nargs="+", default=[500, 500])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--name", default="hopper_terminations")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = [run_seed(seed, args) for seed in args.seeds]
    rows = []
    for name in ("terminations", "no terminations"):
        lengths = [statistics.mean(e["length"] for e in s["episodes"][name]) for s in seeds]
        returns = [statistics.mean(e["return"] for e in s["episodes"][name]) for s in seeds]
        sd = statistics.stdev if len(seeds) > 1 else (lambda _: 0.0)
        rows.append(
            {
                "scoring": name,
                "seeds": len(seeds),
                "episodes/seed": args.episodes,
                "length mean": statistics.mean(lengths),
                "length sd(seeds)": sd(lengths),
                "return mean": statistics.mean(returns),
                "return sd(seeds)": sd(returns),
                "per-seed lengths": " ".join(f"{x:.0f}" for x in lengths),
                "per-seed returns": " ".join(f"{x:.0f}" for x in returns),
            }
        )
    print_table(rows)
    path = write(args.name, rows, {"args": vars(args), "seeds": seeds})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
