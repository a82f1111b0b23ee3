"""A checkpoint's replay buffers kept as what rebuilds them exactly (SAC's and ``sac_mbpo``'s).

SAC's replay (component ``replay``) holds the real transitions in the order the env gave
them: compacted, its rows are the actions that made them and the seeded resets (a
:class:`~torchrl_mbmf.runs.dataset_replay.DatasetReplay` record), rebuilt by replaying them in
the env. ``sac_mbpo``'s model replay (``model_replay``) holds the imagined transitions of its
last rollout rounds: compacted, it is the record of those rounds the checkpoint always holds
(``model_rounds``, :class:`~torchrl_mbmf.world_model.branched_rollouts.RolloutRounds`),
rebuilt by re-running each round into the buffer at its original position (the record leaves
out a parameter set equal to the checkpoint's world model). Either is accepted
only once the rebuilt files pass the checkpoint's integrity record bit for bit.
:func:`~torchrl_mbmf.runs.dataset_replay.compact_checkpoint` and
:func:`~torchrl_mbmf.runs.dataset_replay.expand_checkpoint` call these. Why this works:
``docs/design/run_folder.md``.
"""

from __future__ import annotations

import itertools
import json
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase

from torchrl_mbmf.data import TransitionDataset
from torchrl_mbmf.data.memmap import load_tensor_folder
from torchrl_mbmf.runs.dataset_replay import (
    DatasetReplay,
    NotReplayableError,
    find_resets,
    replay_rows,
)
from torchrl_mbmf.runs.storage import (
    ReplayCheckpointAdapter,
    TensorStateAdapter,
    read_tensor_state,
    verify_checkpoint,
)

__all__ = [
    "REBUILD_DIR",
    "RolloutsLike",
    "compact_replay",
    "expand_replay",
    "replay_components",
]

#: The folder a compacted replay component holds instead of its rows (``data``).
REBUILD_DIR = "rebuild"
_RECORD = "rebuild.json"
_FORMAT = "torchrl_mbmf.replay_rebuild/1"
_DATA = "data"  # ReplayCheckpointAdapter's rows
_STATE_KEY = "observation"


class RolloutsLike(Protocol):
    """What re-runs ``sac_mbpo``'s rollout rounds (a ``BranchedRollouts`` built like the run's).

    Args:
        *args: none (a protocol is not instantiated).
        **kwargs: none.

    Examples:
        >>> sorted(RolloutsLike.__annotations__)
        ['actor', 'replay', 'termination_fn', 'world_model']
    """

    actor: TensorDictModuleBase
    world_model: torch.nn.Module
    termination_fn: object
    replay: TensorDictReplayBuffer

    def imagine_round(self, states: torch.Tensor) -> TensorDictBase:
        """A round's kept transitions from start states drawn from ``states``."""
        ...


def replay_components(checkpoint: Path) -> dict[str, Path]:
    """The replay buffer folders of a checkpoint by component name (from its manifest).

    Args:
        checkpoint: the checkpoint folder.

    Examples:
        >>> import tempfile
        >>> from torchrl_mbmf.runs.storage import SealedWriter
        >>> with tempfile.TemporaryDirectory() as d:
        ...     replay_components(SealedWriter(progress={"a": 1}).save(Path(d) / "c"))
        {}
    """
    manifest = json.loads((checkpoint / "manifest.json").read_text())
    return {
        name: checkpoint / entry["path"]
        for name, entry in manifest["components"].items()
        if entry.get("adapter") == ReplayCheckpointAdapter.adapter_id
    }


def _component(checkpoint: Path, name: str) -> Path:
    manifest = json.loads((checkpoint / "manifest.json").read_text())
    entry = manifest["components"].get(name)
    if entry is None:
        raise NotReplayableError(f"{checkpoint} holds no {name} component")
    return checkpoint / entry["path"]


