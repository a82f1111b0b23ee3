"""The exported policy's integrity record: verified on load, damage and edits refused."""

from __future__ import annotations

import json
import logging
import pickle

import pytest
import torch

from torchrl_mbmf.runs.export import CorruptPolicyError, read_policy_state, save_policy
from torchrl_mbmf.runs.layout import POLICY, POLICY_RECORD


@pytest.fixture
def run(tmp_path):
    torch.manual_seed(0)
    save_policy(torch.nn.Linear(3, 2), tmp_path, step=42)
    return tmp_path


def test_round_trip_and_record(run):
    record = json.loads((run / POLICY_RECORD).read_text())
    assert record["size"] == (run / POLICY).stat().st_size and record["real_steps"] == 42
    state, steps = read_policy_state(run)
    assert steps == 42 and set(state) == {"weight", "bias"}


def _flip_a_bit(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def _nan_weights_rewritten(path):
    saved = torch.load(path, weights_only=True)
    saved["state_dict"]["weight"][0, 0] = float("nan")
    torch.save(saved, path)


def _truncated(path):
    path.write_bytes(path.read_bytes()[:1000])


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (_flip_a_bit, "SHA-256 differs"),
        (_nan_weights_rewritten, "bytes, its record|SHA-256 differs"),
        (_truncated, "bytes, its record"),
    ],
)
def test_damaged_or_edited_policy_is_refused(run, damage, message):
    damage(run / POLICY)
    with pytest.raises(CorruptPolicyError, match=message):
        read_policy_state(run)


def test_without_a_record_nan_truncation_and_pickles_are_still_refused(run, caplog):
    (run / POLICY_RECORD).unlink()
    with caplog.at_level(logging.WARNING):
        assert read_policy_state(run)[1] == 42
    assert "no integrity record" in caplog.text
    _nan_weights_rewritten(run / POLICY)
    with pytest.raises(CorruptPolicyError, match=r"NaN or Inf weights in \['weight'\]"):
        read_policy_state(run)
    (run / POLICY).write_bytes(pickle.dumps({"state_dict": {}, "real_steps": 1}))
    with pytest.raises(CorruptPolicyError, match="pickle this package never loads"):
        read_policy_state(run)
    _truncated_source = torch.nn.Linear(3, 2)
    save_policy(_truncated_source, run, step=1)
    (run / POLICY_RECORD).unlink()
    _truncated(run / POLICY)
    with pytest.raises(CorruptPolicyError, match="cannot be loaded as a policy export"):
        read_policy_state(run)


def test_a_garbage_record_is_named(run):
    (run / POLICY_RECORD).write_text("{oops")
    with pytest.raises(CorruptPolicyError, match=r"policy\.json is not valid JSON"):
        read_policy_state(run)


def test_run_folder_names_damaged_files_and_skips_garbage_rows(tmp_path, caplog):
    from torchrl_mbmf.runs.layout import RunFolder

    run = RunFolder(tmp_path)
    run.write_record({"seed": 0})
    (tmp_path / "summary.json").write_text("{garbage")
    with pytest.raises(ValueError, match=r"summary\.json' is not valid JSON"):
        run.read_summary()
    (tmp_path / "config.yaml").write_text("a: [unclosed")
    with pytest.raises(ValueError, match=r"config\.yaml' is not valid YAML"):
        run.read_config()
    csv = run.scalar_file("train/episode_return")
    csv.parent.mkdir(parents=True)
    csv.write_text("100,1.5\n200,nan\nabc,2\n300,inf\n400\n500,2.5\n")
    with caplog.at_level(logging.WARNING):
        steps, values = run.read_scalar("train/episode_return")
    assert steps.tolist() == [100, 500] and values.tolist() == [1.5, 2.5]
    assert "left out 4 row(s)" in caplog.text and "[2, 3, 4, 5]" in caplog.text


def test_a_kill_during_the_export_leaves_only_run_files(tmp_path):
    """The staging files of an interrupted export are a run's own: a rerun may resume."""
    from torchrl_mbmf.runs.claim import claim_run_folder

    save_policy(torch.nn.Linear(3, 2), tmp_path, step=1)
    (tmp_path / f"{POLICY}.tmp").write_bytes(b"partial")
    (tmp_path / f"{POLICY_RECORD}.tmp").write_text("{")
    claim_run_folder(tmp_path, {"seed": 0}).release()
