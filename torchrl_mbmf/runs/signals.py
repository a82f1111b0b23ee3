"""Stop signals for a training run: the first SIGTERM/SIGINT stops at the next checkpoint.

A checkpoint ends the collector in progress, and the next one starts from envs seeded with
``seed + real_steps``; a checkpoint at an unscheduled step would therefore change the data. So
the first signal lets the run go on to its next scheduled checkpoint, save it and stop (exit
code 0; rerunning the same command resumes to the same weights as an uninterrupted run). A
second signal stops at once, without a checkpoint (the rerun resumes from the previous one).
"""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType, TracebackType

__all__ = ["StopRequest"]

log = logging.getLogger(__name__)


class StopRequest:
    """Catches SIGTERM and SIGINT while a run trains (a context manager).

    Handlers are installed only in the main thread; elsewhere the object never requests a stop.

    Args:
        signals: the signals to catch. Defaults to ``(SIGTERM, SIGINT)``.

    Examples:
        >>> import os, signal
        >>> from torchrl_mbmf.runs.signals import StopRequest
        >>> with StopRequest() as stop:
        ...     os.kill(os.getpid(), signal.SIGTERM)
        ...     stop.requested
        'SIGTERM'
    """

    def __init__(
        self, signals: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGINT)
    ) -> None:
        self.signals = signals
        self.requested: str | None = None
        self._previous: dict[signal.Signals, object] = {}

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in self.signals:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        self._previous.clear()

    def keep_installed(self) -> None:
        """Puts the handlers back if a library replaced them since (torchrl's storages do)."""
        for sig in self._previous:
            if signal.getsignal(sig) != self._handle:
                signal.signal(sig, self._handle)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.requested is None:
            self.requested = name
            log.warning(
                "%s received: the run stops after its next checkpoint; send it again to stop "
                "at once without one",
                name,
            )
            return
        log.warning("second %s: stopping now; a rerun resumes from the last checkpoint", name)
        raise SystemExit(128 + signum)
