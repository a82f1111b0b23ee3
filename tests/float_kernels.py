"""Whether this machine computes the same float bits as the one the pins were recorded on.

Float kernels differ between CPUs (AVX-512 against AVX2, AMD against Intel) and BLAS builds,
so a hash of weights, or the exact episode returns of a training run, is only comparable on a
machine with the recording machine's kernels. The canary is a stock model and a short stock
Adam fit on fixed data; its hash equals :data:`CANARY` only on such a machine. The pinned
tests compare hashes and exact floats where it does, and readable numbers within a tolerance
elsewhere (``tests/modules/test_stack_pins.py``, ``tests/recipes/test_run_pins.py``).
"""

from __future__ import annotations

import functools
import hashlib

import torch

from torchrl_mbmf.modules import DeltaDynamicsModel

#: The canary's hash on the machine the pins were recorded on (AMD EPYC, torch's AVX512 kernels).
CANARY = "fcc542876eb9711111b89c40e385ba72657615d11730176cca998dada3611cb1"


def sha(*tensors: torch.Tensor) -> str:
    """SHA-256 of the tensors' bytes, in order."""
    h = hashlib.sha256()
    for t in tensors:
        h.update(t.detach().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()


def canary() -> str:
    """Stock model outputs and a short stock fit: equal only on the same float kernels."""
    with torch.random.fork_rng():
        torch.manual_seed(0)
        model = DeltaDynamicsModel(18, 6, hidden_sizes=(32, 32))
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        x = torch.randn(64, 24)
        for _ in range(3):
            loss = model.net(x).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        return sha(model.net(x), *model.parameters())


@functools.cache
def recording_kernels() -> bool:
    """True where the canary reproduces :data:`CANARY` (computed once per test process)."""
    return canary() == CANARY


#: The reason given where a pinned hash or exact float is not compared.
OTHER_KERNELS_REASON = "float kernels of this machine differ from those the pins were recorded on"
