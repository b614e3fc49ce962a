"""Termination signals in the window: Ctrl-C in the terminal, ``kill``, a logout (SIGINT, SIGTERM, SIGHUP).

Python runs a signal handler only between two of its own bytecodes, and Qt's event loop, waiting for events, runs
none: a handler installed with ``signal.signal`` alone never fires while the window is idle (the command line's
``signals`` module raises ``SystemExit`` there, which an event loop could not unwind anyway). So the C-level
handler also writes a byte to a socket (``signal.set_wakeup_fd``) that Qt watches (``QSocketNotifier``): the
event loop wakes, runs a little Python, the pending handler runs in it, and it asks the window to quit without a
question (``CarmRegWidget.close_for_signal``: unsaved work kept in the autosave, the application's exit code
128 + the signal's number, as a shell reports a killed command).
"""

from __future__ import annotations

import signal
import socket

from qtpy import QtCore

HANDLED = ("SIGINT", "SIGTERM", "SIGHUP")


def quit_window_on_signals(app, window) -> None:
    """Route ``HANDLED`` signals to ``window.close_for_signal(signum)`` through ``app``'s event loop (main
    thread only; the sockets and the notifier live as long as ``app``)."""
    receive, send = socket.socketpair()
    receive.setblocking(False)
    send.setblocking(False)
    signal.set_wakeup_fd(send.fileno(), warn_on_full_buffer=False)
    # no Qt parent: Python owns it, so dropping it (``restore_default_signals``) deletes it at once and a later
    # notifier on a reused descriptor number is the only one
    notifier = QtCore.QSocketNotifier(receive.fileno(), QtCore.QSocketNotifier.Type.Read)

    def drain() -> None:  # the pending Python handler runs around this call
        try:
            receive.recv(256)
        except OSError:
            pass

    def handler(signum, _frame) -> None:
        QtCore.QTimer.singleShot(0, lambda: window.close_for_signal(signum))

    notifier.activated.connect(drain)
    for name in HANDLED:
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), handler)
    app._carmreg_signal_wakeup = (receive, send, notifier)  # alive as long as the application


def restore_default_signals(app) -> None:
    """Undo ``quit_window_on_signals`` (tests): the default handlers back, no wakeup socket."""
    signal.set_wakeup_fd(-1)
    for name in HANDLED:
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.default_int_handler if name == "SIGINT" else signal.SIG_DFL)
    held = getattr(app, "_carmreg_signal_wakeup", None)
    if held is not None:
        receive, send, notifier = held
        notifier.setEnabled(False)
        receive.close()
        send.close()
        app._carmreg_signal_wakeup = None
