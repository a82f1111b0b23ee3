"""The run folder on disk: its files, checkpoints, resume, logs, exported policy, compact data."""

from torchrl_mbmf.runs.checkpoint import RunCheckpoint
from torchrl_mbmf.runs.claim import (
    FinishedRunError,
    RunFolderError,
    RunFolderLock,
    claim_run_folder,
)
from torchrl_mbmf.runs.dataset_replay import DatasetReplay, compact_checkpoint, expand_checkpoint
from torchrl_mbmf.runs.export import load_policy, save_policy, variant_tag
from torchrl_mbmf.runs.layout import RunFolder, write_run_record
from torchrl_mbmf.runs.resume import fingerprint
from torchrl_mbmf.runs.summary_text import end_of_run_message, format_seconds

__all__ = [
    "DatasetReplay",
    "FinishedRunError",
    "RunCheckpoint",
    "RunFolder",
    "RunFolderError",
    "RunFolderLock",
    "claim_run_folder",
    "compact_checkpoint",
    "end_of_run_message",
    "expand_checkpoint",
    "fingerprint",
    "format_seconds",
    "load_policy",
    "save_policy",
    "variant_tag",
    "write_run_record",
]
