"""The intraoperative X-ray: pixels, C-arm intrinsics and where each geometry value came from.

Reading
-------
``load_xray(path, ...)`` reads DICOM (XA, RF, DX, CR; single or multi-frame) or PNG/TIFF/JPEG (8 or 16 bit,
grey, or RGB whose channels are equal). Geometry comes from the DICOM header when present and from the
caller (the CLI's ``--sdd-mm``, ``--pixel-spacing-mm``, ``--principal-point-px``, ``--sod-mm``) otherwise;
a value given by the caller always wins. ``XrayImage.sources`` says where each value came from.

DICOM tags used (all optional):

- ``DistanceSourceToDetector`` (0018,1110) -> ``sdd_mm``.
- ``DistanceSourceToPatient`` (0018,1111) -> ``sod_mm`` (source to isocentre for XA/RF; approximate for DX).
- ``ImagerPixelSpacing`` (0018,1164), stored **row spacing \\ column spacing**, -> ``pixel_spacing_mm =
  (column, row)``. Without it, ``PixelSpacing`` (0028,0030) is used and flagged: it may be calibrated to
  the patient plane (detector spacing / magnification) rather than measured at the detector.
- ``EstimatedRadiographicMagnificationFactor`` (0018,1114), positioner angles, field-of-view flip and
  rotation: recorded in ``meta`` only.
- ``PhotometricInterpretation`` MONOCHROME1 (minimum shown white) is inverted so that larger = brighter - except
  when ``PixelIntensityRelationship`` (0028,1040) is LIN with sign +1: the stored values are then the X-ray
  intensity itself, whose -log is the attenuation (``image.prepare``, linear-intensity storage), while the
  inverted values are neither intensity nor its log (a flat-panel case of the appearance benchmark: GC 0.79
  against 0.89, levels not clicked 3.6-3.8 mm against 0.4-0.6 mm with the values kept); they are kept as stored
  and the image is shown bone dark (``meta["note_linear_intensity"]``). Such a file states its storage, linear
  intensity, whatever its photometric interpretation (``sources["storage"]``, ``XrayImage.stated_storage``).

Pixels
------
``XrayImage.pixels`` is float32 ``image[row, column]`` holding the stored values after the MONOCHROME1 inversion (so
larger values are brighter as displayed; not for linear intensities, above) and the DICOM modality LUT
(``RescaleSlope`` x value + ``RescaleIntercept``, when the file has them; recorded in ``meta["modality_lut"]``).

Display polarity ``bone_dark``: what the file says
---------------------------------------------------
True when dense bone appears dark (fluoroscopy: pixel value grows with the X-ray intensity reaching the
detector). From DICOM ``PixelIntensityRelationshipSign`` (0028,1041): +1 means lower stored values where
less X-ray reaches the detector (behind bone), i.e. bone dark in the stored values; the MONOCHROME1 inversion
flips that. Without the tag the default is True for XA and RF (fluoroscopy display) and False for DX and CR
(radiographs are shown with bone bright); PNG/TIFF/JPEG carry no polarity (True). ``sources["bone_dark"]``
records which rule applied. This is only the header's word: the registration finds the polarity from the image
against the CT (``image.appearance``) unless the user sets it.

Writing
-------
``write_xray_dicom`` writes an uncompressed (explicit VR little endian) 16-bit MONOCHROME2 DICOM carrying
the geometry (and the principal point in a private CarmReg block, group 0029), ``write_png16`` a 16-bit
grey PNG. Both are atomic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carmreg.logic.errors import GeometryError, InputFileError
from carmreg.logic.io.dicom_common import has_dicom_marker, quiet_libraries
from carmreg.logic.io.limits import regular_file
from carmreg.logic.io.xray_dicom import read_dicom
from carmreg.logic.io.xray_image import XrayImage
from carmreg.logic.io.xray_raster import read_raster
from carmreg.logic.io.xray_write import write_png16, write_xray_dicom

__all__ = ["XrayImage", "load_xray", "write_png16", "write_xray_dicom"]

DICOM_SUFFIXES = {".dcm", ".dicom", ".ima", ""}
IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg"}


def load_xray(path: str | Path, *, sdd_mm: float | None = None,
              pixel_spacing_mm: float | tuple[float, float] | None = None,
              principal_point_px: tuple[float, float] | None = None, sod_mm: float | None = None,
              frame: int | None = None, bone_dark: bool | None = None,
              distortion_mm: float | None = None) -> XrayImage:
    """Read an X-ray (DICOM, PNG, TIFF or JPEG) and its geometry; manual values override the file's.

    pixel_spacing_mm: one number (square pixels) or (column, row) spacing at the detector, mm.
    principal_point_px: (u0, v0) = (column, row); default the detector centre.
    frame: 0-based frame of a multi-frame file (required when it holds more than one).
    bone_dark: override the display polarity (see module docstring).
    distortion_mm: an image intensifier's pincushion from the C-arm's calibration, the outward shift (mm) of an
        image point 100 mm from the centre (``CarmIntrinsics.distortion_mm``); default 0 (none).
    Raises InputFileError for unreadable files, GeometryError for impossible geometry values.
    """
    path = Path(path)
    _check_file(path)
    with quiet_libraries() as notes:
        try:
            if _is_dicom(path):
                image = read_dicom(path, frame)
            elif path.suffix.lower() in IMAGE_SUFFIXES:
                image = read_raster(path, frame)
            else:
                raise InputFileError(f"{path}: unknown X-ray format {path.suffix!r}; give a DICOM file or a "
                                     "PNG/TIFF/JPEG")
        except OSError as exc:  # permission denied, I/O error: one line, not a traceback
            raise InputFileError(f"{path}: the X-ray file cannot be read ({exc.strerror or exc}); check its "
                                 "permissions or copy it again") from None
    if notes:
        image.meta["library_warnings"] = notes
    manual = {"sdd_mm": sdd_mm, "pixel_spacing_mm": _spacing_pair(pixel_spacing_mm),
              "principal_point_px": principal_point_px, "sod_mm": sod_mm, "distortion_mm": distortion_mm}
    for key, value in manual.items():
        if value is not None:
            image.geometry[key] = value
            image.sources[key] = "manual"
    if bone_dark is not None:
        image.bone_dark, image.sources["bone_dark"] = bool(bone_dark), "manual"
    return image.finish(path)


def _spacing_pair(spacing) -> tuple[float, float] | None:
    if spacing is None:
        return None
    values = np.atleast_1d(np.asarray(spacing, dtype=float)).ravel()
    if values.size == 1:
        return float(values[0]), float(values[0])
    if values.size == 2:
        return float(values[0]), float(values[1])
    raise GeometryError(f"--pixel-spacing-mm takes one number or two (column, row), got {values.size}")


def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputFileError(f"{path}: X-ray file not found")
    if path.is_dir():
        raise InputFileError(f"{path}: is a folder; give one X-ray file (DICOM, PNG, TIFF or JPEG)")
    regular_file(path, "X-ray file")
    if path.stat().st_size == 0:
        raise InputFileError(f"{path}: X-ray file is empty")


def _is_dicom(path: Path) -> bool:
    """DICOM by its 'DICM' marker at byte 128, or by a DICOM-like or empty suffix (PACS exports such as
    'IM0001', files without preamble)."""
    return has_dicom_marker(path) or path.suffix.lower() in DICOM_SUFFIXES
