"""The README's "Use it in your own TorchRL code" example runs, and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"
SECTION = "## Use it in your own TorchRL code"


def _example() -> str:
    text = README.read_text()
    assert SECTION in text, f"README.md has no {SECTION!r} section"
    block = re.search(r"```python\n(.*?)```", text[text.index(SECTION) :], re.S)
    assert block is not None, f"no python block under {SECTION!r}"
    return block.group(1)


def test_readme_example_on_hopper():
    namespace: dict[str, object] = {}
    exec(compile(_example(), str(README), "exec"), namespace)
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
