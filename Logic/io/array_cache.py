"""A folder of cached float32 arrays: the DRR databases (``db``) and the CT's attenuation levels (``mu``).

Each entry is ``<prefix>-<key>.npy`` (the raw array; memory-mapped on load, so a large one costs no copy) beside
``<prefix>-<key>.json`` (key, shape, format version, the data file's SHA-256 when it was written, and the
caller's extra fields, e.g. an affine). An entry that cannot be read, whose key, shape or format differs, whose
data no longer match the recorded SHA-256, that holds non-finite values, or that is not a regular file (a pipe, a
device) is a miss: rebuilt, never trusted. Each write first sweeps the folder: temporary files a killed run left
(older than ``STALE_TEMP_SECONDS``) go, and the least recently used entries go until the folder fits
``MAX_CACHE_BYTES``. A cache that cannot be written costs only the next run's time: the write returns a note in
words instead of raising.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from pathlib import Path

import numpy as np

from carmreg.logic.io.atomic import atomic_write, atomic_write_json, file_sha256
from carmreg.logic.io.limits import file_kind

PREFIXES = ("db", "mu")
MAX_CACHE_BYTES = 4 * 1024**3
"""Cap of the cache folder: the least recently used entries are deleted beyond it."""
STALE_TEMP_SECONDS = 15 * 60.0
"""A hidden temporary file older than this was left by a killed run (a write takes seconds)."""
MAX_SIDECAR_BYTES = 64 * 1024


def _paths(cache_dir, prefix: str, key: str) -> tuple[Path, Path]:
    return Path(cache_dir) / f"{prefix}-{key}.npy", Path(cache_dir) / f"{prefix}-{key}.json"


def load_array(cache_dir, prefix: str, key: str, fmt: int, shape: tuple | None = None
               ) -> tuple[np.ndarray, dict] | None:
    """(array memory-mapped read-only, sidecar) when the entry is whole and is this key, format (and shape), else
    None (module docstring)."""
    data_path, meta_path = _paths(cache_dir, prefix, key)
    if file_kind(data_path) is not None or file_kind(meta_path) is not None:
        return None
    try:
        if meta_path.stat().st_size > MAX_SIDECAR_BYTES:
            return None
        meta = json.loads(meta_path.read_text())
        if (meta.get("key") != key or meta.get("format") != fmt
                or (shape is not None and tuple(meta.get("shape", ())) != tuple(shape))
                or meta.get("sha256") != file_sha256(data_path)):
            return None
        array = np.load(data_path, mmap_mode="r", allow_pickle=False)
        if array.shape != tuple(meta["shape"]) or array.dtype != np.float32 or not np.isfinite(array).all():
            return None
        os.utime(data_path)  # least recently used goes first when the cache is over its cap
        return array, meta
    except (OSError, ValueError, EOFError, json.JSONDecodeError, AttributeError, TypeError, KeyError):
        return None


def save_array(cache_dir, prefix: str, key: str, array: np.ndarray, fmt: int, what: str,
               extra: dict | None = None) -> list[str]:
    """Write the entry (data, then the sidecar with the data's SHA-256) after sweeping the folder; returns notes
    in words (``what`` names the array in them) instead of raising when it cannot be cached."""
    data_path, meta_path = _paths(cache_dir, prefix, key)
    if array.nbytes > MAX_CACHE_BYTES:
        return [f"the {what} ({array.nbytes / 1024**3:.1f} GiB) is larger than the cache cap "
                f"({MAX_CACHE_BYTES / 1024**3:.0f} GiB); it is not cached"]
    try:
        sweep_cache(cache_dir, room_bytes=array.nbytes + 4096)
        atomic_write(data_path, lambda tmp: np.save(tmp, array, allow_pickle=False))
        atomic_write_json(meta_path, {**(extra or {}), "key": key, "shape": list(array.shape), "format": fmt,
                                      "sha256": file_sha256(data_path)})
    except OSError as exc:
        return [f"could not write the {what} cache in {cache_dir} ({exc.strerror or exc}); it will be rebuilt "
                "next time"]
    return []


def sweep_cache(cache_dir, room_bytes: int = 0, now: float | None = None) -> list[Path]:
    """Delete what a killed run left (hidden temporary files older than STALE_TEMP_SECONDS) and the least
    recently used entries until the cached ones plus ``room_bytes`` fit MAX_CACHE_BYTES; returns what was
    deleted."""
    folder = Path(cache_dir)
    if not folder.is_dir():
        return []
    now = time.time() if now is None else now
    deleted = []
    for prefix in PREFIXES:
        for entry in folder.glob(f".{prefix}-*"):
            with contextlib.suppress(OSError):
                if now - entry.lstat().st_mtime > STALE_TEMP_SECONDS:
                    entry.unlink()
                    deleted.append(entry)
    entries = []
    for prefix in PREFIXES:
        for data in folder.glob(f"{prefix}-*.npy"):
            with contextlib.suppress(OSError):
                info = data.lstat()
                entries.append((info.st_mtime, info.st_size, data))
    total = sum(size for _, size, _ in entries) + room_bytes
    for _, size, data in sorted(entries):
        if total <= MAX_CACHE_BYTES:
            break
        for path in (data, data.with_suffix(".json")):
            with contextlib.suppress(OSError):
                path.unlink()
                deleted.append(path)
        total -= size
    return deleted


class ArrayCache:
    """The cache folder as an object, for code that must not know where it lives (``MuPyramid``)."""

    def __init__(self, cache_dir):
        self.cache_dir = cache_dir
        self.notes: list[str] = []

    def load(self, prefix: str, key: str, fmt: int, shape: tuple | None = None):
        return load_array(self.cache_dir, prefix, key, fmt, shape)

    def save(self, prefix: str, key: str, array: np.ndarray, fmt: int, what: str, extra: dict | None = None):
        self.notes += save_array(self.cache_dir, prefix, key, array, fmt, what, extra)

    def take_notes(self) -> list[str]:
        """The notes of the writes since the last call (each said once)."""
        notes, self.notes = self.notes, []
        return notes
