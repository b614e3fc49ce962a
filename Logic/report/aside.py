"""Drawing figures in a second process while this one writes the other result files (the command line's time).

matplotlib holds the GIL while it draws, so the figures of ``result_files`` (~1 s of drawing) cannot overlap the
other writes in a thread. A child process can: on Linux the command line forks one (``start``) that computes
``fn(*args)`` (here ``result_files.figures``: {figure: its file's bytes} for the report page and the convergence
plot) on the second core and sends the value back through a pipe, while the parent draws the overlay and writes
the other files and the 3D Slicer scene. The child reads the parent's memory as it was at the fork (nothing is
copied or pickled on the way in) and writes no file: the parent writes what it receives, inside its own folder
transaction.

``finish`` returns the child's value, or None when the child failed, died, or sent nothing within ``timeout_s`` (it
is then killed): the caller then computes the value itself, so the files are the same either way and a child can
cost time but never a result. The child never outlives its use: it ignores Ctrl-C (the parent, stopping, kills it:
``cancel``), and when the parent is gone its send fails (it holds no reading end of the pipe) and it exits. Not used
where forking is unsafe or unavailable (``available``: anything but Linux, whose ``fork`` start method needs no
re-import) nor in the window (Qt); there the caller draws in order as before.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import warnings
from dataclasses import dataclass

FINISH_TIMEOUT_S = 10.0  # drawing takes ~1 s; a child silent this long is taken as hung, killed and replaced
# (drawing in the process instead costs ~0.6 s more)
_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@dataclass
class Aside:
    """A forked child computing a value (``start``); ``finish`` collects it."""

    process: object
    receive: object


def available() -> bool:
    """Whether ``start`` can fork here (Linux with multiprocessing's ``fork`` start method)."""
    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


def start(fn, *args) -> Aside | None:
    """Fork a child that computes ``fn(*args)`` and sends it back (picklable); None when forking is not
    ``available`` or fails (the caller then computes it itself). Termination signals are held while forking, so
    none can unwind the parent's stack (its open folder transaction) inside the child."""
    if not available():
        return None
    context = multiprocessing.get_context("fork")
    receive, send = context.Pipe(duplex=False)
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    try:
        with warnings.catch_warnings():  # Python >= 3.12 warns on forking a process with threads (numba's idle
            warnings.simplefilter("ignore", DeprecationWarning)  # workers); the child runs no numba code
            process = context.Process(target=_child, args=(receive, send, fn, args, held), daemon=True)
            process.start()
    except OSError:
        receive.close()
        return None
    finally:
        send.close()
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
    return Aside(process, receive)


def _child(receive, send, fn, args, held) -> None:
    """The child: send ("value", fn(*args)), or ("error", its message) when it raised (module docstring)."""
    receive.close()  # the parent's end: with it closed here, a send to a parent that is gone fails at once
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for signum in _SIGNALS:
        if signum != signal.SIGINT:
            signal.signal(signum, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_SETMASK, held)
    try:
        message = ("value", fn(*args))
    except Exception as exc:  # the parent computes the value itself and meets the error there
        message = ("error", f"{type(exc).__name__}: {exc}")
    try:
        send.send(message)
        send.close()
    except OSError:  # the parent is gone
        os._exit(0)


def finish(aside: Aside | None, timeout_s: float = FINISH_TIMEOUT_S):
    """The child's value, or None (module docstring); the child is gone when this returns."""
    if aside is None:
        return None
    try:
        kind, value = aside.receive.recv() if aside.receive.poll(timeout_s) else ("silent", None)
    except (EOFError, OSError):  # the child died before sending
        kind, value = "died", None
    cancel(aside, exiting_s=1.0 if kind == "value" else 0.0)
    return value if kind == "value" else None


def cancel(aside: Aside | None, exiting_s: float = 0.0) -> None:
    """The pipe closed and the child gone: given ``exiting_s`` to exit by itself (it sent its value), else killed
    (it failed to, or the parent stopped before ``finish``: an error, Ctrl-C)."""
    if aside is None:
        return
    aside.receive.close()
    aside.process.join(exiting_s)
    if aside.process.is_alive():
        aside.process.kill()
        aside.process.join()
