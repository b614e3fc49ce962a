"""Reading a CT from DICOM: a series folder (or one of its files) or one enhanced multi-frame CT file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, describe
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.dicom_common import (
    dicom_int,
    dicom_numbers,
    dicom_parse_errors,
    drop_unreadable_elements,
    has_dicom_marker,
)
from carmreg.logic.io.limits import check_dicom_size, file_kind
from carmreg.logic.io.volume_checks import check_memory, checked_volume

# A CT series: every file under the folder (recursively; hidden files and DICOMDIR skipped) that reads as
# DICOM. Objects without an image plane (reports, dose summaries) and localizers (ImageType LOCALIZER) are
# left out. The remaining images must form one series (SeriesInstanceUID), of modality CT.
#
# Geometry of a slice: row direction r = IOP[0:3] (increasing column index i), column direction
# c = IOP[3:6] (increasing row index j), normal n = r x c, PixelSpacing = [row spacing dr, column spacing dc].
# Slices are sorted by d = IPP . n; the voxel (i, j, k) is at IPP_0 + i dc r + j dr c + k s with the slice
# step s = (IPP_last - IPP_0) / (n - 1) (a gantry tilt stays as a shear). Every IPP must lie on that line
# and the gaps must be equal, otherwise a slice is missing and the series is refused. HU = stored value x
# RescaleSlope + RescaleIntercept, per slice.

SECONDARY_CAPTURE_PREFIX = "1.2.840.10008.5.1.4.1.1.7"
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


def load_dicom_series(folder: str | Path, *, series_uid: str | None = None) -> Volume:
    """Read one CT series from a folder (see the DICOM notes above)."""
    folder = Path(folder)
    headers, skipped = _dicom_headers(folder)
    series = _choose_series(headers, folder, series_uid)
    _check_ct(series, folder)
    ordered, affine, spacing_note = _slice_geometry(series, folder)
    first = ordered[0][1]
    check_memory((*_columns_rows(first, ordered[0][0]), len(ordered)), 2 + 4, folder)
    hu = _read_slices(ordered, lambda path: _slice_pixels(path))
    meta = {"format": "DICOM", "series_uid": str(first.get("SeriesInstanceUID", "")),
            "series_description": str(first.get("SeriesDescription", "")), "n_slices": len(ordered),
            "skipped_files": skipped, "slice_spacing": spacing_note}
    return checked_volume(hu, affine, folder, meta)


def load_dicom_file(path: str | Path, *, series_uid: str | None = None) -> Volume:
    """One DICOM file: read the series it belongs to from its folder."""
    import pydicom

    path = Path(path)
    ds = _read_header(path, pydicom)
    if ds is None:
        raise InputFileError(f"{path}: not a readable DICOM file")
    if dicom_int(ds, "NumberOfFrames", 1, path) > 1:
        return load_enhanced_ct(path)
    if "ImagePositionPatient" not in ds or _is_localizer(ds):  # its folder's slices would be searched in vain
        modality = str(ds.get("Modality", "") or "").strip()
        raise InputFileError(f"{path}: a DICOM {modality + ' ' if modality else ''}image without a slice position "
                             "(a projection X-ray or a localizer, not a CT slice); give the CT's series folder or a "
                             "NIfTI/NRRD/MetaImage volume (the X-ray goes to --xray)")
    return load_dicom_series(path.parent, series_uid=series_uid or str(ds.get("SeriesInstanceUID", "")))


def _read_header(path: Path, pydicom):
    """Header without pixels (every element decoded), or None when the file is not DICOM.

    A file that says it is DICOM (the 'DICM' marker) but cannot be parsed raises InputFileError rather than
    being skipped, so a damaged slice is named instead of silently dropped from the series.
    """
    from pydicom.errors import InvalidDicomError

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except InvalidDicomError:
        ds = None
    except dicom_parse_errors() as exc:
        if has_dicom_marker(path):
            raise InputFileError(f"{path}: damaged DICOM file ({describe(exc, 80)}); "
                                 "copy it again or remove it from the folder") from None
        return None
    if ds is None:
        ds = _read_header_without_preamble(path, pydicom)
        if ds is None:
            return None
    _drop_unneeded_damage(ds, path)
    return ds


SLICE_KEYWORDS = {"ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "Rows", "Columns",
                  "RescaleSlope", "RescaleIntercept", "SeriesInstanceUID", "Modality", "SOPClassUID",
                  "ImageType", "NumberOfFrames", "PerFrameFunctionalGroupsSequence",
                  "SharedFunctionalGroupsSequence", "BitsAllocated", "BitsStored", "PixelRepresentation",
                  "SamplesPerPixel"}
"""Header elements the CT reader uses: one of them unreadable makes the slice unusable."""


def _drop_unneeded_damage(ds, path: Path) -> None:
    """Drop elements pydicom cannot decode (e.g. a broken vendor private tag); refuse the slice when one of
    them is needed to place or scale it, so a damaged slice is named instead of misread or skipped."""
    needed = [name for name in drop_unreadable_elements(ds) if name.split(" ")[-1] in SLICE_KEYWORDS]
    if needed:
        raise InputFileError(f"{path}: the DICOM header is damaged: {', '.join(needed)} cannot be read; copy "
                             "or export the series again")


def _read_header_without_preamble(path: Path, pydicom):
    """A DICOM file without the 128-byte preamble (only tried for DICOM-like suffixes), or None."""
    if path.suffix.lower() not in ("", ".dcm", ".dicom", ".ima"):
        return None
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True, force=True)
        return ds if "SOPClassUID" in ds else None
    except Exception:  # noqa: BLE001 - forced parsing of a non-DICOM file fails in many ways
        return None


def _dicom_headers(folder: Path) -> tuple[list, int]:
    """[(path, header)] of the image slices under ``folder``; and how many files were left out."""
    import pydicom

    headers, skipped = [], 0
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith(".") or name.upper() == "DICOMDIR":
                continue
            path = Path(root) / name
            if file_kind(path) is not None:  # a pipe, a device, a broken or looping symlink: never opened
                skipped += 1
                continue
            ds = _read_header(path, pydicom)
            if ds is None or "ImagePositionPatient" not in ds or _is_localizer(ds):
                skipped += 1
                continue
            headers.append((path, ds))
    if not headers:
        raise InputFileError(f"{folder}: no DICOM image slices found in this folder; give the folder of a CT "
                             "series, or a NIfTI/NRRD/MetaImage file")
    return headers, skipped


def _is_localizer(ds) -> bool:
    image_type = [str(t).upper() for t in (ds.get("ImageType") or [])]
    return "LOCALIZER" in image_type


def _choose_series(headers: list, folder: Path, series_uid: str | None) -> list:
    groups: dict[str, list] = {}
    for path, ds in headers:
        groups.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((path, ds))
    if series_uid:
        if series_uid not in groups:
            raise InputFileError(f"{folder}: no series with SeriesInstanceUID {series_uid}; it holds "
                                 f"{_describe_series(groups)}")
        return groups[series_uid]
    if len(groups) > 1:
        raise InputFileError(f"{folder}: holds {len(groups)} image series ({_describe_series(groups)}); put "
                             "the CT series alone in a folder or choose it with --series-uid")
    return next(iter(groups.values()))


def _describe_series(groups: dict) -> str:
    parts = []
    for uid, items in groups.items():
        ds = items[0][1]
        parts.append(f"{uid or '(no UID)'}: {ds.get('Modality', '?')} '{ds.get('SeriesDescription', '')}', "
                     f"{len(items)} images")
    return "; ".join(parts)


def _check_ct(series: list, folder: Path) -> None:
    ds = series[0][1]
    modality = str(ds.get("Modality", "")).upper()
    sop_class = str(ds.get("SOPClassUID", ""))
    what = f"{folder}: series '{ds.get('SeriesDescription', '')}'"
    if sop_class.startswith(SECONDARY_CAPTURE_PREFIX):
        raise InputFileError(f"{what} is a secondary capture (screenshots), not a CT reconstruction; give "
                             "the original CT series")
    if modality != "CT":
        raise InputFileError(f"{what} has modality {modality or 'unknown'}, not CT; CarmReg needs a CT in "
                             "Hounsfield units (give the CT series of the patient)")


def _required(ds, keyword: str, path: Path, count: int):
    try:
        value = dicom_numbers(ds.get(keyword), count, keyword, path)
    except InputFileError:
        value = None
    if value is None:
        raise InputFileError(f"{path}: DICOM slice lacks a valid {keyword}; the series cannot be placed in "
                             "space (export it again from the scanner or PACS)")
    return value


def _columns_rows(ds, path: Path) -> tuple[int, int]:
    cols, rows = dicom_int(ds, "Columns", 0, path), dicom_int(ds, "Rows", 0, path)
    if cols < 1 or rows < 1:
        raise InputFileError(f"{path}: DICOM slice has no valid Rows/Columns ({rows} x {cols}); the file is "
                             "damaged")
    return cols, rows


def _slice_geometry(series: list, folder: Path) -> tuple[list, np.ndarray, str]:
    """Sort slices along the normal; check orientation, size and even spacing; build ijk_to_lps."""
    if len(series) < 2:
        raise InputFileError(f"{folder}: the CT series has only {len(series)} slice; give the whole series")
    first_path, first = series[0]
    iop = _required(first, "ImageOrientationPatient", first_path, 6)
    spacing_rc = _required(first, "PixelSpacing", first_path, 2)
    row_dir, col_dir = iop[:3], iop[3:]
    if (abs(np.linalg.norm(row_dir) - 1) > 1e-2 or abs(np.linalg.norm(col_dir) - 1) > 1e-2
            or abs(row_dir @ col_dir) > 1e-2):
        raise InputFileError(f"{first_path}: ImageOrientationPatient {iop.tolist()} is not two orthogonal "
                             "unit vectors; the slice cannot be placed in space (export the series again)")
    if np.any(spacing_rc <= 0):
        raise InputFileError(f"{first_path}: PixelSpacing {spacing_rc.tolist()} mm is not positive; the "
                             "header is damaged")
    normal = np.cross(row_dir, col_dir)
    for path, ds in series:
        _check_same_plane(ds, path, iop, spacing_rc, first)
    positions = np.array([_required(ds, "ImagePositionPatient", path, 3) for path, ds in series])
    depth = positions @ normal
    order = np.argsort(depth, kind="stable")
    ordered, positions, depth = [series[i] for i in order], positions[order], depth[order]
    step, note = _even_step(positions, depth, folder)
    affine = np.eye(4)
    affine[:3, 0] = row_dir * spacing_rc[1]
    affine[:3, 1] = col_dir * spacing_rc[0]
    affine[:3, 2] = step
    affine[:3, 3] = positions[0]
    return ordered, affine, note


def _check_same_plane(ds, path: Path, iop: np.ndarray, spacing_rc: np.ndarray, first) -> None:
    if np.max(np.abs(_required(ds, "ImageOrientationPatient", path, 6) - iop)) > 1e-3:
        raise InputFileError(f"{path}: slice orientation differs from the rest of the series; the folder "
                             "mixes reconstructions, give one series")
    if np.max(np.abs(_required(ds, "PixelSpacing", path, 2) - spacing_rc)) > 1e-4:
        raise InputFileError(f"{path}: pixel spacing differs from the rest of the series; give one series")
    if _columns_rows(ds, path) != _columns_rows(first, path):
        raise InputFileError(f"{path}: slice size differs from the rest of the series; give one series")


def _even_step(positions: np.ndarray, depth: np.ndarray, folder: Path) -> tuple[np.ndarray, str]:
    """The slice step vector; refuse duplicated positions, missing slices and uneven spacing."""
    gaps = np.diff(depth)
    if np.any(gaps < 1e-3):
        k = int(np.argmin(gaps))
        raise InputFileError(f"{folder}: two slices lie at the same position ({depth[k]:.3f} mm along the "
                             "slice normal); the folder holds several acquisitions of one series, export a "
                             "single reconstruction")
    spacing = float(np.median(gaps))
    tolerance = max(0.01, 0.05 * spacing)
    bad = np.flatnonzero(np.abs(gaps - spacing) > tolerance)
    if bad.size:
        k = int(bad[0])
        raise InputFileError(f"{folder}: slice spacing is uneven: {gaps[k]:.3f} mm between the slices at "
                             f"{depth[k]:.3f} and {depth[k + 1]:.3f} mm where the series spacing is "
                             f"{spacing:.3f} mm; a slice is probably missing (copy the whole series) or the "
                             "series mixes spacings (resample it to even spacing)")
    step = (positions[-1] - positions[0]) / (len(positions) - 1)
    residual = positions - (positions[0] + np.arange(len(positions))[:, None] * step)
    if np.max(np.linalg.norm(residual, axis=1)) > tolerance:
        raise InputFileError(f"{folder}: slice positions do not lie on one line; the series cannot be "
                             "stacked into a volume")
    return step, f"{spacing:.4f} mm from ImagePositionPatient"


def _read_slices(ordered: list, stored_pixels) -> np.ndarray:
    """Stack the slices as hu[i = column, j = row, k = slice], applying RescaleSlope/Intercept.

    ordered: [(key, header)] in slice order; stored_pixels(key) -> (rows, columns) stored values.
    """
    first = ordered[0][1]
    rescale = [_rescale(ds, key) for key, ds in ordered]
    integer = all(s == 1.0 and b == round(b) for s, b in rescale)
    cols, rows = _columns_rows(first, ordered[0][0])
    hu = np.empty((cols, rows, len(ordered)), np.int16 if integer else np.float32, order="F")
    for k, ((key, ds), (slope, intercept)) in enumerate(zip(ordered, rescale, strict=True)):
        if isinstance(key, Path):
            samples = dicom_int(ds, "SamplesPerPixel", 1, key)
            check_dicom_size(key, rows, cols, 1, samples * max(1, dicom_int(ds, "BitsAllocated", 16, key) // 8))
        stored = stored_pixels(key)
        if stored.shape != (rows, cols):
            raise InputFileError(f"{key}: pixel data of shape {stored.shape} does not match Rows x Columns "
                                 f"{rows} x {cols}; the slice is damaged")
        if integer:
            values = stored.astype(np.int32) + int(intercept)
            if values.min() < -32768 or values.max() > 32767:
                hu = hu.astype(np.float32)
                integer = False
            hu[:, :, k] = values.T
        else:
            hu[:, :, k] = (stored.astype(np.float32) * np.float32(slope) + np.float32(intercept)).T
    return hu


def _rescale(ds, key) -> tuple[float, float]:
    """(RescaleSlope, RescaleIntercept), default (1, 0) when absent; a zero slope is refused."""
    slope = dicom_numbers(ds.get("RescaleSlope"), 1, "RescaleSlope", Path(str(key)))
    intercept = dicom_numbers(ds.get("RescaleIntercept"), 1, "RescaleIntercept", Path(str(key)))
    if slope is not None and slope[0] == 0:
        raise InputFileError(f"{key}: RescaleSlope is 0, so every voxel would have the same HU; the header "
                             "is damaged (export the series again)")
    return 1.0 if slope is None else float(slope[0]), 0.0 if intercept is None else float(intercept[0])


def _slice_pixels(path: Path) -> np.ndarray:
    import pydicom

    try:
        ds = pydicom.dcmread(path)
        pixels = ds.pixel_array
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds for bad or undecodable data
        raise InputFileError(f"{path}: cannot decode this slice's pixel data ({describe(exc, 100)}); the "
                             "file may be truncated or compressed in a format without a decoder (decompress "
                             "it, e.g. gdcmconv --raw)") from None
    if pixels.ndim != 2:
        raise InputFileError(f"{path}: slice pixel data has shape {pixels.shape}; expected one grey image")
    return pixels


def load_enhanced_ct(path: str | Path) -> Volume:
    """A single-file multi-frame (enhanced) CT: per-frame ImagePositionPatient, shared or per-frame
    orientation, pixel spacing and rescale from the functional groups; then as a series."""
    import pydicom

    path = Path(path)
    header = _read_header(path, pydicom)
    if header is None:
        raise InputFileError(f"{path}: not a readable DICOM file")
    _check_ct([(path, header)], path)
    frames = _frame_headers(header, path)
    ordered, affine, spacing_note = _slice_geometry(frames, path)
    check_memory((*_columns_rows(header, path), len(ordered)), 2 + 4, path)
    stack = _decoded_frames(path, len(frames))
    hu = _read_slices(ordered, lambda frame: stack[frame])
    meta = {"format": "DICOM enhanced", "series_uid": str(header.get("SeriesInstanceUID", "")),
            "series_description": str(header.get("SeriesDescription", "")), "n_slices": len(ordered),
            "slice_spacing": spacing_note}
    return checked_volume(hu, affine, path, meta)


_FRAME_FIELDS = (("ImagePositionPatient", "PlanePositionSequence"),
                 ("ImageOrientationPatient", "PlaneOrientationSequence"),
                 ("PixelSpacing", "PixelMeasuresSequence"),
                 ("RescaleSlope", "PixelValueTransformationSequence"),
                 ("RescaleIntercept", "PixelValueTransformationSequence"))


def _frame_headers(ds, path: Path) -> list:
    """[(frame index, pseudo-header with the classic per-slice tags)] from the functional groups."""
    from pydicom.dataset import Dataset

    per_frame = ds.get("PerFrameFunctionalGroupsSequence") or []
    shared = (ds.get("SharedFunctionalGroupsSequence") or [Dataset()])[0]
    if len(per_frame) != dicom_int(ds, "NumberOfFrames", 1, path):
        raise InputFileError(f"{path}: multi-frame DICOM without one functional group per frame; export the "
                             "CT as a classic series or convert it to NIfTI (e.g. with dcm2niix)")
    frames = []
    for index, group in enumerate(per_frame):
        header = Dataset()
        header.Rows, header.Columns = ds.Rows, ds.Columns
        for keyword, sequence in _FRAME_FIELDS:
            for source in (group, shared, ds):
                item = source.get(sequence)
                holder = item[0] if item else (source if source is ds else None)
                if holder is not None and keyword in holder:
                    setattr(header, keyword, holder[keyword].value)
                    break
        frames.append((index, header))
    return frames


def _decoded_frames(path: Path, n_frames: int) -> np.ndarray:
    import pydicom

    try:
        stack = pydicom.dcmread(path).pixel_array
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds for bad or undecodable data
        raise InputFileError(f"{path}: cannot decode the pixel data ({describe(exc, 100)}); the file may be "
                             "truncated or compressed without a decoder") from None
    if stack.ndim != 3 or stack.shape[0] != n_frames:
        raise InputFileError(f"{path}: pixel data of shape {stack.shape} does not hold {n_frames} grey "
                             "frames")
    return stack
