"""Compiled kernels that run wherever the user can run Python.

numba's ``cache=True`` keeps compiled kernels on disk (beside the source in ``__pycache__``, or in
``$NUMBA_CACHE_DIR``, or in the user cache ``~/.cache/numba``); when none of those is writable (a service
account, a container with a random UID, a read-only install) numba refuses to even define the function
("cannot cache function ...: no locator available"). ``njit`` here asks for the disk cache and, when numba
finds no writable place, compiles the kernel in memory instead (every process then compiles it once, about
10 s) and says so once, in one line on the ``carmreg`` logger (stderr when logging is not configured). A cache
folder that fills up later (no space left) costs the same note, not a traceback.
"""

from __future__ import annotations

import logging

import numba

LOGGER = logging.getLogger("carmreg")
_NOTED: list[str] = []


def _note_no_cache(name: str, reason: str) -> None:
    if not _NOTED:
        LOGGER.warning("carmreg: note: no writable cache for compiled kernels (%s); they are compiled in memory "
                       "in every run (about 10 s more; set NUMBA_CACHE_DIR to a writable folder to keep them)",
                       reason)
    _NOTED.append(name)


def njit(**options):
    """``numba.njit(cache=True, **options)`` where a cache can be written, else ``numba.njit(**options)``."""

    def decorate(func):
        try:
            dispatcher = numba.njit(cache=True, **options)(func)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available for file ..."
            if "locator" not in str(exc):
                raise
            _note_no_cache(func.__qualname__, "neither the install, $NUMBA_CACHE_DIR nor the user cache folder "
                           "is writable")
            return numba.njit(cache=False, **options)(func)
        _tolerate_failed_saves(dispatcher, func.__qualname__)
        return dispatcher

    return decorate


def _tolerate_failed_saves(dispatcher, name: str) -> None:
    """A cache folder that fills up or turns read-only later (numba writes after compiling, and the kernel
    is already usable then): the save is skipped with the one-line note instead of a traceback."""
    cache = getattr(dispatcher, "_cache", None)
    save = getattr(cache, "save_overload", None)
    if save is None:
        return

    def save_or_note(sig, data):
        try:
            save(sig, data)
        except OSError as exc:
            _note_no_cache(name, f"writing to it failed: {exc.strerror or exc}")

    cache.save_overload = save_or_note


def kernels_cached() -> bool:
    """False when some kernel had to be compiled in memory (no writable cache)."""
    return not _NOTED