def _buffer_state(folder: Path) -> tuple[int, list[NestedKey], dict[str, int]]:
    state = json.loads((folder / "replay.json").read_text())
    keys = [tuple(k) if len(k) > 1 else k[0] for k in state["keys"]]
    return int(state["filled"]), keys, {k: int(v) for k, v in state["writer"].items()}


def _tuple(key: NestedKey) -> tuple[str, ...]:
    return key if isinstance(key, tuple) else (key,)


def _pick(keys: list[NestedKey]) -> Any:
    """Maps a collector batch to the entries SAC's replay stores (``SACAgent.observe``)."""
    kept = [k for k in keys if k != "index"]
    return lambda batch: batch.reshape(-1).select(*kept, strict=False)


def _ordered(rows: TensorDictBase, keys: list[NestedKey]) -> TensorDictBase:
    """``rows`` with its entries in the stored order (the buffer's files follow it)."""
    out = TensorDict({}, batch_size=rows.batch_size, device=rows.device)
    for key in keys:
        if key != "index":
            out.set(key, rows.get(key))
    return out


def _write_rows(buffer: TensorDictReplayBuffer, folder: Path) -> None:
    """Writes ``buffer``'s rows as ``folder/data`` (the adapter's own writing)."""
    scratch = Path(tempfile.mkdtemp(prefix=".rebuilt.", dir=folder))
    try:
        ReplayCheckpointAdapter().save(buffer, scratch, args=(), kwargs={})
        shutil.rmtree(folder / _DATA, ignore_errors=True)
        (scratch / _DATA).rename(folder / _DATA)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


# ------------------------------------------------------------ real transitions
def _dataset_actions(checkpoint: Path, rows: int) -> torch.Tensor | None:
    """The first ``rows`` actions of the checkpoint's dataset, if it holds that many."""
    manifest = json.loads((checkpoint / "manifest.json").read_text())
    if "dataset" not in manifest["components"]:
        return None
    dataset = TransitionDataset.load(_component(checkpoint, "dataset") / "transitions")
    if len(dataset) < rows or dataset.action_key != "action":
        return None
    return dataset.tensors().get("action")[:rows]


def _compact_real(
    checkpoint: Path, folder: Path, target: Path, env: EnvBase, seed: int
) -> dict[str, Any]:
    filled, keys, writer = _buffer_state(folder)
    if writer.get("_write_count", filled) != filled:
        raise NotReplayableError(
            f"the replay buffer {folder} has wrapped around ({writer.get('_write_count')} rows "
            f"written, {filled} kept): its oldest rows are not the run's first steps, whose "
            "actions are gone; it cannot be rebuilt from actions"
        )
    if _STATE_KEY not in keys or "action" not in keys:
        raise NotReplayableError(f"{folder} lacks {_STATE_KEY!r} or 'action' (keys {keys})")
    rows = load_tensor_folder(folder / _DATA, keys=[_tuple(k) for k in keys])
    actions = rows.get("action").clone()
    resets = find_resets(rows, actions, _STATE_KEY, env, seed, _pick(keys))
    shared = _dataset_actions(checkpoint, filled)
    if shared is not None and torch.equal(shared, actions):  # sac_mpc, sac_mbpo: stored once
        return {"kind": "real", "actions": "dataset", "resets": [list(r) for r in resets]}
    record = {"num_transitions": filled, "keys": [list(_tuple(k)) for k in keys]}
    DatasetReplay(actions, resets, [(0, 0)], record).save(target / REBUILD_DIR / "actions")
    return {"kind": "real"}


def _expand_real(checkpoint: Path, folder: Path, env: EnvBase, meta: Mapping[str, Any]) -> None:
    filled, keys, _ = _buffer_state(folder)
    if meta.get("actions") == "dataset":  # the dataset's first rows (rebuilt first)
        actions = _dataset_actions(checkpoint, filled)
        resets = [(int(row), int(seed)) for row, seed in meta["resets"]]
    else:
        replay = DatasetReplay.load(folder / REBUILD_DIR / "actions")
        actions, resets = replay.actions, replay.resets
    if actions is None or len(actions) != filled:
        raise NotReplayableError(f"{folder}: no actions for its {filled} rows")
    rows = torch.cat(replay_rows(env, actions, resets, _pick(keys)))
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(filled + 1))
    buffer.extend(_ordered(rows, keys))
    _write_rows(buffer, folder)


