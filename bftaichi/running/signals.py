"""SIGTERM and SIGHUP end a command the way Ctrl-C does.

A service manager (systemd, ``docker stop``, ``timeout``) ends a process with SIGTERM; a closed
terminal sends SIGHUP. Inside :func:`handled` both raise :class:`Terminated`, a
``KeyboardInterrupt``, so the run's failure handling runs as for Ctrl-C: the staged outputs are
discarded, the failure is recorded (``status: interrupted``), and the command exits with
``128 + n`` (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP).
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["Terminated", "handled", "describe_interrupt", "exit_code"]

_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class Terminated(KeyboardInterrupt):
    """The process received ``signum`` (SIGTERM or SIGHUP)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise(signum, frame):
    raise Terminated(signum)


@contextlib.contextmanager
def handled():
    """SIGTERM and SIGHUP raise :class:`Terminated` inside the block (main thread only;
    elsewhere Python cannot install handlers and the block runs unchanged)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in _SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _signum(error: BaseException | None) -> int:
    while error is not None:  # click wraps the KeyboardInterrupt in its Abort
        if isinstance(error, Terminated):
            return error.signum
        if isinstance(error, KeyboardInterrupt):
            return signal.SIGINT
        error = error.__cause__ or error.__context__
    return signal.SIGINT


def describe_interrupt(error: BaseException | None) -> str:
    """``interrupted (Ctrl-C)`` or ``interrupted by SIGTERM``."""
    n = _signum(error)
    return "interrupted (Ctrl-C)" if n == signal.SIGINT else \
        f"interrupted by {signal.Signals(n).name}"


def exit_code(error: BaseException | None) -> int:
    """128 + the signal number."""
    return 128 + int(_signum(error))
