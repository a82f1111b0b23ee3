"""The learned termination head against Hopper's known rule on held-out real transitions."""

from __future__ import annotations

import pytest
import torch

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
from torchrl_mbmf.envs.terminations import termination_rule
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.modules.termination import LearnedTermination, classification_scores

X_FIRST = {"exclude_current_positions_from_observation": False}


def _hopper(steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    env = make_gym_state_env("Hopper-v5", seed=seed, **X_FIRST)
    torch.manual_seed(seed)
    td = env.rollout(steps, break_when_any_done=False)
    return td["next", "state"], td["next", "terminated"][:, 0]


def test_head_learns_hoppers_rule_and_plugs_into_the_learned_env():
    states, terminated = _hopper(2000, 0)
    test_states, test_terminated = _hopper(1000, 1)
    rule = termination_rule("Hopper-v5", **X_FIRST)
    assert torch.equal(rule(test_states), test_terminated)  # the reference
    torch.manual_seed(0)
    head = LearnedTermination(12, hidden_sizes=(32, 32))
    fit = head.fit(states, terminated, epochs=20, lr=3e-3, seed=0)
    assert fit.val_size == 200 and fit.val_terminal > 0
    scores = classification_scores(head(test_states), rule(test_states))
    assert scores["balanced_accuracy"] > 0.9 and scores["recall"] > 0.8, scores
    env = LearnedDynamicsEnv(
        DeltaDynamicsModel(12, 3, hidden_sizes=(8,)),
        make_gym_state_env("Hopper-v5", **X_FIRST),
        termination_fn=head,
    )
    assert env.termination_fn is head and not env.never_terminates


def test_head_checks_its_inputs():
    with pytest.raises(ValueError, match="threshold"):
        LearnedTermination(3, threshold=1.5)
    with pytest.raises(ValueError, match="state_dim"):
        LearnedTermination(0)
    head = LearnedTermination(3, hidden_sizes=(4,))
    with pytest.raises(ValueError, match="2 flags for 3 states"):
        head.fit(torch.zeros(3, 3), torch.zeros(2))
    with pytest.raises(ValueError, match="expected state_dim=3"):
        head(torch.zeros(2, 4))
