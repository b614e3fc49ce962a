"""Stage 1a: the preoperative DRR database over C-arm translations (method paper Algorithm 1).

DRRs of the coarse mu level (paper: 4 mm) on the coarse detector (the X-ray's detector binned to ~4 mm
pixels), at C-arm poses ``(tx = tx_mm, ty, tz, 0, 0, 0)`` for ty in ``ty_range_mm`` and tz in
``tz_range_mm`` (paper: -50..+50 mm in 2 mm steps = 2601 DRRs). Stored as ``drrs[iy, iz, row, col]`` float32
line integrals.

Cache: ``<cache_dir>/db-<key>.npy`` (the raw float32 array, memory-mapped on load so a cached database
costs no copy) beside ``db-<key>.json`` (key, shape, grid), where the key is a SHA-256 of the mu level
(bytes and affine), the geometry (intrinsics, isocentre, SOD), the grid, and the format version: any change
gives a new key. A cache that cannot be read, whose stored key or shape differs, or whose data no longer
match the SHA-256 recorded in the sidecar when it was written, is rebuilt, never trusted. Each write first
sweeps the folder: temporary files a killed run left (older than 15 min) go, and the least recently used
databases go until the folder fits ``MAX_CACHE_BYTES``. A database above ``MAX_DATABASE_BYTES`` is refused
before it is allocated.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import RegistrationError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.io.atomic import atomic_write, atomic_write_json, file_sha256
from carmreg.logic.io.limits import file_kind

FORMAT_VERSION = 3
MAX_DATABASE_BYTES = 1024**3
"""Largest database built (float32 DRRs in memory); the usual one is 40-300 MB."""
MAX_CACHE_BYTES = 4 * 1024**3
"""Cap of the cache folder's databases: the least recently used are deleted beyond it."""
STALE_TEMP_SECONDS = 15 * 60.0
"""A hidden temporary file older than this was left by a killed run (a write takes seconds)."""


@dataclass
class DrrDatabase:
    ty_mm: np.ndarray           # (ny,)
    tz_mm: np.ndarray           # (nz,)
    tx_mm: float
    drrs: np.ndarray            # (ny, nz, rows, cols) float32 line integrals
    intrinsics: CarmIntrinsics  # the coarse detector the DRRs are on
    key: str
    seconds: float = 0.0
    from_cache: bool = False

    def poses(self) -> np.ndarray:
        """(ny, nz, 6) pose vectors of the grid."""
        ty, tz = np.meshgrid(self.ty_mm, self.tz_mm, indexing="ij")
        out = np.zeros(ty.shape + (6,))
        out[..., 0], out[..., 1], out[..., 2] = self.tx_mm, ty, tz
        return out


def grid(half_range_mm: float, step_mm: float, center_mm: float = 0.0) -> np.ndarray:
    """Symmetric grid center +- half_range in steps (both ends included)."""
    n = int(round(half_range_mm / step_mm))
    return center_mm + step_mm * np.arange(-n, n + 1, dtype=np.float64)


def level_digest(level: MuLevel) -> str:
    """SHA-256 of a mu level's voxels and affine (what the DRRs are rendered from)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(level.mu_per_mm).tobytes())
    h.update(np.asarray(level.ijk_to_lps, np.float64).tobytes())
    h.update(str(level.mu_per_mm.shape).encode())
    return h.hexdigest()


def source_digest(hu: np.ndarray, ijk_to_lps: np.ndarray, spacing_mm: float, mu_water_per_mm: float) -> str:
    """SHA-256 of the CT (HU voxels, affine) and of how its coarse level is made (spacing, mu_water): it
    identifies the level without computing it, so a cached database costs no resampling."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(hu).tobytes())
    h.update(np.asarray(ijk_to_lps, np.float64).tobytes())
    h.update(json.dumps([str(hu.dtype), list(hu.shape), float(spacing_mm), float(mu_water_per_mm)]).encode())
    return h.hexdigest()


def database_key(digest: str, geometry: CarmGeometry, intrinsics: CarmIntrinsics, ty_mm: np.ndarray,
                 tz_mm: np.ndarray, tx_mm: float) -> str:
    """Cache key: the volume digest, the geometry, the grid and the format version."""
    h = hashlib.sha256(digest.encode())
    desc = {"v": FORMAT_VERSION, "sdd": intrinsics.sdd_mm, "px": list(intrinsics.pixel_spacing_mm),
            "size": list(intrinsics.size_px), "pp": list(intrinsics.principal_point_px),
            "iso": [float(x) for x in geometry.isocenter_lps_mm], "sod": geometry.sod_mm,
            "ty": [float(x) for x in ty_mm], "tz": [float(x) for x in tz_mm], "tx": float(tx_mm)}
    h.update(json.dumps(desc, sort_keys=True).encode())
    return h.hexdigest()[:24]


def _cache_paths(cache_dir, key: str) -> tuple[Path, Path]:
    return Path(cache_dir) / f"db-{key}.npy", Path(cache_dir) / f"db-{key}.json"


def _load_cached(cache_dir, key: str, shape: tuple) -> np.ndarray | None:
    """The cached DRR array (memory-mapped) if its sidecar names this key and shape and the data file's
    SHA-256 matches the one the sidecar recorded when it was written, else None (never a pipe or device)."""
    data_path, meta_path = _cache_paths(cache_dir, key)
    if file_kind(data_path) is not None or file_kind(meta_path) is not None:
        return None
    try:
        if meta_path.stat().st_size > 64 * 1024:
            return None
        meta = json.loads(meta_path.read_text())
        if (meta.get("key") != key or tuple(meta.get("shape", ())) != shape
                or meta.get("format") != FORMAT_VERSION or meta.get("sha256") != file_sha256(data_path)):
            return None
        drrs = np.load(data_path, mmap_mode="r", allow_pickle=False)
        if drrs.shape != shape or drrs.dtype != np.float32 or not np.isfinite(drrs).all():
            return None
        os.utime(data_path)  # least recently used goes first when the cache is over its cap
        return drrs
    except (OSError, ValueError, EOFError, json.JSONDecodeError, AttributeError, TypeError):
        return None