# ------------------------------------------------------------ imagined transitions
def _rounds(checkpoint: Path, folder: Path) -> tuple[list[dict[str, Any]], list[Any]]:
    """The recorded rounds, checked to cover every row of the model replay."""
    state = read_tensor_state(_component(checkpoint, "model_rounds"))
    rounds, params = state["rounds"], state["params"]
    filled, _, writer = _buffer_state(folder)
    total = writer.get("_write_count", -1)
    covered = bool(rounds) and rounds[-1]["write_count"] + rounds[-1]["rows"] == total
    covered = covered and rounds[0]["write_count"] <= total - filled
    for a, b in itertools.pairwise(rounds):
        covered = covered and a["write_count"] + a["rows"] == b["write_count"]
    if filled and not covered:
        raise NotReplayableError(
            f"the model replay {folder} holds rows of rollout rounds its model_rounds record "
            "does not cover (a checkpoint written before rounds were recorded, or soon after "
            "a resume from one); it cannot be rebuilt: keep it whole or compact a later one"
        )
    return rounds, params


def _rebuild_model(
    checkpoint: Path, folder: Path, rollouts: RolloutsLike, states: torch.Tensor
) -> TensorDictReplayBuffer:
    """Re-runs the recorded rounds into a fresh buffer at their original positions."""
    rounds, params = _rounds(checkpoint, folder)
    _, keys, _ = _buffer_state(folder)
    if rollouts.replay.storage.device != torch.device("cpu"):
        raise ValueError("the model replay is rebuilt on the CPU only")
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(rollouts.replay.storage.max_size), batch_size=1
    )
    modules = (rollouts.actor, rollouts.world_model, rollouts.termination_fn)
    threads = torch.get_num_threads()
    with torch.random.fork_rng(devices=[]):
        try:
            for r in rounds:
                for module, key in zip(modules, ("actor", "model", "termination"), strict=True):
                    if r[key] >= 0:
                        module.load_state_dict(params[r[key]])
                torch.set_rng_state(r["rng"])
                torch.set_num_threads(int(r["threads"]))
                buffer.writer.load_state_dict(
                    {"_cursor": r["cursor"], "_write_count": r["write_count"]}
                )
                kept = rollouts.imagine_round(states[: r["real"]])
                if kept.numel() != r["rows"]:
                    raise NotReplayableError(
                        f"re-running the rollout round at write {r['write_count']} gives "
                        f"{kept.numel()} rows, the record says {r['rows']}"
                    )
                buffer.extend(_ordered(kept, keys))
        finally:
            torch.set_num_threads(threads)
    return buffer


def _real_states(checkpoint: Path) -> torch.Tensor:
    dataset = TransitionDataset.load(_component(checkpoint, "dataset") / "transitions")
    return dataset.tensors().get(dataset.state_key)


def _check_model(checkpoint: Path, folder: Path, rollouts: RolloutsLike) -> dict[str, Any]:
    filled, keys, _ = _buffer_state(folder)
    buffer = _rebuild_model(checkpoint, folder, rollouts, _real_states(checkpoint))
    stored = load_tensor_folder(folder / _DATA, keys=[_tuple(k) for k in keys])
    rebuilt = buffer.storage[:filled]
    for key in stored.keys(True, True):
        if not torch.equal(rebuilt.get(key), stored.get(key)):
            raise NotReplayableError(
                f"re-running the recorded rollout rounds gives another {key!r} in {folder}: "
                "the model, actor or machine differ from the run's"
            )
    return {"kind": "model"}


