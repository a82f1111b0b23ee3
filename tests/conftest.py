from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")
# the shared test helpers (tests/rl_helpers.py) import as a top-level module
sys.path.insert(0, str(Path(__file__).resolve().parent))


@pytest.fixture(autouse=True)
def _seed_and_threads():
    """Seeded, single-threaded tests.

    Tiny networks gain nothing from two threads, and on a shared 2-core machine a 2-thread
    OpenMP region waits on whichever core another process holds (measured 0.2 s vs 9 s).
    """
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


class _WritesMarker:
    """Unpickling this object creates the file ``marker`` (stands for arbitrary code)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture
def plant_pickle(tmp_path_factory):
    """Adds a pickled non-tensor entry ``name`` to a ``TensorDict.memmap`` folder.

    ``TensorDict.load_memmap`` would unpickle it and create the returned marker file.
    """
    import json
    import shutil

    from tensordict import TensorDict

    def plant(folder, name: str = "payload"):
        scratch = tmp_path_factory.mktemp("pickle")
        marker = scratch / "marker"
        meta_file = folder / "meta.json"
        meta = json.loads(meta_file.read_text())
        td = TensorDict(batch_size=meta["shape"])
        td.set_non_tensor(name, _WritesMarker(str(marker)))
        td.memmap(scratch / "td")
        shutil.copytree(scratch / "td" / name, folder / name)
        meta[name] = {"type": "NonTensorData"}
        meta_file.write_text(json.dumps(meta))
        return marker

    return plant
