from __future__ import annotations

import json
import re
import shutil

import pytest
import torch
from tensordict import TensorDict

from torchrl_mbmf.data import (
    CorruptDatasetError,
    DatasetMismatchError,
    TransitionDataset,
    collect_random_transitions,
)
from torchrl_mbmf.data.transitions import TRAJ_KEY
from torchrl_mbmf.envs import env_metadata, make_env, make_gym_state_env

META = {"env_id": "Mock-v0", "reward": {"name": "default"}}


def _batch(n_envs, steps, done_at=(), start=0.0):
    """Transitions whose state encodes (env, global step) and with done at given (env, t)."""
    t = torch.arange(steps, dtype=torch.float32) + start
    state = torch.stack([t + 1000 * e for e in range(n_envs)])[..., None].expand(-1, -1, 3)
    done = torch.zeros(n_envs, steps, 1, dtype=torch.bool)
    for e, k in done_at:
        done[e, k] = True
    return TensorDict(
        state=state.clone(),
        action=torch.zeros(n_envs, steps, 1),
        next=TensorDict(
            state=state + 1,
            reward=torch.ones(n_envs, steps, 1),
            done=done,
            batch_size=[n_envs, steps],
        ),
        batch_size=[n_envs, steps],
    )


def test_trajectory_ids_across_batches_and_envs():
    data = TransitionDataset(META)
    data.extend(_batch(2, 4, done_at=[(0, 1), (1, 3)]))
    data.extend(_batch(2, 3, done_at=[(0, 0)], start=4.0))
    trajs = data.trajectories()
    states = data.tensors()["state"][:, 0]
    episodes = sorted(states[idx].tolist() for idx in trajs)
    assert episodes == sorted(
        [
            [0.0, 1.0],  # env 0 until its done at t=1
            [2.0, 3.0, 4.0],  # continues into the second batch, done at t=4
            [5.0, 6.0],
            [1000.0, 1001.0, 1002.0, 1003.0],  # env 1, done on the batch's last step
            [1004.0, 1005.0, 1006.0],  # a fresh id in the next batch
        ]
    )
    assert len(data) == 14
    assert data.tensors()[TRAJ_KEY].unique().numel() == 5


def test_random_collection_batched_keeps_episodes_consecutive():
    env = make_env("Pendulum-v1", num_envs=3)
    data = collect_random_transitions(env, 700, seed=0, chunk=90)
    assert len(data) == 702  # rounded up to a multiple of the 3 copies
    td = data.tensors()
    lengths = []
    for idx in data.trajectories():
        torch.testing.assert_close(td["next", "state"][idx[:-1]], td["state"][idx[1:]])
        lengths.append(idx.numel())
    assert sorted(lengths) == [34, 34, 34, 200, 200, 200]  # 200-step episodes, 234 each
    action = td["action"]
    assert (action.abs() <= 2).all() and action.std() > 0.5  # uniform on Pendulum's [-2, 2]


def test_seeded_collection_is_reproducible():
    a = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 50, seed=1).tensors()
    b = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 50, seed=1).tensors()
    torch.testing.assert_close(a["action"], b["action"])
    torch.testing.assert_close(a["next", "state"], b["next", "state"])


def test_save_load_round_trip_and_append(tmp_path):
    env = make_env("HalfCheetah-v5", reward="shin_pen")
    data = collect_random_transitions(env, 120, seed=3)
    path = data.save(tmp_path / "ds")
    loaded = TransitionDataset.load(path, expect=env_metadata(env))
    assert len(loaded) == 120
    for key in data.keys:
        torch.testing.assert_close(loaded.tensors()[key], data.tensors()[key])
    assert loaded.metadata["seed"] == 3
    assert loaded.metadata["reward"]["name"] == "shin_pen"
    assert loaded.metadata["package_version"]
    # appending continues the open episode
    collect_random_transitions(env, 30, dataset=loaded)
    assert len(loaded) == 150
    with pytest.raises(FileExistsError, match="overwrite=True"):
        loaded.save(path)
    loaded.save(path, overwrite=True)
    assert len(TransitionDataset.load(path)) == 150


def test_load_refuses_other_env_or_reward(tmp_path):
    data = collect_random_transitions(make_env("HalfCheetah-v5", reward="head_pen"), 20, seed=0)
    data.save(tmp_path / "ds")
    other = env_metadata(make_env("HalfCheetah-v5", reward="shin_pen"))
    with pytest.raises(DatasetMismatchError, match=r"head_pen.*shin_pen"):
        TransitionDataset.load(tmp_path / "ds", expect=other)
    retuned = env_metadata(
        make_env("HalfCheetah-v5", reward="head_pen", reward_kwargs={"threshold": -0.3})
    )
    with pytest.raises(DatasetMismatchError, match="reward"):
        TransitionDataset.load(tmp_path / "ds", expect=retuned)
    with pytest.raises(DatasetMismatchError, match="env_id='HalfCheetah-v5'"):
        TransitionDataset.load(tmp_path / "ds", expect={"env_id": "Pendulum-v1"})


