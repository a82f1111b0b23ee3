"""The README's "Use it in your own TorchRL code" example runs, and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from torchrl_mbmf.modules.termination import classification_scores

README = Path(__file__).resolve().parents[1] / "README.md"
SECTION = "## Use it in your own TorchRL code"


def _examples() -> list[str]:
    """The python blocks of the section, in order (each continues the one before)."""
    text = README.read_text()
    assert SECTION in text, f"README.md has no {SECTION!r} section"
    section = text[text.index(SECTION) :]
    section = section[: section.index("\n## ", len(SECTION))]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert blocks, f"no python block under {SECTION!r}"
    return blocks


def test_readme_example_on_hopper():
    namespace: dict[str, object] = {}
    first, *rest = _examples()
    exec(compile(first, str(README), "exec"), namespace)
    env, model, model_env = namespace["env"], namespace["model"], namespace["model_env"]
    data, batch, optim = namespace["data"], namespace["batch"], namespace["optim"]
    # the learned env took Hopper's action bounds from the real env's spec
    assert model.action_bounds == (-1.0, 1.0)
    # its termination rule agrees with Gymnasium's own ends on every real random transition
    # (random Hopper episodes fall long before the 1000-step time limit: every end terminates)
    td = data.tensors()
    with torch.no_grad():
        terminated = model_env.termination_fn(td["next", "observation"])
    ends = td["next", "done"].reshape(-1)
    assert ends.any()
    assert torch.equal(terminated, ends)
    # the collector's last batch: real steps the planner chose, with the actor's log-probs
    assert batch.batch_size == (200,)
    action = batch["action"]
    assert ((action >= env.action_spec.space.low) & (action <= env.action_spec.space.high)).all()
    assert torch.isfinite(batch["action_log_prob"]).all()
    # PPO took one step per batch
    steps = {int(s["step"]) for s in optim.state_dict()["state"].values()}
    assert steps == {2}
    # the learned termination head of the next block: fitted on the dataset's real terminated
    # flags, it is the termination_fn of its learned env and the planner's
    assert len(rest) == 1
    exec(compile(rest[0], str(README), "exec"), namespace)
    head, learned_env = namespace["head"], namespace["learned_env"]
    assert learned_env.termination_fn is head and namespace["planner"].env is learned_env
    with torch.no_grad():
        predicted = head(td["next", "observation"])
    scores = classification_scores(predicted, ends)
    # terminal transitions are rare (about 5%): balanced accuracy and recall, not accuracy
    assert scores["balanced_accuracy"] > 0.85 and scores["recall"] > 0.8, scores
