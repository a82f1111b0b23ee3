from __future__ import annotations

import os

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")


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