def test_corrupt_or_truncated_files_raise(tmp_path):
    data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 64, seed=0)
    path = data.save(tmp_path / "ds")
    memmap = path / "buffer" / "state.memmap"
    raw = bytearray(memmap.read_bytes())
    raw[5] ^= 0xFF
    memmap.write_bytes(bytes(raw))
    with pytest.raises(CorruptDatasetError, match="checksum"):
        TransitionDataset.load(path)
    memmap.write_bytes(bytes(raw[: len(raw) // 2]))
    with pytest.raises(CorruptDatasetError):
        TransitionDataset.load(path)
    (path / "metadata.json").write_text("{not json")
    with pytest.raises(CorruptDatasetError, match="JSON"):
        TransitionDataset.load(path)
    meta_path = data.save(tmp_path / "ds2") / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta["num_transitions"] = 80
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CorruptDatasetError):
        TransitionDataset.load(tmp_path / "ds2")
    del meta["sha256"]
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CorruptDatasetError, match="sha256"):
        TransitionDataset.load(tmp_path / "ds2")
    # a save interrupted before the rename leaves only a hidden temporary folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "ds2"]
    shutil.rmtree(tmp_path / "ds2" / "buffer")
    meta_path.write_text(json.dumps({**meta, "sha256": "0" * 64}))
    with pytest.raises(CorruptDatasetError, match="cannot read the buffer"):
        TransitionDataset.load(tmp_path / "ds2")
    with pytest.raises(FileNotFoundError):
        TransitionDataset.load(tmp_path / "missing")


def test_bad_input():
    with pytest.raises(ValueError, match="env_id"):
        TransitionDataset({"reward": {}})
    data = TransitionDataset(META, capacity=5)
    with pytest.raises(ValueError, match="capacity 5 exceeded"):
        data.extend(_batch(2, 3))
    with pytest.raises(ValueError, match=r"\[T\] or \[N, T\]"):
        data.extend(_batch(1, 2).unsqueeze(0))
    bad = _batch(1, 2)
    bad["state"][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        data.extend(bad)
    with pytest.raises(ValueError, match="empty"):
        data.tensors()
    with pytest.raises(ValueError, match="num_steps"):
        collect_random_transitions(make_gym_state_env("Pendulum-v1"), 0)


@pytest.mark.parametrize("num_envs", [1, 2])
def test_extend_from_collector_keeps_episodes(num_envs):
    from torchrl.collectors import Collector

    env = make_env("Pendulum-v1", num_envs=num_envs, seed=0)
    collector = Collector(env, None, frames_per_batch=150 * num_envs, total_frames=450 * num_envs)
    data = TransitionDataset(env_metadata(env))
    for batch in collector:
        assert batch.batch_size == ((150,) if num_envs == 1 else (num_envs, 150))
        data.extend(batch)
    collector.shutdown()
    assert len(data) == 450 * num_envs
    td = data.tensors()
    lengths = []
    for idx in data.trajectories():
        torch.testing.assert_close(td["next", "state"][idx[:-1]], td["state"][idx[1:]])
        lengths.append(idx.numel())
    # 200-step Pendulum episodes continue across collector batches
    assert sorted(lengths) == sorted([200, 200, 50] * num_envs)


def test_interrupted_save_leaves_nothing(tmp_path, monkeypatch):
    data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 20, seed=0)

    def crash(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("torchrl_mbmf.data.dataset_files.os.replace", crash)
    with pytest.raises(OSError, match="disk full"):
        data.save(tmp_path / "ds")
    assert list(tmp_path.iterdir()) == []


def test_load_never_unpickles_a_planted_entry(tmp_path, plant_pickle):
    data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 20, seed=0)
    path = data.save(tmp_path / "ds")
    marker = plant_pickle(path / "buffer")
    with pytest.raises(CorruptDatasetError, match=r"meta\.json.*payload"):
        TransitionDataset.load(path)
    assert not marker.exists()
    # a pickle sidecar next to the tensors is refused too, by name
    path = data.save(tmp_path / "ds2")
    (path / "buffer" / "other.pickle").write_bytes(b"\x80\x04N.")
    with pytest.raises(CorruptDatasetError, match=r"other\.pickle"):
        TransitionDataset.load(path)


def test_checksum_covers_the_metadata(tmp_path):
    data = collect_random_transitions(make_env("HalfCheetah-v5", reward="head_pen"), 20, seed=0)
    path = data.save(tmp_path / "ds")
    meta_path = path / "metadata.json"
    meta = json.loads(meta_path.read_text())
    for edit in (
        {"reward": {**meta["reward"], "name": "shin_pen"}},
        {"reward": {**meta["reward"], "threshold": 0.9}},
        {"seed": 7},
    ):
        meta_path.write_text(json.dumps({**meta, **edit}))
        with pytest.raises(CorruptDatasetError, match="checksum"):
            TransitionDataset.load(path)
    # a dtype edited in the buffer's meta.json (same bytes) is caught as well
    meta_path.write_text(json.dumps(meta))
    TransitionDataset.load(path)
    buffer_meta = path / "buffer" / "meta.json"
    td_meta = json.loads(buffer_meta.read_text())
    td_meta["traj_id"]["dtype"] = "torch.float64"
    buffer_meta.write_text(json.dumps(td_meta))
    with pytest.raises(CorruptDatasetError, match="checksum"):
        TransitionDataset.load(path)


def test_missing_tensor_file_names_it(tmp_path):
    data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 20, seed=0)
    path = data.save(tmp_path / "ds")
    (path / "buffer" / "next" / "reward.memmap").unlink()
    with pytest.raises(CorruptDatasetError, match=r"next/reward\.memmap"):
        TransitionDataset.load(path)
    # a truncated file is named as well, and is not re-extended on disk
    path = data.save(tmp_path / "ds2")
    state = path / "buffer" / "state.memmap"
    state.write_bytes(state.read_bytes()[:100])
    with pytest.raises(CorruptDatasetError, match=r"state\.memmap has 100 bytes"):
        TransitionDataset.load(path)
    assert state.stat().st_size == 100


