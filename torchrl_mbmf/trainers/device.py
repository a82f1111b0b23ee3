"""The device of a run's networks, world model, planner and updates (the envs stay on the CPU)."""

from __future__ import annotations

import torch

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
        >>> from torchrl_mbmf.trainers.device import resolve_device
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
