"""Checks every CT reader applies before and after reading: memory and physical extent bounded before any
array is allocated, HU kept as int16 when they fit, one 3D scalar grid, finite voxels (see ``volumes``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.volume import Volume

MAX_VOLUME_BYTES = 8 * 1024**3
"""Largest volume (bytes in memory) a reader accepts."""
MAX_CT_EXTENT_MM = 2100.0
"""Longest CT axis accepted (a whole-body scan is about 2 m)."""
MAX_CT_SECTION_MM2 = 1000.0 * 1000.0
"""Largest product of the two shorter axes (a CT field of view is at most about 700 mm)."""

def check_memory(shape, bytes_per_voxel: int, path: Path | str) -> None:
    """Refuse a volume whose array would need more than MAX_VOLUME_BYTES (or with a negative size)."""
    if any(int(n) < 0 for n in shape):
        raise InputFileError(f"{path}: the header gives a negative image size {list(shape)}; the file is "
                             "damaged")
    n_bytes = float(np.prod([float(n) for n in shape])) * int(bytes_per_voxel)
    if n_bytes > MAX_VOLUME_BYTES:
        raise InputFileError(f"{path}: the volume {'x'.join(str(int(n)) for n in shape)} needs "
                             f"{n_bytes / 1024**3:.1f} GiB, more than the "
                             f"{MAX_VOLUME_BYTES / 1024**3:.0f} GiB limit; crop it to the spine or resample "
                             "it to coarser voxels first")


def as_hu(data: np.ndarray) -> np.ndarray:
    """int16 when the values are integers that fit int16 (no copy for int16), else float32."""
    if data.dtype == np.int16:
        return data
    if np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.bool_):
        if data.size == 0 or (data.min() >= -32768 and data.max() <= 32767):
            return data.astype(np.int16)
        return data.astype(np.float32)
    if not np.issubdtype(data.dtype, np.floating):
        raise InputFileError(f"voxel type {data.dtype} is not a number type; give a scalar CT in HU")
    data = data.astype(np.float32, copy=False)
    return data


def checked_volume(data: np.ndarray, affine: np.ndarray, path: Path, meta: dict) -> Volume:
    """A Volume from reader output, refusing what would silently go wrong later: a flat or empty grid,
    NaN or infinite voxels (the DRR would be NaN), a singular or non-finite affine (``Volume`` checks)."""
    if min(data.shape) < 2:
        raise InputFileError(f"{path}: the volume is {'x'.join(str(n) for n in data.shape)} voxels; a CT "
                             "for registration needs at least 2 voxels along every axis (is it one slice?)")
    if np.issubdtype(data.dtype, np.floating):
        lo, hi = float(np.min(data)), float(np.max(data))
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise InputFileError(f"{path}: {int(np.count_nonzero(~np.isfinite(data)))} voxel(s) are NaN or "
                                 "infinite; fill them (e.g. with -1000 HU, air) before loading the CT")
    volume = Volume(data, affine, str(path), meta)
    check_extent(volume.shape, volume.spacing_mm, path)
    return volume


def check_extent(shape, spacing_mm, path: Path | str) -> None:
    """Refuse a CT whose physical box is beyond any patient (spacing in um or cm written as mm): every
    resampled level (``resample_isotropic``) is sized by this box, so it is checked before any is made."""
    extent_mm = np.asarray(shape, float) * np.asarray(spacing_mm, float)
    box = sorted(extent_mm)
    if box[-1] > MAX_CT_EXTENT_MM or box[0] * box[1] > MAX_CT_SECTION_MM2:
        spacing = ", ".join(f"{s:.4g}" for s in spacing_mm)
        raise InputFileError(f"{path}: the CT spans {' x '.join(f'{e:.0f}' for e in extent_mm)} mm "
                             f"({'x'.join(str(int(n)) for n in shape)} voxels of {spacing} mm), larger than a "
                             f"patient (at most {MAX_CT_EXTENT_MM:.0f} mm long, "
                             f"{MAX_CT_SECTION_MM2 ** 0.5:.0f} mm across): the voxel spacing in the header is "
                             "probably not in mm (um or cm?); fix it and save the CT again")


def spatial_3d(data: np.ndarray, path: Path) -> np.ndarray:
    """Drop trailing singleton axes (e.g. NIfTI t=1); refuse anything that is not one 3D scalar volume."""
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise InputFileError(f"{path}: expected one 3D scalar volume, the file holds an array of shape "
                             f"{data.shape}; give a single CT volume (not a time series or vector image)")
    return data
