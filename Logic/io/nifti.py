"""NIfTI ``.nii`` / ``.nii.gz`` CT (nibabel): world RAS; the sform when its code is set, else the qform, else
nibabel's fallback (flagged in ``meta``); ``ijk_to_lps = diag(-1, -1, 1, 1) @ ijk_to_ras``; scl_slope/scl_inter
applied.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, describe
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.transforms import LPS_FROM_RAS
from carmreg.logic.io.volume_checks import as_hu, check_memory, checked_volume, spatial_3d


def load_nifti(path: Path) -> Volume:
    import nibabel as nib

    try:
        image = nib.load(str(path))
        shape = image.shape
        itemsize = np.dtype(image.get_data_dtype()).itemsize
    except _nifti_errors() as exc:
        raise InputFileError(f"{path}: not a readable NIfTI file ({describe(exc, 100)})") from None
    check_memory(shape, 4 + itemsize, path)
    _check_payload(image, shape, itemsize, path)
    try:
        affine_ras, which = _nifti_affine(image)
    except _nifti_errors() as exc:
        raise InputFileError(f"{path}: the NIfTI orientation (sform/qform) cannot be read "
                             f"({describe(exc, 80)}); the header is damaged") from None
    try:
        data = _nifti_data(image, path)
    except _nifti_errors() as exc:
        raise InputFileError(f"{path}: the NIfTI voxel data cannot be read; the file is probably truncated "
                             f"({describe(exc, 80)}); copy it again") from None
    data = as_hu(spatial_3d(np.asarray(data), path))
    meta = {"format": "NIfTI", "affine_from": which}
    if which == "fallback":
        meta["warning_orientation"] = ("NIfTI header has neither sform nor qform; orientation assumed, "
                                       "check left/right in the views")
    return checked_volume(data, LPS_FROM_RAS @ affine_ras, path, meta)


def _check_payload(image, shape, itemsize: int, path: Path) -> None:
    """A file too short for the voxels its header announces is refused before any array is allocated (nibabel
    allocates them first): an uncompressed ``.nii`` by its size, a ``.nii.gz`` by inflating it in chunks, counted
    and dropped, up to the size needed (memory bounded by one chunk)."""
    offset = int(getattr(image.dataobj, "offset", 0) or 0)
    needed = offset + int(np.prod([int(n) for n in shape], dtype=np.int64)) * itemsize
    gz = path.name.lower().endswith(".gz")
    size = _inflated_size(path, needed) if gz else path.stat().st_size
    if size < needed:
        raise InputFileError(f"{path}: {'inflates to' if gz else 'holds'} {size} bytes but its header needs "
                             f"{needed} (voxel data from byte {offset}); the file is truncated, copy it again")


def _inflated_size(path: Path, limit: int, chunk: int = 1 << 22) -> int:
    """Bytes a gzip file inflates to, counted up to ``limit`` (corrupt data: the count so far)."""
    import gzip

    total = 0
    try:
        with gzip.open(path, "rb") as stream:
            while total < limit:
                data = stream.read(min(chunk, limit - total))
                if not data:
                    break
                total += len(data)
    except (OSError, EOFError, zlib.error):
        pass
    return total


def _nifti_errors() -> tuple:
    """What nibabel raises on a damaged or truncated file."""
    from nibabel.filebasedimages import ImageFileError
    from nibabel.spatialimages import HeaderDataError

    return (ImageFileError, HeaderDataError, OSError, EOFError, ValueError, TypeError, OverflowError,
            zlib.error, np.linalg.LinAlgError)


def _nifti_data(image, path: Path) -> np.ndarray:
    """Scaled voxel values; integer stored values with integer slope/intercept stay integers (no float64)
    as long as the scaled values fit int32."""
    proxy = image.dataobj
    slope, inter = float(getattr(proxy, "slope", 1.0)), float(getattr(proxy, "inter", 0.0))
    if not (np.isfinite(slope) and np.isfinite(inter)):
        raise InputFileError(f"{path}: NIfTI scaling scl_slope = {slope}, scl_inter = {inter} is not finite; "
                             "the header is damaged")
    if (np.issubdtype(image.get_data_dtype(), np.integer) and hasattr(proxy, "get_unscaled")
            and slope == round(slope) and inter == round(inter)):
        stored = np.asarray(proxy.get_unscaled())
        if slope == 1.0 and inter == 0.0:
            return stored
        extreme = max(abs(int(stored.min())), abs(int(stored.max()))) if stored.size else 0
        if abs(slope) * extreme + abs(inter) < 2**31:
            return stored.astype(np.int32) * np.int32(slope) + np.int32(inter)
    return np.asarray(np.asanyarray(proxy), dtype=np.float32)


def _nifti_affine(image) -> tuple[np.ndarray, str]:
    """ijk -> RAS affine: sform if coded, else qform if coded, else nibabel's fallback."""
    sform, s_code = image.get_sform(coded=True)
    if sform is not None and int(s_code) > 0:
        return np.asarray(sform, float), "sform"
    qform, q_code = image.get_qform(coded=True)
    if qform is not None and int(q_code) > 0:
        return np.asarray(qform, float), "qform"
    return np.asarray(image.affine, float), "fallback"
