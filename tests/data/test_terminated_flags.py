"""The dataset stores the real env's ``terminated`` beside ``done``; older datasets still load.

``tests/data/legacy/`` holds a dataset and its compact replay written before ``terminated`` was
stored (format ``torchrl_mbmf.transitions/2``, Pendulum-v1, 260 random steps, seed 7).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import RandomPolicy

from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
from torchrl_mbmf.envs import env_metadata, make_env
from torchrl_mbmf.runs.dataset_replay import DatasetReplay, NotReplayableError

LEGACY = Path(__file__).parent / "legacy"
OLD_FORMAT = "torchrl_mbmf.transitions/2"


def _hopper_with_truncations() -> tuple[TransitionDataset, TensorDict]:
    """Random Hopper steps with a 25-step time limit: falls and truncations both occur."""
    env = make_env("Hopper-v5", seed=3, max_episode_steps=25)
    torch.manual_seed(3)
    batch = env.rollout(400, break_when_any_done=False)
    data = TransitionDataset(env_metadata(env))
    data.extend(batch)
    return data, batch


def test_terminated_is_stored_apart_from_truncations():
    data, batch = _hopper_with_truncations()
    terminated = batch["next", "terminated"].reshape(-1)
    truncated = batch["next", "truncated"].reshape(-1)
    assert terminated.any() and (truncated & ~terminated).any()  # both kinds of episode end
    assert torch.equal(data.terminated(), terminated)
    assert torch.equal(data.tensors()["next", "done"].reshape(-1), terminated | truncated)
    assert data.stores_terminated and data.record()["format"] == "torchrl_mbmf.transitions/3"


def test_batches_without_terminated_make_a_dataset_that_refuses_to_guess():
    meta = {"env_id": "Mock-v0", "reward": {"name": "default"}}

    def batch(terminated: bool) -> TensorDict:
        nxt = {"state": torch.ones(4, 2), "reward": torch.ones(4, 1), "done": torch.zeros(4, 1)}
        if terminated:
            nxt["terminated"] = torch.zeros(4, 1, dtype=torch.bool)
        nxt["done"] = nxt["done"].bool()
        return TensorDict(
            state=torch.zeros(4, 2), action=torch.zeros(4, 1), next=nxt, batch_size=[4]
        )

    done_only = TransitionDataset(meta)
    done_only.extend(batch(terminated=False))
    done_only.extend(batch(terminated=True))  # the flags of later batches are not stored
    assert not done_only.stores_terminated and ("next", "terminated") not in done_only.keys
    with pytest.raises(ValueError, match=r"does not store the real env's \('next', 'terminated'\)"):
        done_only.terminated()
    flagged = TransitionDataset(meta)
    flagged.extend(batch(terminated=True))
    with pytest.raises(ValueError, match=r"lack keys \[\('next', 'terminated'\)\]"):
        flagged.extend(batch(terminated=False))
    assert len(flagged) == 4


def test_a_dataset_saved_before_terminated_loads_keeps_its_format_and_refuses_to_guess(tmp_path):
    saved = json.loads((LEGACY / "pendulum_transitions_v2" / "metadata.json").read_text())
    data = TransitionDataset.load(LEGACY / "pendulum_transitions_v2")
    assert len(data) == 260 and not data.stores_terminated
    assert data.record() == saved  # same format, keys and checksum
    with pytest.raises(ValueError, match=OLD_FORMAT):
        data.terminated()
    # saved again, it is the same dataset byte for byte
    again = data.save(tmp_path / "again")
    assert json.loads((again / "metadata.json").read_text()) == saved
    # a resumed run extends it in its own format (the new flags are not stored)
    env = make_env("Pendulum-v1", seed=1)
    data.extend(env.rollout(20))
    assert data.record()["format"] == OLD_FORMAT and len(data.record()["keys"]) == 6
    loaded = TransitionDataset.load(data.save(tmp_path / "extended"))
    assert len(loaded) == 280 and not loaded.stores_terminated


def test_an_old_compact_replay_expands_bit_for_bit(tmp_path):
    saved = json.loads((LEGACY / "pendulum_transitions_v2" / "metadata.json").read_text())
    replay = DatasetReplay.load(LEGACY / "pendulum_replay_v2")
    rebuilt = replay.rebuild(make_env("Pendulum-v1"))
    assert rebuilt.record() == saved
    stored = TransitionDataset.load(LEGACY / "pendulum_transitions_v2").tensors()
    for key in rebuilt.keys:
        assert torch.equal(rebuilt.tensors()[key], stored[key]), key
    # and a replay record of it is the committed one
    copy = shutil.copytree(LEGACY / "pendulum_transitions_v2", tmp_path / "d")
    again = DatasetReplay.from_dataset(
        TransitionDataset.load(copy), make_env("Pendulum-v1"), seed=7
    )
    assert again.record == replay.record and again.resets == replay.resets


def test_the_replay_checks_and_rebuilds_the_terminated_flags():
    env = make_env("Hopper-v5", seed=2)
    data = TransitionDataset({**env_metadata(env), "seed": 2})
    collector = LeanCollector(env, RandomPolicy(env.full_action_spec), frames_per_batch=300)
    torch.manual_seed(0)
    data.extend(next(iter(collector)))
    collector.shutdown()
    assert data.terminated().any()
    replay = DatasetReplay.from_dataset(data, make_env("Hopper-v5"), seed=2)
    assert replay.rebuild(make_env("Hopper-v5")).record() == data.record()
    # a flag that the env does not give is found, named by its key and row
    data.tensors()["next", "terminated"][5] = True
    with pytest.raises(NotReplayableError, match=r"\('next', 'terminated'\) at row 5"):
        DatasetReplay.from_dataset(data, make_env("Hopper-v5"), seed=2)


def test_random_collection_stores_the_flags():
    data = collect_random_transitions(make_env("Hopper-v5", max_episode_steps=30), 200, seed=0)
    done = data.tensors()["next", "done"].reshape(-1)
    assert data.terminated().any() and bool((data.terminated() <= done).all())
