"""A dataset kept as its actions rebuilds bit for bit by replaying them in the env."""

from __future__ import annotations

import itertools
import json
import shutil

import pytest
import torch
from torchrl.envs.utils import RandomPolicy

from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.data import CorruptDatasetError, TransitionDataset
from torchrl_mbmf.envs import env_metadata, make_env
from torchrl_mbmf.runs.dataset_replay import DatasetReplay, NotReplayableError

SEED = 5


def _trainer_like_dataset(bounds=(0, 200, 350, 500)) -> TransitionDataset:
    """Transitions collected as the trainer does: each collector from an env seeded with
    ``SEED + real steps``, episodes reset by the env itself in between (Pendulum: 200 steps).
    The default bounds put one collector start on an episode end (200) and one mid-episode
    (350)."""
    env = make_env("Pendulum-v1", seed=SEED)
    data = TransitionDataset({**env_metadata(env), "seed": SEED})
    for start, stop in itertools.pairwise(bounds):
        env.set_seed(SEED + start)
        collector = LeanCollector(env, RandomPolicy(env.full_action_spec), frames_per_batch=50)
        for _ in range((stop - start) // 50):
            data.extend(next(iter(collector)))
        collector.shutdown()
    return data


def test_the_replay_finds_every_seeded_collector_start_and_rebuilds_bit_for_bit():
    data = _trainer_like_dataset()
    replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=SEED)
    # the start at 200 follows an episode end, yet the env was seeded there: the replay tells
    # it from the env's own reset by the state it gives; the one at 350 cuts an episode
    assert replay.resets == [(0, SEED), (200, SEED + 200), (350, SEED + 350)]
    ids = data.tensors()["traj_id"]
    # the dataset joins the episode cut at 350 to the next one under one id
    assert replay.trajectories == [(0, 0), (200, 1)]
    assert ids[199] == 0 and ids[200] == 1 and ids[499] == 1
    rebuilt = replay.rebuild(make_env("Pendulum-v1"))
    assert rebuilt.record() == data.record()
    for key in data.keys:
        assert torch.equal(rebuilt.tensors()[key], data.tensors()[key]), key


def test_an_episode_the_env_reset_itself_is_not_reseeded():
    data = _trainer_like_dataset(bounds=(0, 500))
    replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=SEED)
    assert replay.resets == [(0, SEED)]
    assert replay.rebuild(make_env("Pendulum-v1")).record()["sha256"] == data.record()["sha256"]


def test_save_and_load_keep_everything_and_refuse_damaged_actions(tmp_path):
    data = _trainer_like_dataset()
    replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=SEED)
    path = replay.save(tmp_path / "replay")
    assert sorted(p.name for p in path.iterdir()) == ["actions.bin", "replay.json"]
    assert (path / "actions.bin").stat().st_size == 4 * 500  # float32, one action dim
    loaded = DatasetReplay.load(path)
    assert torch.equal(loaded.actions, replay.actions)
    assert (loaded.resets, loaded.trajectories) == (replay.resets, replay.trajectories)
    assert loaded.rebuild(make_env("Pendulum-v1")).record() == data.record()
    with pytest.raises(FileExistsError, match="overwrite=True"):
        replay.save(path)
    raw = bytearray((path / "actions.bin").read_bytes())
    raw[7] ^= 1
    (path / "actions.bin").write_bytes(bytes(raw))
    with pytest.raises(CorruptDatasetError, match="does not match its SHA-256"):
        DatasetReplay.load(path)
    (path / "actions.bin").write_bytes(bytes(raw[:-4]))
    with pytest.raises(CorruptDatasetError, match="has 1996 bytes, expected 2000"):
        DatasetReplay.load(path)
    meta = json.loads((path / "replay.json").read_text())
    (path / "replay.json").write_text(json.dumps({**meta, "format": "other/1"}))
    with pytest.raises(CorruptDatasetError, match="has format 'other/1'"):
        DatasetReplay.load(path)
    shutil.rmtree(path)
    with pytest.raises(FileNotFoundError, match=r"missing replay\.json"):
        DatasetReplay.load(path)


def test_another_env_or_seed_is_named_and_a_changed_action_fails_the_checksum():
    data = _trainer_like_dataset()
    with pytest.raises(NotReplayableError, match="'state' at row 0"):
        DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=SEED + 1)
    replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=SEED)
    actions = replay.actions.clone()
    actions[123] += 1e-3
    changed = DatasetReplay(actions, replay.resets, replay.trajectories, replay.record)
    with pytest.raises(CorruptDatasetError, match="do not match their checksum"):
        changed.rebuild(make_env("Pendulum-v1"))


def test_inconsistent_records_are_refused_before_any_replay():
    data = _trainer_like_dataset()
    replay = DatasetReplay.from_dataset(data, make_env("Pendulum-v1"), seed=SEED)
    with pytest.raises(ValueError, match=r"one row per transition \(500\)"):
        DatasetReplay(replay.actions[:-1], replay.resets, replay.trajectories, replay.record)
    with pytest.raises(ValueError, match="resets must start at row 0"):
        DatasetReplay(replay.actions, [(5, SEED)], replay.trajectories, replay.record)
    with pytest.raises(ValueError, match="trajectories must start at row 0"):
        DatasetReplay(replay.actions, replay.resets, [(0, 0), (600, 1)], replay.record)
    with pytest.raises(ValueError, match="single real env"):
        replay.rebuild(make_env("Pendulum-v1", num_envs=2))
