"""Hopper-v5: a learned termination head against the known rule on held-out real transitions.

python benchmarks/hopper_termination_head.py     # -> results/hopper_termination_head.json

For each seed, :class:`~torchrl_mbmf.modules.termination.LearnedTermination` (an MLP on the
next state) is fitted on ``--train-steps`` uniform-random real transitions' next states and
``terminated`` flags (Hopper-v5, x position first), then scored on ``--test-steps``
transitions of another seed: accuracy, balanced accuracy, precision and recall against the
real env's ``terminated``, and agreement with the known rule
(:class:`~torchrl_mbmf.envs.terminations.HopperTermination`, itself equal to ``terminated``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import print_table, write

from torchrl_mbmf.envs import make_gym_state_env
from torchrl_mbmf.envs.terminations import termination_rule
from torchrl_mbmf.modules.termination import LearnedTermination, classification_scores

KWARGS = {"exclude_current_positions_from_observation": False}


def transitions(steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform-random real transitions (auto-reset): next states and ``terminated``."""
    env = make_gym_state_env("Hopper-v5", seed=seed, **KWARGS)
    torch.manual_seed(seed)  # the spec's random actions
    td = env.rollout(steps, break_when_any_done=False)
    return td.get(("next", "state")), td.get(("next", "terminated")).reshape(-1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--train-steps", type=int, default=20_000)
    parser.add_argument("--test-steps", type=int, default=10_000)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rule = termination_rule("Hopper-v5", **KWARGS)
    rows = []
    for seed in args.seeds:
        torch.manual_seed(seed)
        states, terminated = transitions(args.train_steps, seed)
        test_states, test_terminated = transitions(args.test_steps, seed + 100)
        assert torch.equal(rule(test_states), test_terminated.bool())
        head = LearnedTermination(states.shape[-1])
        head.fit(states, terminated, epochs=args.epochs, seed=seed)
        predicted = head(test_states)
        scores = classification_scores(predicted, test_terminated)
        rows.append(
            {
                "seed": seed,
                "test transitions": int(test_terminated.numel()),
                "test terminal": int(test_terminated.sum()),
                **scores,
                "agreement with rule": float((predicted == rule(test_states)).float().mean()),
            }
        )
    summary = {
        k: statistics.mean(r[k] for r in rows)
        for k in ("accuracy", "balanced_accuracy", "precision", "recall")
    }
    rows.append({"seed": "mean", **summary})
    print_table(rows)
    print(f"wrote {write('hopper_termination_head', rows, {'args': vars(args)})}")


if __name__ == "__main__":
    main()
