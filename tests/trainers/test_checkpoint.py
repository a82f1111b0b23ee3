"""Replay-buffer checkpoints hold the filled rows only and restore the buffer exactly."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_mbmf.runs.storage import ReplayCheckpointAdapter as _ReplayAdapter


def _buffer(capacity: int) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=8)


def _folder_bytes(path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _rows(n: int, offset: int = 0) -> TensorDict:
    return TensorDict(
        {"obs": torch.arange(offset, offset + n).float().unsqueeze(-1).expand(n, 17).clone()},
        [n],
    )


def test_replay_checkpoint_writes_filled_rows_and_restores_sampling(tmp_path):
    source = _buffer(1_000_000)
    source.extend(_rows(300))
    _ReplayAdapter().save(source, tmp_path, args=(), kwargs={})
    # 300 x 17 float32 rows (~20 kB), not the 1e6-row capacity (68 MB)
    assert _folder_bytes(tmp_path) < 200_000

    restored = _buffer(1_000_000)
    restored.extend(_rows(5, offset=900))  # stale content is replaced
    _ReplayAdapter().load(restored, tmp_path)
    assert len(restored) == 300
    torch.testing.assert_close(restored.storage[:300]["obs"], source.storage[:300]["obs"])
    torch.manual_seed(1)
    a = source.sample()
    torch.manual_seed(1)
    b = restored.sample()
    torch.testing.assert_close(a["obs"], b["obs"])
    # the next writes land at the same positions
    source.extend(_rows(4, offset=5000))
    restored.extend(_rows(4, offset=5000))
    torch.testing.assert_close(restored.storage[:304]["obs"], source.storage[:304]["obs"])


def test_replay_checkpoint_keeps_the_cursor_after_wrapping(tmp_path):
    source = _buffer(10)
    source.extend(_rows(13))  # wrapped: rows 10..12 overwrote positions 0..2
    _ReplayAdapter().save(source, tmp_path, args=(), kwargs={})
    restored = _buffer(10)
    _ReplayAdapter().load(restored, tmp_path)
    torch.testing.assert_close(restored.storage[:10]["obs"], source.storage[:10]["obs"])
    source.extend(_rows(2, offset=100))
    restored.extend(_rows(2, offset=100))
    torch.testing.assert_close(restored.storage[:10]["obs"], source.storage[:10]["obs"])


def test_empty_replay_checkpoint_round_trips(tmp_path):
    _ReplayAdapter().save(_buffer(100), tmp_path, args=(), kwargs={})
    restored = _buffer(100)
    restored.extend(_rows(3))
    _ReplayAdapter().load(restored, tmp_path)
    assert len(restored) == 0
