"""The CT volume: voxels in Hounsfield units and their place in the LPS world.

``Volume.hu`` is indexed ``hu[i, j, k]`` (i fastest in the file, usually columns, then rows, then slices)
and ``ijk_to_lps`` is the 4x4 affine that maps a continuous voxel index (voxel *centres* at integer
indices) to LPS millimetres::

    lps_mm = ijk_to_lps @ [i, j, k, 1]

Its 3x3 block is direction x spacing (columns are the LPS direction of each index axis scaled by the
spacing); it may be oblique. Nothing here assumes axis-aligned volumes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.errors import InputFileError

MU_WATER_PER_MM = 0.02
"""Linear attenuation of water near 60-70 keV, 1/mm (method paper Eq. 3)."""


@dataclass
class Volume:
    """A CT volume in HU with its voxel-to-LPS affine.

    hu: (ni, nj, nk) float32 or int16 Hounsfield units.
    ijk_to_lps: (4, 4) float64 affine, voxel index -> LPS mm.
    source: where it was read from (path), for messages and provenance.
    """

    hu: np.ndarray
    ijk_to_lps: np.ndarray
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ijk_to_lps = np.asarray(self.ijk_to_lps, dtype=np.float64)
        if self.hu.ndim != 3:
            raise InputFileError(f"{self.source or 'volume'}: expected a 3D image, got {self.hu.ndim}D")
        if self.ijk_to_lps.shape != (4, 4) or not np.all(np.isfinite(self.ijk_to_lps)):
            raise InputFileError(f"{self.source or 'volume'}: voxel-to-world affine is not a finite 4x4")
        if abs(np.linalg.det(self.ijk_to_lps[:3, :3])) < 1e-9:
            raise InputFileError(f"{self.source or 'volume'}: voxel-to-world affine is singular "
                                 "(zero spacing or degenerate directions)")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.hu.shape)

    @property
    def spacing_mm(self) -> np.ndarray:
        """Voxel size along i, j, k in mm (norms of the affine's columns)."""
        return np.linalg.norm(self.ijk_to_lps[:3, :3], axis=0)

    @property
    def lps_to_ijk(self) -> np.ndarray:
        return np.linalg.inv(self.ijk_to_lps)

    def corners_lps_mm(self) -> np.ndarray:
        """(8, 3) LPS positions of the outer corners of the voxel grid (voxel edges, not centres)."""
        n = np.array(self.shape, dtype=float)
        lo, hi = -0.5 * np.ones(3), n - 0.5
        ijk = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
        return apply_affine(self.ijk_to_lps, ijk)

    def center_lps_mm(self) -> np.ndarray:
        """LPS position of the centre of the voxel grid."""
        return apply_affine(self.ijk_to_lps, (np.array(self.shape, float) - 1.0) / 2.0)

    def contains_lps(self, points_lps_mm: np.ndarray, margin_vox: float = 0.5) -> np.ndarray:
        """Boolean mask: which points lie inside the voxel grid (extended by ``margin_vox``)."""
        ijk = apply_affine(self.lps_to_ijk, np.atleast_2d(points_lps_mm))
        n = np.array(self.shape, float)
        return np.all((ijk >= -margin_vox) & (ijk <= n - 1 + margin_vox), axis=1)


def apply_affine(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``affine`` (4x4) applied to (..., 3) points: ``p @ A[:3, :3].T + A[:3, 3]`` (e.g. ``ijk_to_lps`` on voxel
    indices, ``lps_to_ijk`` on LPS mm)."""
    points = np.asarray(points, dtype=np.float64)
    return points @ affine[:3, :3].T + affine[:3, 3]


def hu_to_mu(hu: np.ndarray, mu_water_per_mm: float = MU_WATER_PER_MM) -> np.ndarray:
    """Linear attenuation (1/mm) from HU, method paper Eq. 3, clamped at 0 (air and below).

    mu = mu_water * (1000 + HU) / 1000
    """
    mu = np.array(hu, dtype=np.float32)  # one new float32 array, updated in place
    mu += np.float32(1000.0)
    mu *= np.float32(mu_water_per_mm / 1000.0)
    return np.maximum(mu, np.float32(0.0), out=mu)


def resample_isotropic(values: np.ndarray, ijk_to_lps: np.ndarray, spacing_mm: float,
                       smooth: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Resample a volume onto a grid of ``spacing_mm`` along the same index axes and extent.

    The new grid covers the same physical box (voxel edges) as the old one; its voxel centres are at
    ``new_ijk -> old_ijk = (new_ijk + 0.5) * s_new / s_old - 0.5`` along each axis. When coarsening, the
    input is first smoothed with a Gaussian of sigma = 0.4 * (s_new / s_old) voxels per axis (anti-alias),
    then sampled trilinearly. Returns (values float32, new ijk_to_lps).
    """
    from scipy import ndimage

    old_spacing = np.linalg.norm(ijk_to_lps[:3, :3], axis=0)
    ratio = spacing_mm / old_spacing
    n_old = np.array(values.shape)
    n_new = np.maximum(1, np.round(n_old / ratio).astype(int))
    ratio_exact = n_old / n_new  # keep the physical extent exactly
    src = values.astype(np.float32, copy=False)
    if smooth and np.any(ratio_exact > 1.0):
        sigma = np.where(ratio_exact > 1.0, 0.4 * ratio_exact, 0.0)
        src = ndimage.gaussian_filter(src, sigma=sigma, mode="nearest")
    coords = [(np.arange(n) + 0.5) * r - 0.5 for n, r in zip(n_new, ratio_exact, strict=True)]
    out = ndimage.map_coordinates(src, np.meshgrid(*coords, indexing="ij"), order=1, mode="nearest")
    new_affine = ijk_to_lps.copy()
    new_affine[:3, :3] = ijk_to_lps[:3, :3] * ratio_exact[None, :]
    new_affine[:3, 3] = apply_affine(ijk_to_lps, 0.5 * ratio_exact - 0.5)
    return out.astype(np.float32), new_affine


@dataclass
class MuLevel:
    """One level of the attenuation pyramid: mu (1/mm, float32) and its affine. Resampled levels are C-contiguous;
    the CT's own grid keeps the CT's memory order (the DRR engines copy a level into their own layout anyway; one
    more transposed copy of the whole CT took 0.3-0.5 s inside a run on this 2-core machine)."""

    mu_per_mm: np.ndarray
    ijk_to_lps: np.ndarray
    spacing_mm: float | None  # None = the CT's own grid


LEVEL_CACHE_FORMAT = 1


class MuPyramid:
    """HU -> mu once, then resampled levels on demand (cached): ``pyramid.level(4.0)``.

    ``level(None)`` is the CT's own grid. The paper uses 4 mm for the coarse database and 1 mm / 0.5 mm
    later; any spacing works.
    """

    def __init__(self, volume: Volume, mu_water_per_mm: float = MU_WATER_PER_MM, cache=None):
        self.volume = volume
        self.mu_water_per_mm = mu_water_per_mm
        self.cache = cache  # an ``io.array_cache.ArrayCache`` (resampled levels kept across runs) or None
        self._levels: dict[float | None, MuLevel] = {}
        self._ct_hash = None

    def digest(self, spacing_mm: float) -> str:
        """SHA-256 of the CT (HU voxels, affine) and of how its level of ``spacing_mm`` is made (spacing,
        mu_water): it identifies the level without computing it (cache keys)."""
        if self._ct_hash is None:
            h = hashlib.sha256()
            h.update(np.ascontiguousarray(self.volume.hu))  # the C-order bytes, without a second copy
            h.update(np.asarray(self.volume.ijk_to_lps, np.float64).tobytes())
            self._ct_hash = h
        h = self._ct_hash.copy()
        hu = self.volume.hu
        h.update(json.dumps([str(hu.dtype), list(hu.shape), float(spacing_mm), float(self.mu_water_per_mm)]).encode())
        return h.hexdigest()

    def level(self, spacing_mm: float | None = None) -> MuLevel:
        key = None if spacing_mm is None else round(float(spacing_mm), 4)
        if key not in self._levels:
            if key is None:
                mu = hu_to_mu(self.volume.hu, self.mu_water_per_mm)
                self._levels[None] = MuLevel(mu, self.volume.ijk_to_lps.copy(), None)
            else:
                name = self.digest(key)[:24] if self.cache else ""
                self._levels[key] = self._cached(name, key) or self._resampled(self.level(None), key, name)
        return self._levels[key]

    def _cached(self, name: str, spacing_mm: float) -> MuLevel | None:
        hit = self.cache.load("mu", name, LEVEL_CACHE_FORMAT) if self.cache else None
        if hit is None:
            return None
        mu, meta = hit
        return MuLevel(np.array(mu, dtype=np.float32, order="C"), np.asarray(meta["ijk_to_lps"], float), spacing_mm)

    def _resampled(self, full: MuLevel, spacing_mm: float, name: str) -> MuLevel:
        mu, affine = resample_isotropic(full.mu_per_mm, full.ijk_to_lps, spacing_mm)
        level = MuLevel(np.ascontiguousarray(mu), affine, spacing_mm)
        if self.cache:
            self.cache.save("mu", name, level.mu_per_mm, LEVEL_CACHE_FORMAT,
                            "attenuation level", {"ijk_to_lps": affine.tolist()})
        return level
