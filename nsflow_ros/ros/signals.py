"""Quiet, prompt shutdown on SIGINT and SIGTERM for the package's ROS processes.

rclpy's own handlers shut the context down inside the signal handler, so the summary logged next meets an
invalid context; instead rclpy starts without them (:func:`init_without_signal_handlers`) and
:class:`StopSignals` only records the first signal, letting the process finish in order and exit 0. A
second signal raises :class:`StopRequested` at once, for a process stuck somewhere.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType
from typing import Any

__all__ = ["STOP_SIGNALS", "StopRequested", "StopSignals", "init_without_signal_handlers"]

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequested(BaseException):
    """Raised by :class:`StopSignals` (``raise_now=True``, or a second signal): stop what you are doing."""


class StopSignals:
    """Context manager: SIGINT / SIGTERM set :attr:`requested` (and raise :class:`StopRequested` if asked).

    Args:
        raise_now: raise :class:`StopRequested` in the main thread on the first signal (for code that only
            sleeps and publishes); False = only set the event, the caller polls it.

    Attributes:
        requested: set once a signal came.
        signum: the first signal received, or None.
    """

    def __init__(self, *, raise_now: bool = False) -> None:
        self.raise_now = raise_now
        self.requested = threading.Event()
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        first = not self.requested.is_set()
        self.requested.set()
        if first:
            self.signum = signum
        if self.raise_now or not first:
            raise StopRequested(signal.Signals(signum).name)

    def install(self) -> StopSignals:
        """Install the handlers (only the main thread can; elsewhere this does nothing)."""
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def restore(self) -> None:
        """Put the previous handlers back."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(
        self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.restore()


def init_without_signal_handlers(args: list[str] | None = None, context: Any = None) -> None:
    """``rclpy.init`` without rclpy's signal handlers (pair it with :class:`StopSignals`)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)
