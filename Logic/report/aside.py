"""Drawing figures in a second process while this one writes the other result files (the command line's time).

matplotlib holds the GIL while it draws, so the figures of ``result_files`` (the convergence and similarity plots
and the report page, ~1 s) cannot overlap the other writes in a thread. A child process can: on Linux the
command line forks one (``start``) that computes ``fn(*args)`` (bytes to write) on the second core and sends the
value back through a pipe, while the parent writes the overlay, the DRR and the 3D Slicer scene. The child reads
the parent's memory as it was at the fork (nothing is copied or pickled on the way in) and writes no file: the
parent writes what it receives, inside its own folder transaction.

``finish`` returns the child's value, or None when the child failed, was killed, or sent nothing within
``timeout_s`` (it is then killed): the caller then computes the value itself, so the files are the same either way
and a child can cost time but never a result. Not used where forking is unsafe or unavailable (``available``:
anything but Linux, whose ``fork`` is the only start method that needs no re-import) nor in the window (Qt); there
the caller draws in order as before.
"""

from __future__ import annotations

import multiprocessing
import signal
import sys
import warnings
from dataclasses import dataclass

FINISH_TIMEOUT_S = 60.0  # drawing takes ~1 s; a child silent for this long is taken as hung, killed, replaced


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
    ``available`` or fails (the caller then computes it itself)."""
    if not available():
        return None
    context = multiprocessing.get_context("fork")
    receive, send = context.Pipe(duplex=False)
    try:
        with warnings.catch_warnings():  # Python >= 3.12 warns on forking a process with threads (numba's idle
            warnings.simplefilter("ignore", DeprecationWarning)  # workers); the child runs no numba code
            process = context.Process(target=_child, args=(send, fn, args), daemon=True)
            process.start()
    except OSError:
        receive.close()
        return None
    finally:
        send.close()
    return Aside(process, receive)


def _child(send, fn, args) -> None:
    """The child: send ("value", fn(*args)), or ("error", its message) when it raised. Ctrl-C reaches the whole
    process group: the child ignores it (no second traceback) and the parent, stopping, kills it (``cancel``)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        message = ("value", fn(*args))
    except Exception as exc:  # the parent computes the value itself and meets the error there
        message = ("error", f"{type(exc).__name__}: {exc}")
    send.send(message)
    send.close()


def finish(aside: Aside | None, timeout_s: float = FINISH_TIMEOUT_S):
    """The child's value, or None (module docstring); the child is gone when this returns."""
    if aside is None:
        return None
    try:
        kind, value = aside.receive.recv() if aside.receive.poll(timeout_s) else ("silent", None)
    except (EOFError, OSError):  # the child died before sending
        kind, value = "died", None
    finally:
        aside.receive.close()
    if kind != "value":
        aside.process.kill()
    aside.process.join(5.0)
    return value if kind == "value" else None


def cancel(aside: Aside | None) -> None:
    """Kill the child, if it is still there (the parent stopped before ``finish``: an error, Ctrl-C)."""
    if aside is not None and aside.process.is_alive():
        aside.process.kill()
        aside.process.join(5.0)
