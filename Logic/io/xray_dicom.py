"""Reading an X-ray DICOM (XA, RF, DX, CR; single or multi-frame): pixels after the MONOCHROME1 inversion and
the modality LUT, the header's geometry with its source, the header's polarity (see ``xray`` for the tags).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, describe
from carmreg.logic.io.dicom_common import (
    dicom_int,
    dicom_numbers,
    dicom_parse_errors,
    drop_unreadable_elements,
)
from carmreg.logic.io.limits import check_dicom_size
from carmreg.logic.io.xray_image import (
    DEFAULT_BONE_DARK,
    EXPLICIT_POLARITY_SOURCE,
    LINEAR_INTENSITY_SOURCE,
    PRIVATE_CREATOR,
    PRIVATE_GROUP,
    PRIVATE_PRINCIPAL_POINT,
    SOP_CLASS_UIDS,
    XrayParts,
    check_frame_size,
    grey_from_channels,
    select_frame,
)


def read_dicom(path: Path, frame: int | None) -> XrayParts:
    ds = _dcmread(path)
    dropped = drop_unreadable_elements(ds)
    if "SOPClassUID" not in ds and "PixelData" not in ds:
        raise InputFileError(f"{path}: not a DICOM file (nor PNG/TIFF/JPEG); give the X-ray image")
    modality = str(ds.get("Modality", "") or "").upper()
    if modality and modality not in SOP_CLASS_UIDS and modality not in ("OT", "XC", "RG", "PX", "IO", "MG"):
        raise InputFileError(f"{path}: DICOM modality {modality!r} is not an X-ray image; give an XA, RF, DX "
                             "or CR projection image")
    stack = _dicom_frames(ds, path)
    pixels, frame = select_frame(stack, frame, path)
    meta = {"format": "DICOM", "modality": modality, "frame": frame, "n_frames": int(stack.shape[0]),
            "photometric": str(ds.get("PhotometricInterpretation", ""))}
    if pixels.ndim == 3:
        pixels = grey_from_channels(pixels, path, meta)
    pixels = pixels.astype(np.float32)
    monochrome1 = meta["photometric"].upper() == "MONOCHROME1"
    inverted = monochrome1 and not _stores_linear_intensity(ds)
    if monochrome1 and not inverted:  # the intensities as stored: -log of them is the attenuation (``xray``)
        meta["note_linear_intensity"] = ("MONOCHROME1 with a linear intensity relationship (LIN, sign +1): the "
                                         "stored intensities kept, not inverted, so the image is shown bone dark")
    if inverted:
        pixels = _invert_monochrome1(pixels, ds, path)
        meta["note_inverted"] = "MONOCHROME1: stored values inverted so that larger = brighter"
    pixels = _modality_lut(pixels, ds, frame, path, meta)
    if dropped:
        meta["warning_unreadable_elements"] = ", ".join(dropped[:6]) + (" ..." if len(dropped) > 6 else "")
    part = XrayParts(pixels, True, meta=meta)
    part.bone_dark, part.sources["bone_dark"] = _dicom_bone_dark(ds, modality, inverted)
    if _stores_linear_intensity(ds):
        part.sources["storage"] = LINEAR_INTENSITY_SOURCE
    _dicom_geometry(ds, part, frame, path)
    return part


def _modality_lut(pixels: np.ndarray, ds, frame: int, path: Path, meta: dict) -> np.ndarray:
    """Apply the DICOM modality LUT ``value = RescaleSlope * stored + RescaleIntercept`` (top level or this
    frame's functional group), so the image is in the modality's units, as every DICOM viewer shows it.
    Linear with a positive slope, it commutes with the MONOCHROME1 inversion applied before."""
    slope = dicom_numbers(_find(ds, "RescaleSlope", frame), 1, "RescaleSlope", path)
    intercept = dicom_numbers(_find(ds, "RescaleIntercept", frame), 1, "RescaleIntercept", path)
    slope = 1.0 if slope is None else float(slope[0])
    intercept = 0.0 if intercept is None else float(intercept[0])
    if not (np.isfinite(slope) and np.isfinite(intercept) and slope != 0):
        raise InputFileError(f"{path}: DICOM RescaleSlope {slope:g} / RescaleIntercept {intercept:g} cannot map "
                             "the stored values; the header is damaged, export the X-ray again")
    if slope == 1.0 and intercept == 0.0:
        return pixels
    meta["modality_lut"] = {"slope": slope, "intercept": intercept}
    return (pixels * np.float32(slope) + np.float32(intercept)).astype(np.float32)


def _dcmread(path: Path):
    import pydicom

    try:
        head = pydicom.dcmread(path, force=True, stop_before_pixels=True)
        if "Rows" in head and "Columns" in head:  # before pydicom reads the whole file into memory
            frames = dicom_int(head, "NumberOfFrames", 1, path)
            per_pixel = dicom_int(head, "SamplesPerPixel", 1, path) * max(1, dicom_int(head, "BitsAllocated", 16,
                                                                                      path) // 8)
            check_dicom_size(path, dicom_int(head, "Rows", 0, path), dicom_int(head, "Columns", 0, path), frames,
                             per_pixel)
        ds = pydicom.dcmread(path, force=True)
    except dicom_parse_errors() as exc:
        raise InputFileError(f"{path}: not a readable DICOM file ({describe(exc, 100)})") from None
    return ds



def _dicom_frames(ds, path: Path) -> np.ndarray:
    """Decoded pixel data as (frames, rows, cols[, samples])."""
    if "PixelData" not in ds:
        raise InputFileError(f"{path}: DICOM file has no image (no PixelData); give an image file, not a "
                             "report or DICOMDIR")
    n_frames = dicom_int(ds, "NumberOfFrames", 1, path)
    samples = dicom_int(ds, "SamplesPerPixel", 1, path)
    check_frame_size(dicom_int(ds, "Columns", 0, path), dicom_int(ds, "Rows", 0, path), path,
                n_frames=max(n_frames, 1), bytes_per_pixel=max(samples, 1) * max(1, dicom_int(
                    ds, "BitsAllocated", 16, path) // 8))
    try:
        pixels = ds.pixel_array
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds for bad or undecodable data
        syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        name = getattr(syntax, "name", str(syntax))
        raise InputFileError(f"{path}: cannot decode the DICOM pixel data (transfer syntax {name}; "
                             f"{describe(exc, 120)}). If the file is truncated, copy "
                             "it again; if compressed, decompress it (e.g. gdcmconv --raw) or install "
                             "pylibjpeg") from None
    if n_frames <= 1:
        pixels = pixels[None]
    expected = 3 + (samples > 1)
    if pixels.ndim != expected:
        raise InputFileError(f"{path}: unexpected pixel array shape {pixels.shape} for {n_frames} frame(s) "
                             f"of {samples} sample(s)")
    return pixels


def _stores_linear_intensity(ds) -> bool:
    """Whether the stored values are the X-ray intensity itself: PixelIntensityRelationship (0028,1040) LIN with
    PixelIntensityRelationshipSign (0028,1041) +1 (values rise with the X-ray reaching the detector)."""
    relationship = str(ds.get("PixelIntensityRelationship", "")).strip().upper()
    return relationship == "LIN" and ds.get("PixelIntensityRelationshipSign") == 1


def _invert_monochrome1(pixels: np.ndarray, ds, path: Path) -> np.ndarray:
    """Map the stored range onto itself reversed: unsigned v -> (2^bits - 1) - v, signed v -> -1 - v."""
    bits = dicom_int(ds, "BitsStored", 16, path)
    if ds.get("PixelRepresentation", 0) == 1:
        return np.float32(-1.0) - pixels
    return np.float32(2**bits - 1) - pixels


def _dicom_bone_dark(ds, modality: str, monochrome1: bool) -> tuple[bool, str]:
    """The header's polarity of the pixels as read: the sign's, flipped when ``monochrome1`` inverted them."""
    sign = ds.get("PixelIntensityRelationshipSign")
    if isinstance(sign, int) and sign in (1, -1):
        dark = (int(sign) == 1) != monochrome1
        return dark, EXPLICIT_POLARITY_SOURCE + (" + MONOCHROME1" if monochrome1 else "")
    default = DEFAULT_BONE_DARK.get(modality, True)
    return default, f"default for modality {modality or 'unknown'} (bone {'dark' if default else 'bright'})"


def _find(ds, keyword: str, frame: int):
    """Value of ``keyword`` at top level, or in the enhanced multi-frame functional groups (this frame's
    per-frame group first, then the shared group); None when absent."""
    if keyword in ds and ds[keyword].value not in (None, ""):
        return ds[keyword].value
    groups = []
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    if per_frame and frame < len(per_frame):
        groups.append(per_frame[frame])
    shared = ds.get("SharedFunctionalGroupsSequence")
    if shared:
        groups.append(shared[0])
    for group in groups:
        for element in group:
            if element.VR == "SQ" and len(element.value) > 0 and keyword in element.value[0]:
                value = element.value[0][keyword].value
                if value not in (None, ""):
                    return value
    return None


def _dicom_geometry(ds, part: XrayParts, frame: int, path: Path) -> None:
    """Fill sdd, pixel spacing, sod and principal point from the header; notes into meta."""
    g, src, meta = part.geometry, part.sources, part.meta
    sdd = dicom_numbers(_find(ds, "DistanceSourceToDetector", frame), 1, "DistanceSourceToDetector", path)
    if sdd is not None:
        g["sdd_mm"], src["sdd_mm"] = float(sdd[0]), "DICOM (0018,1110) DistanceSourceToDetector"
    sod = dicom_numbers(_find(ds, "DistanceSourceToPatient", frame), 1, "DistanceSourceToPatient", path)
    if sod is not None:
        g["sod_mm"], src["sod_mm"] = float(sod[0]), "DICOM (0018,1111) DistanceSourceToPatient"
    imager = dicom_numbers(_find(ds, "ImagerPixelSpacing", frame), 2, "ImagerPixelSpacing", path)
    plain = dicom_numbers(_find(ds, "PixelSpacing", frame), 2, "PixelSpacing", path)
    if imager is not None:
        g["pixel_spacing_mm"] = (float(imager[1]), float(imager[0]))  # stored row \ column
        src["pixel_spacing_mm"] = "DICOM (0018,1164) ImagerPixelSpacing"
    elif plain is not None:
        g["pixel_spacing_mm"] = (float(plain[1]), float(plain[0]))
        src["pixel_spacing_mm"] = "DICOM (0028,0030) PixelSpacing (may be calibrated to the patient)"
        meta["warning_pixel_spacing"] = ("pixel spacing taken from PixelSpacing (0028,0030), which may be "
                                         "calibrated to the patient plane; give --pixel-spacing-mm with the "
                                         "detector pixel size if the registration scale looks wrong")
    _private_principal_point(ds, g, src, path)
    for keyword in ("EstimatedRadiographicMagnificationFactor", "PositionerPrimaryAngle",
                    "PositionerSecondaryAngle", "FieldOfViewHorizontalFlip", "FieldOfViewRotation",
                    "Manufacturer", "ManufacturerModelName", "KVP"):
        value = _find(ds, keyword, frame)
        if value is not None:
            meta[keyword] = _meta_value(value)


def _meta_value(value):
    """A header value for ``meta`` (shown, never computed with): text as is, a number as float, else text."""
    if isinstance(value, str):
        return value
    try:
        return float(value)
    except (TypeError, ValueError):
        return str(value)[:64]


def _private_principal_point(ds, g: dict, src: dict, path: Path) -> None:
    try:
        block = ds.private_block(PRIVATE_GROUP, PRIVATE_CREATOR)
        value = block[PRIVATE_PRINCIPAL_POINT].value
    except (KeyError, ValueError):
        return
    numbers = dicom_numbers(value, 2, "CarmReg private principal point (0029,1001)", path)
    if numbers is not None:
        g["principal_point_px"] = (float(numbers[0]), float(numbers[1]))
        src["principal_point_px"] = "DICOM private (0029,1001) CarmReg"