# ------------------------------------------------------------ the rounds' record
#: The component whose parameters a round's model parameters may equal (stored once).
_CURRENT = "world_model"


class _State:
    """A state for :class:`TensorStateAdapter` to write."""

    def __init__(self, state: Mapping[str, Any]) -> None:
        self.state = state

    def state_dict(self) -> Mapping[str, Any]:
        return self.state


def _same(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Whether two parameter sets are equal bit for bit."""
    return list(a) == list(b) and all(
        a[k].dtype == b[k].dtype and a[k].cpu().numpy().tobytes() == b[k].cpu().numpy().tobytes()
        for k in a
    )


def _full_rounds(checkpoint: Path, compact: Mapping[str, Any]) -> dict[str, Any]:
    """The ``model_rounds`` state from its compact form (shared sets from the world model)."""
    current = dict(read_tensor_state(_component(checkpoint, _CURRENT)).items())
    shared = set(compact["shared"])
    params = [current if i in shared else p for i, p in enumerate(compact["params"])]
    return {"rounds": compact["rounds"], "params": params}


def _compact_rounds(checkpoint: Path, staging: Path) -> None:
    """Writes ``model_rounds`` without the parameter sets equal to the world model's."""
    folder = _component(checkpoint, "model_rounds")
    state = read_tensor_state(folder)
    current = read_tensor_state(_component(checkpoint, _CURRENT))
    shared = [i for i, p in enumerate(state["params"]) if _same(p, current)]
    if not shared:
        return
    params = [{} if i in shared else p for i, p in enumerate(state["params"])]
    compact = {"rounds": state["rounds"], "params": params, "shared": shared}
    target = staging / folder.relative_to(checkpoint)
    with tempfile.TemporaryDirectory() as scratch:  # the expansion must give the same files
        TensorStateAdapter().save(
            _State(_full_rounds(checkpoint, compact)), Path(scratch), args=(), kwargs={}
        )
        for file in folder.iterdir():
            if (Path(scratch) / file.name).read_bytes() != file.read_bytes():
                return  # kept whole
    shutil.rmtree(target)
    TensorStateAdapter().save(_State(compact), target / REBUILD_DIR, args=(), kwargs={})


def _expand_rounds(checkpoint: Path) -> None:
    """Writes ``model_rounds`` back whole if :func:`_compact_rounds` compacted it."""
    folder = _component(checkpoint, "model_rounds")
    if not (folder / REBUILD_DIR).is_dir():
        return
    state = _full_rounds(checkpoint, read_tensor_state(folder / REBUILD_DIR))
    TensorStateAdapter().save(_State(state), folder, args=(), kwargs={})
    shutil.rmtree(folder / REBUILD_DIR)


# ------------------------------------------------------------ both
def compact_replay(
    checkpoint: Path,
    name: str,
    staging: Path,
    env: EnvBase,
    *,
    seed: int,
    rollouts: RolloutsLike | None = None,
) -> bool:
    """Replaces a replay component's rows in ``staging`` (a copy of ``checkpoint``) by its record.

    The SAC replay (``replay``) is checked by replaying its actions value by value; the model
    replay (``model_replay``) by re-running its recorded rounds, which must give its rows bit for
    bit.

    Args:
        checkpoint: the verified checkpoint.
        name: the component (``replay`` or ``model_replay``).
        staging: the copy being compacted (its rows are removed).
        env: a fresh copy of the run's real env (``num_envs=1``).

    Keyword Args:
        seed: the run's seed.
        rollouts: rollouts built like the run's (``model_replay`` only; their parameters are
            overwritten).

    Returns:
        Whether the component was compacted (``False``: it is empty).

    Raises:
        NotReplayableError: if the rows cannot be rebuilt exactly (naming why).
        ValueError: if ``model_replay`` is given no ``rollouts``.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl.envs.utils import RandomPolicy
        >>> from torchrl_mbmf.collectors import LeanCollector
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.runs.storage import (
        ...     ReplayCheckpointAdapter, SealedWriter, verify_checkpoint)
        >>> env = make_env("Pendulum-v1", seed=0)  # a run's first 300 steps, as SAC stores them
        >>> policy = RandomPolicy(env.full_action_spec)
        >>> batch = next(iter(LeanCollector(env, policy, frames_per_batch=300)))
        >>> keys = ["observation", "action", ("next", "observation"), ("next", "reward"),
        ...         ("next", "done"), ("next", "terminated")]
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(1000))
        >>> _ = buffer.extend(batch.select(*keys))
        >>> saver = SealedWriter().register("replay", buffer, adapter=ReplayCheckpointAdapter())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     saved = saver.save(Path(d) / "ckpt")
        ...     staging = Path(d) / "copy"
        ...     _ = shutil.copytree(saved, staging)
        ...     env = make_env("Pendulum-v1")
        ...     compacted = compact_replay(saved, "replay", staging, env, seed=0)
        ...     expanded = expand_replay(staging, "replay", make_env("Pendulum-v1"))
        ...     verify_checkpoint(staging)  # the rebuilt rows are the saved ones
        >>> compacted, expanded
        (True, True)
    """
    folder = _component(checkpoint, name)
    target = staging / folder.relative_to(checkpoint)
    filled, _, _ = _buffer_state(folder)
    if not filled:
        return False
    if name == "model_replay":
        if rollouts is None:
            raise ValueError(f"{checkpoint}: compacting the model replay needs rollouts=")
        meta = _check_model(checkpoint, folder, rollouts)
        _compact_rounds(checkpoint, staging)
    else:
        meta = _compact_real(checkpoint, folder, target, env, seed)
    shutil.rmtree(target / _DATA)
    (target / REBUILD_DIR).mkdir(exist_ok=True)
    (target / REBUILD_DIR / _RECORD).write_text(json.dumps({"format": _FORMAT, **meta}))
    return True


def expand_replay(
    checkpoint: Path, name: str, env: EnvBase, *, rollouts: RolloutsLike | None = None
) -> bool:
    """Rebuilds in place a replay component :func:`compact_replay` compacted.

    Args:
        checkpoint: the checkpoint (its dataset already rebuilt).
        name: the component.
        env: a fresh copy of the run's real env (``num_envs=1``).

    Keyword Args:
        rollouts: rollouts built like the run's (``model_replay`` only; their parameters are
            overwritten).

    Returns:
        Whether it was rebuilt (``False``: not compacted).

    Raises:
        NotReplayableError: if a record does not fit its rows.
        ValueError: if ``model_replay`` is given no ``rollouts``, or on an unknown record.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.runs.storage import SealedWriter
        >>> with tempfile.TemporaryDirectory() as d:  # a checkpoint without replays
        ...     saved = SealedWriter(progress={"step": 1}).save(Path(d) / "c")
        ...     print(replay_components(saved))
        {}
    """
    folder = _component(checkpoint, name)
    record_file = folder / REBUILD_DIR / _RECORD
    if not record_file.is_file():
        return False
    meta: Mapping[str, Any] = json.loads(record_file.read_text())
    if meta.get("format") != _FORMAT or meta.get("kind") not in ("real", "model"):
        raise ValueError(f"{record_file} has format {meta.get('format')!r}, expected {_FORMAT!r}")
    if meta["kind"] == "model":
        if rollouts is None:
            raise ValueError(f"{checkpoint}: rebuilding the model replay needs rollouts=")
        _expand_rounds(checkpoint)  # then checked: a changed record is refused before re-running
        verify_checkpoint(checkpoint, compacted=(REBUILD_DIR, "replay"))
        buffer = _rebuild_model(checkpoint, folder, rollouts, _real_states(checkpoint))
        _write_rows(buffer, folder)
    else:
        _expand_real(checkpoint, folder, env, meta)
    shutil.rmtree(folder / REBUILD_DIR)
    return True
