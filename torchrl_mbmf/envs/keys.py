"""Tensordict keys of the real and the learned environments (see :mod:`torchrl_mbmf.keys`)."""

from __future__ import annotations

from torchrl_mbmf.keys import *  # noqa: F403
from torchrl_mbmf.keys import __all__  # noqa: F401
