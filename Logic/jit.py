"""Compiled kernels that run wherever the user can run Python.

numba's ``cache=True`` keeps compiled kernels on disk (beside the source in ``__pycache__``, or in
``$NUMBA_CACHE_DIR``, or in the user cache ``~/.cache/numba``); when none of those is writable (a service
account, a container with a random UID, a read-only install) numba refuses to even define the function
("cannot cache function ...: no locator available"). ``njit`` here asks for the disk cache and, when numba
finds no writable place, compiles the kernel in memory instead (every process then compiles it once, about
10 s) and says so once, in one line on the ``carmreg`` logger (stderr when logging is not configured).
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
            return numba.njit(cache=True, **options)(func)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available for file ..."
            if "locator" not in str(exc):
                raise
            _note_no_cache(func.__qualname__, "neither the install, $NUMBA_CACHE_DIR nor the user cache folder "
                           "is writable")
            return numba.njit(cache=False, **options)(func)

    return decorate


def kernels_cached() -> bool:
    """False when some kernel had to be compiled in memory (no writable cache)."""
    return not _NOTED
