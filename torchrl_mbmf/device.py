"""The device of a run's networks, world model, planner and updates (the envs stay on the CPU)."""

from __future__ import annotations

import torch

__all__ = ["DEVICE_CHOICES", "DeviceError", "keep_freed_memory", "resolve_device"]

#: Values the ``device`` setting takes besides ``cuda:N``.
DEVICE_CHOICES: tuple[str, ...] = ("cpu", "cuda", "auto")


class DeviceError(ValueError):
    """The ``device`` setting names a device this machine does not have."""


def resolve_device(value: str | torch.device) -> torch.device:
    """Turns the ``device`` setting into a :class:`torch.device`, checking it exists here.

    ``"auto"`` picks the first CUDA GPU when torch sees one, else the CPU; ``"cuda"`` and
    ``"cuda:N"`` must name a GPU torch can use.

    Args:
        value: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``.

    Raises:
        DeviceError: for another value, or a GPU torch does not see, naming the ``device``
            key and what is available.

    Examples:
        >>> from torchrl_mbmf.device import resolve_device
        >>> resolve_device("cpu")
        device(type='cpu')
        >>> resolve_device("auto").type in ("cpu", "cuda")
        True
    """
    name = str(value)
    if name == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        index = 0 if name == "cuda" else name.split(":", 1)[1]
        if not str(index).isdigit():
            raise DeviceError(f"device={name!r}: the GPU index must be a number, as in 'cuda:0'")
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if int(index) >= count:
            seen = f"{count} GPU(s)" if count else "no GPU (torch.cuda.is_available() is False)"
            raise DeviceError(
                f"device={name!r} asks for a CUDA GPU but torch sees {seen}; use device=cpu "
                "or device=auto"
            )
        return torch.device(f"cuda:{int(index)}")
    raise DeviceError(
        f"device={name!r} is not supported; allowed: {list(DEVICE_CHOICES)} or 'cuda:N'"
    )


def keep_freed_memory(mmap_threshold: int = 256 * 2**20, trim_threshold: int = 2**30) -> bool:
    """Makes glibc's ``malloc`` keep freed memory for reuse instead of unmapping it.

    Eager PyTorch on CPU allocates and frees every intermediate tensor; with glibc's defaults
    blocks above a (dynamic) threshold are ``mmap``-ed and returned to the system on free, so
    the next update touches fresh pages and pays a page fault per 4 KiB (about 600 per SAC
    update at batch 256 with 256-wide networks, a sizeable share of its time on a VM). Raising
    the mmap and trim thresholds keeps those blocks in the heap. Process-wide and
    irreversible for the process; it changes no numbers, only where memory comes from (the
    process keeps up to ``trim_threshold`` bytes of freed memory). Call it once at start-up.

    Args:
        mmap_threshold: allocations of at least this many bytes are still ``mmap``-ed.
            Defaults to 256 MiB.
        trim_threshold: free memory at the top of the heap beyond this is returned to the
            system. Defaults to 1 GiB.

    Returns:
        whether the settings were applied (``False`` where the C library is not glibc).

    Examples:
        >>> from torchrl_mbmf.device import keep_freed_memory
        >>> isinstance(keep_freed_memory(), bool)
        True
    """
    if mmap_threshold <= 0 or trim_threshold <= 0:
        raise ValueError(
            f"keep_freed_memory: thresholds must be positive, got {mmap_threshold}, "
            f"{trim_threshold}"
        )
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc <malloc.h>
    return bool(mallopt(m_mmap_threshold, int(mmap_threshold))) and bool(
        mallopt(m_trim_threshold, int(trim_threshold))
    )
