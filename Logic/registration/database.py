"""Stage 1a: the preoperative DRR database over C-arm translations (method paper Algorithm 1).

DRRs of the coarse mu level (paper: 4 mm) on the coarse detector (the X-ray's detector binned to ~4 mm
pixels), at C-arm poses ``(tx = tx_mm, ty, tz, 0, 0, 0)`` for ty in ``ty_range_mm`` and tz in
``tz_range_mm`` (paper: -50..+50 mm in 2 mm steps = 2601 DRRs). Stored as ``drrs[iy, iz, row, col]`` float32
line integrals.

Cache: ``<cache_dir>/db-<key>.npy`` with its sidecar (``io.array_cache``: checksummed, capped, swept), where
the key is a SHA-256 of the mu level (bytes and affine), the geometry (intrinsics, isocentre, SOD), the grid, and
the format version: any change gives a new key. A database above ``MAX_DATABASE_BYTES`` is refused before it is
allocated.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import RegistrationError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.io.array_cache import load_array, save_array

FORMAT_VERSION = 3
MAX_DATABASE_BYTES = 1024**3
"""Largest database built (float32 DRRs in memory); the usual one is 40-300 MB."""


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
    notes: list = field(default_factory=list)  # for the user: e.g. the cache could not be written

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
    h.update(np.ascontiguousarray(level.mu_per_mm))  # the C-order bytes, without a second copy
    h.update(np.asarray(level.ijk_to_lps, np.float64).tobytes())
    h.update(str(level.mu_per_mm.shape).encode())
    return h.hexdigest()




def database_key(digest: str, geometry: CarmGeometry, intrinsics: CarmIntrinsics, ty_mm: np.ndarray,
                 tz_mm: np.ndarray, tx_mm: float) -> str:
    """Cache key: the volume digest, the geometry, the grid and the format version."""
    h = hashlib.sha256(digest.encode())
    desc = {"v": FORMAT_VERSION, "sdd": intrinsics.sdd_mm, "px": list(intrinsics.pixel_spacing_mm),
            "size": list(intrinsics.size_px), "pp": list(intrinsics.principal_point_px),
            "iso": [float(x) for x in geometry.isocenter_lps_mm], "sod": geometry.sod_mm,
            "ty": [float(x) for x in ty_mm], "tz": [float(x) for x in tz_mm], "tx": float(tx_mm)}
    if intrinsics.distortion_mm:  # keyed only when present: the pinhole's keys (and caches) stay as they were
        desc["distortion_mm"] = float(intrinsics.distortion_mm)
    h.update(json.dumps(desc, sort_keys=True).encode())
    return h.hexdigest()[:24]










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

    ``level`` may be a callable that makes the mu level: with ``digest`` (``MuPyramid.digest``) given, it is
    called only when the cache misses.
    """
    start = time.perf_counter()
    if digest is None:
        level = level() if callable(level) else level
        digest = level_digest(level)
    key = database_key(digest, geometry, intrinsics, ty_mm, tz_mm, tx_mm)
    cols, rows = intrinsics.size_px
    shape = (len(ty_mm), len(tz_mm), rows, cols)
    cached = load_array(cache_dir, "db", key, FORMAT_VERSION, shape) if cache_dir else None
    if cached is not None:
        return DrrDatabase(ty_mm, tz_mm, tx_mm, cached[0], intrinsics, key, time.perf_counter() - start, True)
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
        db.notes += save_array(cache_dir, "db", key, db.drrs, FORMAT_VERSION, "DRR database")
    db.seconds = time.perf_counter() - start
    return db
