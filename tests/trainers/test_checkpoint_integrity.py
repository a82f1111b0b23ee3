"""Damaged, interrupted or crafted checkpoints are never restored (issue 12, defects 1 and 2)."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_mbmf.trainers import Trainer

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "method=ppo",
    "env=pendulum",
    "total_steps=480",
    "ppo.frames_per_batch=160",
    "ppo.hidden_sizes=[16,16]",
    "eval_every=100000",
    "eval_episodes=1",
    "checkpoint.every_steps=160",
    "checkpoint.keep_last=2",
    "progress=false",
    "threads=1",
]


def _cfg():
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose("train", overrides=TINY)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished tiny run: checkpoints at 320 and 480 real steps (keep_last=2)."""
    run = tmp_path_factory.mktemp("trained") / "run"
    Trainer(_cfg(), run).train()
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names == ["checkpoint-000000000320", "checkpoint-000000000480"], names
    return run


@pytest.fixture
def run_dir(trained, tmp_path):
    """The trained run's folder as an interrupted run's (a finished run has nothing to train)."""
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    (run / "summary.json").unlink()
    return run


def _latest(run: Path) -> Path:
    return run / "checkpoints" / "checkpoint-000000000480"


def _weight_file(checkpoint: Path) -> Path:
    """The largest file of the actor-critic ("loss") component: a weight matrix."""
    (component,) = (checkpoint / "components").glob("*-loss")
    weights = (f for f in component.rglob("*") if f.is_file() and f.suffix != ".json")
    return max(weights, key=lambda f: f.stat().st_size)


def _flip_bit(file: Path) -> None:
    raw = bytearray(file.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    file.write_bytes(bytes(raw))


def _truncate(file: Path) -> None:
    file.write_bytes(file.read_bytes()[:1000])


def _resume(run: Path) -> Trainer:
    return Trainer(_cfg(), run)


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(_flip_bit, id="bit_flip"),
        pytest.param(_truncate, id="truncated_to_1000_bytes"),
        pytest.param(Path.unlink, id="missing_file"),
    ],
)
def test_damaged_latest_checkpoint_falls_back_to_the_previous(run_dir, damage):
    weight = _weight_file(_latest(run_dir))
    assert weight.stat().st_size > 1000
    damage(weight)
    size = weight.stat().st_size if weight.exists() else None
    with pytest.warns(UserWarning, match=rf"{weight.name}.*checkpoint-000000000320"):
        trainer = _resume(run_dir)
    assert trainer.resumed and trainer.progress["real_steps"] == 320
    # the damaged checkpoint was moved aside, its file neither loaded nor re-extended
    (aside,) = (run_dir / "checkpoints" / "damaged").iterdir()
    moved = aside / weight.relative_to(_latest(run_dir))
    assert moved.stat().st_size == size if size is not None else not moved.exists()
    # the damaged checkpoint left the rotation: the resumed run writes a good one at 480
    assert not _latest(run_dir).exists()
    trainer.train()
    assert _latest(run_dir).exists()
    (run_dir / "summary.json").unlink()  # resumed once more, as an interrupted run
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _resume(run_dir).progress["real_steps"] == 480
    assert not [w for w in caught if "damaged" in str(w.message)]


def test_resume_equals_the_undamaged_run_after_fallback(run_dir, trained):
    _flip_bit(_weight_file(_latest(run_dir)))
    with pytest.warns(UserWarning):
        trainer = _resume(run_dir)
    trainer.train()
    reference = json.loads((trained / "summary.json").read_text())["params_sha256"]
    assert trainer.parameters_digest() == reference


def test_no_intact_checkpoint_is_a_clear_error(run_dir):
    for checkpoint in (run_dir / "checkpoints").iterdir():
        _flip_bit(_weight_file(checkpoint))
    with pytest.raises(RuntimeError, match=r"no intact checkpoint.*checkpoint-000000000320"):
        _resume(run_dir)
    # nothing was moved or deleted: the error stays until someone acts
    assert len(list((run_dir / "checkpoints").glob("checkpoint-*"))) == 2


def test_staging_leftover_is_removed_never_loaded(run_dir):
    checkpoints = run_dir / "checkpoints"
    # an interrupted save of step 640: a complete-looking copy under a staging name
    for name in (".checkpoint-000000000640.stage-0123abcd", ".checkpoint-000000000640.verify-9f"):
        shutil.copytree(_latest(run_dir), checkpoints / name)
    trainer = _resume(run_dir)
    assert trainer.progress["real_steps"] == 480
    assert sorted(p.name for p in checkpoints.iterdir()) == [
        "checkpoint-000000000320",
        "checkpoint-000000000480",
    ]


def test_resume_never_unpickles_a_checkpoint_component(run_dir, plant_pickle):
    (component,) = (_latest(run_dir) / "components").glob("*-rng")
    state = component / "state"
    if not (state / "meta.json").exists():
        TensorDict().memmap(state)
    marker = plant_pickle(state)
    try:  # a crafted checkpoint comes with a matching integrity record
        from torchrl_mbmf.runs.storage import write_integrity_record

        write_integrity_record(_latest(run_dir))
    except ImportError:
        pass
    with pytest.raises(Exception, match="rng"):
        _resume(run_dir)
    assert not marker.exists()


def test_replay_checkpoint_never_unpickles(tmp_path, plant_pickle):
    from torchrl_mbmf.runs.storage import ReplayCheckpointAdapter

    source = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
    source.extend(TensorDict({"obs": torch.arange(12.0)[:, None]}, [12]))
    ReplayCheckpointAdapter().save(source, tmp_path, args=(), kwargs={})
    marker = plant_pickle(tmp_path / "data")
    target = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
    with pytest.raises(ValueError, match=r"meta\.json.*payload"):
        ReplayCheckpointAdapter().load(target, tmp_path)
    assert not marker.exists()
    # an unexpected (plain tensor) key is refused too when the adapter knows its keys
    ReplayCheckpointAdapter().save(source, tmp_path / "ok", args=(), kwargs={})
    with pytest.raises(ValueError, match="unexpected keys"):
        ReplayCheckpointAdapter(keys=["action"]).load(target, tmp_path / "ok")


def test_a_tensor_that_could_not_be_loaded_is_refused_before_writing(tmp_path):
    from torchrl_mbmf.runs.storage import TensorStateAdapter

    class Holder:
        def state_dict(self):
            return {"fine": torch.zeros(2), "nested": [torch.zeros(2, dtype=torch.complex64)]}

    target = tmp_path / "component"
    with pytest.raises(TypeError, match=r"Holder\['nested'\]\[0\]: a torch\.complex64 tensor"):
        TensorStateAdapter().save(Holder(), target, args=(), kwargs={})
    assert not target.exists()


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.int64, torch.bool])
def test_every_allowed_dtype_round_trips(tmp_path, dtype):
    from torchrl_mbmf.runs.storage import TensorStateAdapter

    class Holder:
        def __init__(self, value):
            self.value = value

        def state_dict(self):
            return {"value": self.value}

        def load_state_dict(self, state):
            self.value = state["value"]

    source = Holder(torch.arange(6).reshape(2, 3).to(dtype))
    target = Holder(None)
    TensorStateAdapter().save(source, tmp_path, args=(), kwargs={})
    TensorStateAdapter().load(target, tmp_path)
    assert target.value.dtype == dtype and torch.equal(target.value, source.value)
