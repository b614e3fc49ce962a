"""Termination signals unwind the command like Ctrl-C, wherever they land.

SIGTERM and SIGHUP raise ``SystemExit(128 + signal)``, so every ``finally`` and context manager runs: temporary
files and staging folders are removed. Python delivers a signal between two bytecodes of the main thread; when
those bytecodes belong to a finaliser (``__del__``, a weakref callback) the exception cannot propagate, and
Python would print it as "Exception ignored" and carry on. The unraisable hook installed here catches exactly
that case (a ``SystemExit`` from these handlers, or a ``KeyboardInterrupt``), prints nothing, and sends the same
signal again a moment later, so it lands in ordinary code and the command still stops.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

HANDLED = ("SIGTERM", "SIGHUP")
REDELIVER_AFTER_S = 0.02


def _terminate(signum, frame):
    raise SystemExit(128 + signum)


def _swallowed_signal(exc) -> int | None:
    """The signal whose exception a finaliser swallowed, or None if ``exc`` is not one of ours."""
    if isinstance(exc, KeyboardInterrupt):
        return int(signal.SIGINT)
    codes = {128 + int(getattr(signal, name)): int(getattr(signal, name)) for name in HANDLED if hasattr(signal, name)}
    if isinstance(exc, SystemExit) and exc.code in codes:
        return codes[exc.code]
    return None


def _redeliver(signum: int) -> None:
    timer = threading.Timer(REDELIVER_AFTER_S, os.kill, (os.getpid(), signum))
    timer.daemon = True
    timer.start()


def install() -> None:
    """Install the handlers and the hook (main thread only; elsewhere this does nothing)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for name in HANDLED:
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _terminate)
    previous = sys.unraisablehook

    def hook(unraisable):
        signum = _swallowed_signal(unraisable.exc_value)
        if signum is None:
            previous(unraisable)
        else:
            _redeliver(signum)

    sys.unraisablehook = hook