@pytest.mark.parametrize(
    "field", ["state", "action", ("next", "state"), ("next", "reward")], ids=str
)
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_extend_refuses_non_finite_transitions(field, value):
    data = TransitionDataset(META)
    bad = _batch(2, 3)
    bad.get(field)[1, 2, 0] = value
    with pytest.raises(ValueError, match=re.escape(f"NaN or Inf in {field!r}")):
        data.extend(bad)
    assert len(data) == 0
    data.extend(_batch(2, 3))
    assert len(data) == 6


def _resized(batch, key, size, dtype=torch.float32):
    value = batch.get(key)
    batch.set(key, torch.zeros(*value.shape[:-1], size, dtype=dtype))
    return batch


@pytest.mark.parametrize(
    ("make_bad", "message"),
    [
        (lambda: _resized(_batch(2, 3), "state", 4), r"'state' has trailing shape \[4\]"),
        (lambda: _resized(_batch(2, 3), "action", 2), r"'action' has trailing shape \[2\]"),
        (
            lambda: _resized(_batch(2, 3), ("next", "state"), 3, torch.float64),
            "wrap a float64 env in torchrl's DoubleToFloat",
        ),
        (lambda: _batch(2, 0), r"empty batch of shape \(2, 0\)"),
    ],
)
def test_extend_refuses_another_layout_before_storing(make_bad, message):
    data = TransitionDataset(META)
    data.extend(_batch(2, 3))
    with pytest.raises(ValueError, match=message):
        data.extend(make_bad())
    assert len(data) == 6


def test_first_extend_checks_the_state_against_the_metadata_and_next_state():
    data = TransitionDataset({**META, "state_shape": [3]})
    with pytest.raises(ValueError, match=r"metadata says state_shape=\[3\]"):
        data.extend(_resized(_resized(_batch(2, 3), "state", 5), ("next", "state"), 5))
    with pytest.raises(ValueError, match=r"next state \[4\]"):
        TransitionDataset(META).extend(_resized(_batch(2, 3), ("next", "state"), 4))
    assert len(data) == 0
    data.extend(_batch(2, 3))
    assert len(data) == 6


def test_loaded_dataset_keeps_its_layout(tmp_path):
    data = TransitionDataset(META)
    data.extend(_batch(2, 3))
    loaded = TransitionDataset.load(data.save(tmp_path / "d"))
    with pytest.raises(ValueError, match=r"the dataset holds \[3\]"):
        loaded.extend(_resized(_batch(1, 2), "state", 5))


@pytest.mark.parametrize("capacity", [2.5, True, 0, float("nan")])
def test_capacity_must_be_a_positive_integer(capacity):
    with pytest.raises(ValueError, match="capacity must be an integer >= 1"):
        TransitionDataset(META, capacity=capacity)


def test_the_package_s_datasets_refuse_a_first_extend_of_another_state_size():
    """``collect_random_transitions`` records the env's state shape; another size is refused."""
    from torchrl_mbmf.envs import make_gym_state_env

    env = make_gym_state_env("Pendulum-v1")
    data = collect_random_transitions(env, 10, seed=0)
    assert data.metadata["state_shape"] == [env.observation_spec["state"].shape[-1]]
    other = collect_random_transitions(make_gym_state_env("InvertedPendulum-v5"), 10, seed=0)
    fresh = type(data)(dict(data.metadata))
    with pytest.raises(ValueError, match=r"state_shape=\[3\]"):
        fresh.extend(other.tensors())
