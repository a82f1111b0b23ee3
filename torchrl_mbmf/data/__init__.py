from torchrl_mbmf.data.mixed_replay import MixedReplaySampler
from torchrl_mbmf.data.replay import ReplaySampler
from torchrl_mbmf.data.transitions import (
    CorruptDatasetError,
    DatasetMismatchError,
    TransitionDataset,
    collect_random_transitions,
)

__all__ = [
    "CorruptDatasetError",
    "DatasetMismatchError",
    "MixedReplaySampler",
    "ReplaySampler",
    "TransitionDataset",
    "collect_random_transitions",
]