def _save_cached(cache_dir, key: str, drrs: np.ndarray) -> None:
    """Write the cache (data, then the sidecar with the data's SHA-256), keep the folder under its cap; a
    cache that cannot be written costs only the next run's time (warning)."""
    data_path, meta_path = _cache_paths(cache_dir, key)
    if drrs.nbytes > MAX_CACHE_BYTES:
        warnings.warn(f"the DRR database ({drrs.nbytes / 1024**3:.1f} GiB) is larger than the cache cap "
                      f"({MAX_CACHE_BYTES / 1024**3:.0f} GiB); it is not cached", stacklevel=3)
        return
    try:
        sweep_cache(cache_dir, room_bytes=drrs.nbytes + 4096)
        atomic_write(data_path, lambda tmp: np.save(tmp, drrs, allow_pickle=False))
        atomic_write_json(meta_path, {"key": key, "shape": list(drrs.shape), "format": FORMAT_VERSION,
                                      "sha256": file_sha256(data_path)})
    except OSError as exc:
        warnings.warn(f"could not write the DRR database cache in {cache_dir} ({exc.strerror or exc}); "
                      "it will be rebuilt next time", stacklevel=3)


def sweep_cache(cache_dir, room_bytes: int = 0, now: float | None = None) -> list[Path]:
    """Delete what a killed run left (hidden temporary files older than STALE_TEMP_SECONDS) and the least
    recently used databases until the cached ones plus ``room_bytes`` fit MAX_CACHE_BYTES; returns what
    was deleted."""
    folder = Path(cache_dir)
    if not folder.is_dir():
        return []
    now = time.time() if now is None else now
    deleted = []
    for entry in folder.glob(".db-*"):
        with contextlib.suppress(OSError):
            if now - entry.lstat().st_mtime > STALE_TEMP_SECONDS:
                entry.unlink()
                deleted.append(entry)
    databases = []
    for data in folder.glob("db-*.npy"):
        with contextlib.suppress(OSError):
            info = data.lstat()
            databases.append((info.st_mtime, info.st_size, data))
    total = sum(size for _, size, _ in databases) + room_bytes
    for _, size, data in sorted(databases):
        if total <= MAX_CACHE_BYTES:
            break
        for path in (data, data.with_suffix(".json")):
            with contextlib.suppress(OSError):
                path.unlink()
                deleted.append(path)
        total -= size
    return deleted


def check_database_size(n_drrs: int, size_px: tuple[int, int]) -> None:
    """Refuse, before allocating, a database larger than MAX_DATABASE_BYTES (float32 DRRs)."""
    cols, rows = size_px
    n_bytes = float(n_drrs) * cols * rows * 4
    if n_bytes > MAX_DATABASE_BYTES:
        raise RegistrationError(f"the DRR database would hold {n_drrs} DRRs of {cols}x{rows} px "
                                f"({n_bytes / 1024**3:.1f} GiB, limit {MAX_DATABASE_BYTES / 1024**3:.0f} GiB): "
                                "the labelled CT levels span too far or the detector is too large; label only "
                                "the vertebrae near the X-ray, and check the pixel spacing")


def build_database(level: MuLevel | Callable[[], MuLevel], geometry: CarmGeometry, intrinsics: CarmIntrinsics,
                   ty_mm: np.ndarray, tz_mm: np.ndarray, tx_mm: float = 0.0, cache_dir: str | Path | None = None,
                   progress=None, chunk: int = 256, digest: str | None = None) -> DrrDatabase:
    """Render (or load from cache) the database. ``progress(fraction)`` is called between chunks.

    ``level`` may be a callable that makes the mu level: with ``digest`` (``source_digest``) given, it is
    called only when the cache misses.
    """
    start = time.perf_counter()
    if digest is None:
        level = level() if callable(level) else level
        digest = level_digest(level)
    key = database_key(digest, geometry, intrinsics, ty_mm, tz_mm, tx_mm)
    cols, rows = intrinsics.size_px
    shape = (len(ty_mm), len(tz_mm), rows, cols)
    cached = _load_cached(cache_dir, key, shape) if cache_dir else None
    if cached is not None:
        return DrrDatabase(ty_mm, tz_mm, tx_mm, cached, intrinsics, key, time.perf_counter() - start, True)
    level = level() if callable(level) else level
    check_database_size(len(ty_mm) * len(tz_mm), intrinsics.size_px)
    db = DrrDatabase(ty_mm, tz_mm, tx_mm, np.empty(0), intrinsics, key)
    poses = db.poses().reshape(-1, 6)
    flat = np.empty((len(poses), rows, cols), np.float32)
    for i in range(0, len(poses), chunk):
        flat[i:i + chunk] = render_line_integrals(level, geometry, poses[i:i + chunk], intrinsics)
        if progress:
            progress(min(1.0, (i + chunk) / len(poses)))
    db.drrs = flat.reshape(shape)
    if cache_dir:
        _save_cached(cache_dir, key, db.drrs)
    db.seconds = time.perf_counter() - start
    return db
