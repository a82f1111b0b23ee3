"""torchrl_mbmf: model-based + model-free reinforcement learning components for TorchRL."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("torchrl_mbmf")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
