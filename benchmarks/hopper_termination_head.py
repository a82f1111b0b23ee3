"""Hopper-v5: the learned termination head of ``learn_termination`` against the known rule.

python benchmarks/hopper_termination_head.py     # -> results/hopper_termination_head.json

For each seed, uniform-random real transitions are collected into a
:class:`~torchrl_mbmf.data.TransitionDataset` (``make_env("Hopper-v5")``: the recipes' env,
x position first), and a :class:`~torchrl_mbmf.modules.LearnedTermination` is fitted on them
exactly as a run with ``world_model.learn_termination=true`` fits it after a model fit
(:func:`~torchrl_mbmf.world_model.termination_fit.fit_termination`: the dataset's next states
and stored ``terminated`` flags, ``TERMINATION_EPOCHS`` epochs). It is then scored on
``--test-steps`` held-out transitions of another seed against the real env's ``terminated``:
accuracy, balanced accuracy (terminal transitions are rare: always answering "not terminal"
already scores ``majority accuracy``), precision and recall on terminal transitions, and
agreement with the known rule (:class:`~torchrl_mbmf.envs.terminations.HopperTermination`,
checked equal to ``terminated`` on the same transitions).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import print_table, write

from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import make_env
from torchrl_mbmf.envs.terminations import termination_rule_of_env
from torchrl_mbmf.modules.termination import LearnedTermination, classification_scores
from torchrl_mbmf.world_model.termination_fit import TERMINATION_EPOCHS, fit_termination

ENV_ID = "Hopper-v5"
SCORES = ("accuracy", "balanced_accuracy", "precision", "recall", "majority accuracy")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--train-steps", type=int, default=20_000)
    parser.add_argument("--test-steps", type=int, default=10_000)
    parser.add_argument("--epochs", type=int, default=TERMINATION_EPOCHS)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for seed in args.seeds:
        env = make_env(ENV_ID, seed=seed)
        rule = termination_rule_of_env(env)
        train = collect_random_transitions(env, args.train_steps, seed=seed)
        test = collect_random_transitions(make_env(ENV_ID), args.test_steps, seed=seed + 100)
        test_states, test_terminated = test.tensors()["next", "state"], test.terminated()
        assert torch.equal(rule(test_states), test_terminated)  # the reference
        torch.manual_seed(seed)
        head = LearnedTermination(test_states.shape[-1])
        fit = fit_termination(head, train, epochs=args.epochs, seed=seed)
        predicted = head(test_states)
        rows.append(
            {
                "seed": seed,
                "train terminal": int(train.terminated().sum()),
                "val accuracy": fit.val_accuracy,
                "test transitions": int(test_terminated.numel()),
                "test terminal": int(test_terminated.sum()),
                **classification_scores(predicted, test_terminated),
                "majority accuracy": 1.0 - float(test_terminated.float().mean()),
                "agreement with rule": float((predicted == rule(test_states)).float().mean()),
            }
        )
    rows.append({"seed": "mean", **{k: statistics.mean(r[k] for r in rows) for k in SCORES}})
    print_table(rows)
    print(f"wrote {write('hopper_termination_head', rows, {'args': vars(args)})}")


if __name__ == "__main__":
    main()
