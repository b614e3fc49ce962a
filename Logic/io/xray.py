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
- ``PhotometricInterpretation`` MONOCHROME1 (minimum shown white) is inverted so that larger = brighter.

Pixels
------
``XrayImage.pixels`` is float32 ``image[row, column]`` holding the stored values after the MONOCHROME1
inversion (so larger values are brighter as displayed) and the DICOM modality LUT (``RescaleSlope`` x value +
``RescaleIntercept``, when the file has them; recorded in ``meta["modality_lut"]``).

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

import datetime as _dt
import logging
import struct
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carmreg.logic.errors import GeometryError, InputFileError
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.io.atomic import atomic_write
from carmreg.logic.io.limits import check_dicom_size, regular_file

DICOM_SUFFIXES = {".dcm", ".dicom", ".ima", ""}
IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg"}
SOP_CLASS_UIDS = {
    "XA": "1.2.840.10008.5.1.4.1.1.12.1",  # X-Ray Angiographic Image Storage
    "RF": "1.2.840.10008.5.1.4.1.1.12.2",  # X-Ray Radiofluoroscopic Image Storage
    "DX": "1.2.840.10008.5.1.4.1.1.1.1",   # Digital X-Ray Image Storage - For Presentation
    "CR": "1.2.840.10008.5.1.4.1.1.1",     # Computed Radiography Image Storage
}
PRIVATE_GROUP = 0x0029
PRIVATE_CREATOR = "CarmReg"
PRIVATE_PRINCIPAL_POINT = 0x01  # (0029,xx01) DS: u0 \ v0 in px (column, row)
DEFAULT_BONE_DARK = {"XA": True, "RF": True, "DX": False, "CR": False}
MAX_XRAY_PIXELS = 64 * 1024**2
"""Largest single X-ray frame accepted (pixels); real detectors are below ~20 Mpx."""
MAX_XRAY_BYTES = 4 * 1024**3
"""Largest decoded pixel array accepted (all frames of a DICOM run), bytes."""


@dataclass
class XrayImage:
    """One X-ray frame with its geometry.

    pixels: (rows, columns) float32, image[row, column], larger = brighter as displayed.
    intrinsics: the C-arm intrinsics, or None when the source-to-detector distance or the pixel spacing is
        unknown (call ``require_intrinsics()`` to get a clear error).
    sod_mm: source-to-isocentre (DICOM: source-to-patient) distance when known.
    bone_dark: True when dense bone appears dark (see module docstring).
    source: the file read.
    sources: where each geometry value came from, e.g. {"sdd_mm": "DICOM (0018,1110)", "sod_mm": "manual"}.
    meta: other facts worth showing (modality, frame, magnification factor, positioner angles, notes).
    """

    pixels: np.ndarray
    intrinsics: CarmIntrinsics | None
    sod_mm: float | None = None
    bone_dark: bool = True
    source: str = ""
    sources: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    @property
    def size_px(self) -> tuple[int, int]:
        """(columns, rows)."""
        return int(self.pixels.shape[1]), int(self.pixels.shape[0])

    def require_intrinsics(self) -> CarmIntrinsics:
        """The intrinsics, or a GeometryError naming the command-line flags that would complete them."""
        if self.intrinsics is not None:
            return self.intrinsics
        missing = []
        if "sdd_mm" not in self.sources:
            missing.append("the source-to-detector distance (give --sdd-mm, about 1000 for a C-arm)")
        if "pixel_spacing_mm" not in self.sources:
            missing.append("the detector pixel spacing (give --pixel-spacing-mm, e.g. 0.3 or 0.3,0.3 as "
                           "column,row)")
        what = " and ".join(missing) or "the C-arm geometry"
        verb = "are" if len(missing) > 1 else "is"
        damaged = self.meta.get("warning_unreadable_elements")
        note = f" (unreadable header elements were ignored: {damaged})" if damaged else ""
        raise GeometryError(f"{self.source or 'X-ray'}: {what} {verb} not in the file{note}")


# ----------------------------------------------------------------------------------------------- writing

def _dicom_uids(modality: str):
    from pydicom.uid import generate_uid

    if modality not in SOP_CLASS_UIDS:
        raise ValueError(f"modality must be one of {sorted(SOP_CLASS_UIDS)}, got {modality!r}")
    return SOP_CLASS_UIDS[modality], generate_uid(), generate_uid(), generate_uid()


def write_xray_dicom(path: str | Path, pixels_uint16: np.ndarray, intrinsics: CarmIntrinsics, *,
                     sod_mm: float | None = None, modality: str = "XA", patient_name: str = "CarmReg^Sample",
                     bone_dark: bool = True) -> Path:
    """Write a single-frame 16-bit MONOCHROME2 X-ray DICOM (explicit VR little endian), atomically.

    pixels_uint16: (rows, columns) image[row, column]; must match ``intrinsics.size_px``.
    Geometry written: DistanceSourceToDetector = sdd_mm, ImagerPixelSpacing = [row spacing, column
    spacing] (DICOM order), DistanceSourceToPatient and EstimatedRadiographicMagnificationFactor =
    sdd/sod when ``sod_mm`` is given, the principal point in private tag (0029,1001) "CarmReg".
    ``bone_dark`` sets PixelIntensityRelationshipSign (+1 bone dark, -1 bone bright).
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    pixels = np.asarray(pixels_uint16)
    if pixels.ndim != 2 or pixels.dtype != np.uint16:
        raise ValueError(f"pixels_uint16 must be a 2D uint16 array, got {pixels.dtype} {pixels.shape}")
    if (pixels.shape[1], pixels.shape[0]) != tuple(intrinsics.size_px):
        raise ValueError(f"image is {pixels.shape[1]}x{pixels.shape[0]} px but intrinsics.size_px is "
                         f"{intrinsics.size_px}")
    sop_class, sop_instance, study_uid, series_uid = _dicom_uids(modality)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_instance
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    now = _dt.datetime.now()
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, sop_instance
    ds.StudyInstanceUID, ds.SeriesInstanceUID = study_uid, series_uid
    ds.Modality = modality
    ds.PatientName, ds.PatientID = patient_name, "CARMREG"
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.SeriesNumber, ds.InstanceNumber = 1, 1
    ds.ImageType = ["DERIVED", "SECONDARY", "SINGLE PLANE"] if modality in ("XA", "RF") else ["DERIVED",
                                                                                             "SECONDARY"]
    ds.Manufacturer = "CarmReg"
    _set_pixels(ds, pixels)
    ds.PixelIntensityRelationship = "LIN" if bone_dark else "LOG"
    ds.PixelIntensityRelationshipSign = 1 if bone_dark else -1
    _set_geometry(ds, intrinsics, sod_mm)
    atomic_write(path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))
    return Path(path)


def _set_pixels(ds, pixels: np.ndarray) -> None:
    ds.Rows, ds.Columns = int(pixels.shape[0]), int(pixels.shape[1])
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 0
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<u2").tobytes()


def _set_geometry(ds, intrinsics: CarmIntrinsics, sod_mm: float | None) -> None:
    du, dv = intrinsics.pixel_spacing_mm
    ds.DistanceSourceToDetector = ds_decimal(intrinsics.sdd_mm)
    ds.ImagerPixelSpacing = [ds_decimal(dv), ds_decimal(du)]  # DICOM order: row spacing \ column spacing
    if sod_mm is not None:
        ds.DistanceSourceToPatient = ds_decimal(sod_mm)
        ds.EstimatedRadiographicMagnificationFactor = ds_decimal(intrinsics.sdd_mm / sod_mm)
    block = ds.private_block(PRIVATE_GROUP, PRIVATE_CREATOR, create=True)
    block.add_new(PRIVATE_PRINCIPAL_POINT, "DS", [ds_decimal(x) for x in intrinsics.principal_point_px])


def ds_decimal(x: float) -> str:
    """A DICOM decimal string (at most 16 characters) holding ``x`` as precisely as fits."""
    for digits in range(12, 3, -1):
        text = f"{float(x):.{digits}g}"
        if len(text) <= 16:
            return text
    raise ValueError(f"cannot write {x} as a DICOM decimal string")


def write_png16(path: str | Path, pixels_uint16: np.ndarray) -> Path:
    """Write a (rows, columns) uint16 image as a 16-bit greyscale PNG, atomically."""
    from PIL import Image

    pixels = np.asarray(pixels_uint16)
    if pixels.ndim != 2 or pixels.dtype != np.uint16:
        raise ValueError(f"pixels_uint16 must be a 2D uint16 array, got {pixels.dtype} {pixels.shape}")
    image = Image.fromarray(np.ascontiguousarray(pixels))
    atomic_write(path, lambda tmp: image.save(tmp, format="PNG"))
    return Path(path)


# ----------------------------------------------------------------------------------------------- reading

def load_xray(path: str | Path, *, sdd_mm: float | None = None,
              pixel_spacing_mm: float | tuple[float, float] | None = None,
              principal_point_px: tuple[float, float] | None = None, sod_mm: float | None = None,
              frame: int | None = None, bone_dark: bool | None = None) -> XrayImage:
    """Read an X-ray (DICOM, PNG, TIFF or JPEG) and its geometry; manual values override the file's.

    pixel_spacing_mm: one number (square pixels) or (column, row) spacing at the detector, mm.
    principal_point_px: (u0, v0) = (column, row); default the detector centre.
    frame: 0-based frame of a multi-frame file (required when it holds more than one).
    bone_dark: override the display polarity (see module docstring).
    Raises InputFileError for unreadable files, GeometryError for impossible geometry values.
    """
    path = Path(path)
    _check_file(path)
    with quiet_libraries() as notes:
        try:
            if _is_dicom(path):
                image = _read_dicom(path, frame)
            elif path.suffix.lower() in IMAGE_SUFFIXES:
                image = _read_raster(path, frame)
            else:
                raise InputFileError(f"{path}: unknown X-ray format {path.suffix!r}; give a DICOM file or a "
                                     "PNG/TIFF/JPEG")
        except OSError as exc:  # permission denied, I/O error: one line, not a traceback
            raise InputFileError(f"{path}: the X-ray file cannot be read ({exc.strerror or exc}); check its "
                                 "permissions or copy it again") from None
    if notes:
        image.meta["library_warnings"] = notes
    manual = {"sdd_mm": sdd_mm, "pixel_spacing_mm": _spacing_pair(pixel_spacing_mm),
              "principal_point_px": principal_point_px, "sod_mm": sod_mm}
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
    with open(path, "rb") as handle:
        head = handle.read(132)
    return head[128:132] == b"DICM" or path.suffix.lower() in DICOM_SUFFIXES


@dataclass
class _Partial:
    """An X-ray being assembled: pixels plus geometry values found so far (with their sources)."""

    pixels: np.ndarray
    bone_dark: bool
    geometry: dict = field(default_factory=dict)
    sources: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def finish(self, path: Path) -> XrayImage:
        pixels = _checked_pixels(self.pixels, path)
        g = self.geometry
        rows, cols = pixels.shape
        intrinsics = None
        if g.get("sdd_mm") is not None and g.get("pixel_spacing_mm") is not None:
            if g.get("principal_point_px") is None:
                self.sources["principal_point_px"] = "default (detector centre)"
            try:
                spacing = tuple(float(x) for x in g["pixel_spacing_mm"])
                intrinsics = CarmIntrinsics(float(g["sdd_mm"]), spacing, (cols, rows),
                                            _optional_pair(g.get("principal_point_px")),
                                            sources=dict(self.sources))
            except GeometryError as exc:
                raise GeometryError(f"{path}: {exc}{self._origin_of(str(exc))}") from None
        sod = g.get("sod_mm")
        if sod is not None:
            self._check_sod(float(sod), None if intrinsics is None else intrinsics.sdd_mm, path)
        return XrayImage(pixels, intrinsics, None if sod is None else float(sod), self.bone_dark, str(path),
                         self.sources, self.meta)

    def _origin_of(self, message: str) -> str:
        """' (value from ...)' for the geometry value a CarmIntrinsics message is about, when not manual."""
        for prefix, key in (("source-to-detector", "sdd_mm"), ("pixel spacing", "pixel_spacing_mm"),
                            ("principal point", "principal_point_px")):
            source = self.sources.get(key)
            if message.startswith(prefix) and source and source != "manual":
                return f" (the value was read from {source}; the manual value overrides it)"
        return ""

    def _check_sod(self, sod_mm: float, sdd_mm: float | None, path: Path) -> None:
        origin = f" (from {self.sources.get('sod_mm')})" if self.sources.get("sod_mm") != "manual" else ""
        if not (np.isfinite(sod_mm) and sod_mm > 0):
            raise GeometryError(f"{path}: source-to-patient distance {sod_mm} mm{origin} is not positive; "
                                "give --sod-mm (about 0.6 x the source-to-detector distance)")
        if sdd_mm is not None and sod_mm >= sdd_mm:
            raise GeometryError(f"{path}: source-to-patient distance {sod_mm:g} mm{origin} is not shorter "
                                f"than the source-to-detector distance {sdd_mm:g} mm; the patient lies "
                                "between source and detector, give --sod-mm below --sdd-mm")


def _checked_pixels(pixels: np.ndarray, path: Path) -> np.ndarray:
    """float32 image[row, column]; refuse an empty, non-finite or blank (uniform) image."""
    pixels = np.ascontiguousarray(pixels, dtype=np.float32)
    if pixels.ndim != 2 or min(pixels.shape) < 2:
        raise InputFileError(f"{path}: the image has shape {pixels.shape}; an X-ray is one grey image of at "
                             "least 2 x 2 px")
    lo, hi = float(pixels.min()), float(pixels.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = int(np.count_nonzero(~np.isfinite(pixels)))
        raise InputFileError(f"{path}: {bad} pixel(s) are not finite numbers (NaN or infinity); export the "
                             "X-ray again as an integer image")
    if lo == hi:
        raise InputFileError(f"{path}: the image is blank (every pixel is {lo:g}); give the X-ray frame "
                             "itself, not an empty or saturated frame")
    return pixels


def _optional_pair(value) -> tuple[float, float] | None:
    return None if value is None else (float(value[0]), float(value[1]))


def _select_frame(stack: np.ndarray, frame: int | None, path: Path) -> tuple[np.ndarray, int]:
    """(n, rows, cols[, c]) -> one frame; refuse an ambiguous or out-of-range choice."""
    n = stack.shape[0]
    if n == 0:
        raise InputFileError(f"{path}: holds no image frame")
    if frame is None:
        if n > 1:
            raise InputFileError(f"{path}: holds {n} frames; choose one with --frame N (0 to {n - 1}), "
                                 "e.g. the last, sharpest frame of a fluoroscopy run")
        frame = 0
    if frame < 0:
        raise InputFileError(f"{path}: --frame {frame}: frames are counted from 0 (the first) to {n - 1} (the "
                             "last); give a frame number in that range")
    if not frame < n:
        raise InputFileError(f"{path}: frame {frame} does not exist; the file holds {n} frame(s), "
                             f"choose --frame 0 to {n - 1}")
    return stack[frame], frame % n


def _grey_from_channels(pixels: np.ndarray, path: Path, meta: dict) -> np.ndarray:
    """(rows, cols, c) -> (rows, cols) if the colour channels are equal; refuse a real colour image."""
    colour = pixels[..., :3] if pixels.shape[-1] >= 3 else pixels[..., :1]
    if not all(np.array_equal(colour[..., 0], colour[..., c]) for c in range(1, colour.shape[-1])):
        raise InputFileError(f"{path}: is a colour image (its channels differ); export the X-ray as "
                             "greyscale (DICOM, or 8/16-bit grey PNG/TIFF)")
    meta["note_channels"] = f"{pixels.shape[-1]}-channel image with equal colour channels: used the first"
    return colour[..., 0]


# ---- DICOM

def _read_dicom(path: Path, frame: int | None) -> _Partial:
    ds = _dcmread(path)
    dropped = drop_unreadable_elements(ds)
    if "SOPClassUID" not in ds and "PixelData" not in ds:
        raise InputFileError(f"{path}: not a DICOM file (nor PNG/TIFF/JPEG); give the X-ray image")
    modality = str(ds.get("Modality", "") or "").upper()
    if modality and modality not in SOP_CLASS_UIDS and modality not in ("OT", "XC", "RG", "PX", "IO", "MG"):
        raise InputFileError(f"{path}: DICOM modality {modality!r} is not an X-ray image; give an XA, RF, DX "
                             "or CR projection image")
    stack = _dicom_frames(ds, path)
    pixels, frame = _select_frame(stack, frame, path)
    meta = {"format": "DICOM", "modality": modality, "frame": frame, "n_frames": int(stack.shape[0]),
            "photometric": str(ds.get("PhotometricInterpretation", ""))}
    if pixels.ndim == 3:
        pixels = _grey_from_channels(pixels, path, meta)
    pixels = pixels.astype(np.float32)
    monochrome1 = meta["photometric"].upper() == "MONOCHROME1"
    if monochrome1:
        pixels = _invert_monochrome1(pixels, ds, path)
        meta["note_inverted"] = "MONOCHROME1: stored values inverted so that larger = brighter"
    pixels = _modality_lut(pixels, ds, frame, path, meta)
    if dropped:
        meta["warning_unreadable_elements"] = ", ".join(dropped[:6]) + (" ..." if len(dropped) > 6 else "")
    part = _Partial(pixels, True, meta=meta)
    part.bone_dark, part.sources["bone_dark"] = _dicom_bone_dark(ds, modality, monochrome1)
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
    except DICOM_PARSE_ERRORS as exc:
        raise InputFileError(f"{path}: not a readable DICOM file ({describe(exc, 100)})") from None
    return ds


QUIET_LOGGERS = ("pydicom", "nibabel", "nibabel.global", "PIL")


@contextmanager
def quiet_libraries(limit: int = 5) -> Iterator[list[str]]:
    """Collect instead of print what pydicom, Pillow and nibabel warn or log while reading a damaged or
    non-standard file (the command line keeps one line per error on stderr). Yields a list that holds, on
    exit, the first ``limit`` distinct warning messages (for ``meta``); library log records are dropped."""
    notes: list[str] = []
    loggers = [logging.getLogger(name) for name in QUIET_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield notes
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)
        for message in dict.fromkeys(" ".join(str(w.message).split())[:160] for w in caught):
            if len(notes) < limit:
                notes.append(message)


def describe(exc: BaseException, limit: int = 100) -> str:
    """'Kind: message' of a library exception on one line (whitespace collapsed) and at most ``limit``
    characters of message, for embedding in a one-line CarmRegError."""
    text = " ".join(str(exc).split())
    return f"{exc.__class__.__name__}: {text[:limit]}"


def _dicom_parse_errors() -> tuple:
    from pydicom.errors import BytesLengthException, InvalidDicomError

    return (InvalidDicomError, BytesLengthException, struct.error, NotImplementedError, EOFError, OSError,
            ValueError, KeyError, TypeError, IndexError, OverflowError, UnicodeError, AttributeError)


DICOM_PARSE_ERRORS = _dicom_parse_errors()
"""What pydicom raises on a damaged file (while reading, or when an element is first decoded)."""


def drop_unreadable_elements(ds) -> list[str]:
    """Decode every element now (pydicom decodes lazily) and delete, recursively, those that cannot be
    decoded (a damaged or non-standard vendor element); returns their '(gggg,eeee) Keyword' names.

    An X-ray stays usable without, say, a broken private tag; a needed value that was dropped is then simply
    absent (the loader asks for it, naming what was ignored). Pixel data are not decoded.
    """
    from pydicom.datadict import keyword_for_tag

    dropped = []
    for tag in list(ds.keys()):
        try:
            element = ds[tag]
            if element.VR == "SQ":
                for item in element.value:
                    dropped += drop_unreadable_elements(item)
            else:
                _ = element.value
        except DICOM_PARSE_ERRORS:
            keyword = keyword_for_tag(tag)
            dropped.append(f"({tag.group:04X},{tag.element:04X}){' ' + keyword if keyword else ''}")
            del ds[tag]
    return dropped


def dicom_numbers(value, count: int | None, keyword: str, path: Path) -> np.ndarray | None:
    """A DICOM numeric value (DS/IS/US/FD, single or multi-valued) as float64, or None when absent.

    count: how many numbers are required (None: any number >= 1). A present but malformed value (text that
    is not a number, wrong multiplicity, NaN) raises InputFileError naming the tag.
    """
    if value is None or (isinstance(value, (str, bytes)) and not value.strip()):
        return None
    items = [value] if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__") else list(value)
    try:
        numbers = np.array([float(x) for x in items], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputFileError(f"{path}: DICOM {keyword} = {str(value)[:40]!r} is not a number; the header is "
                             "damaged or non-standard (give the value manually, or export the file again)") \
            from None
    if (count is not None and numbers.size != count) or numbers.size == 0 or not np.all(np.isfinite(numbers)):
        want = f"{count} number(s)" if count is not None else "finite numbers"
        raise InputFileError(f"{path}: DICOM {keyword} = {str(value)[:40]!r} is not {want}; the header is "
                             "damaged or non-standard (give the value manually, or export the file again)")
    return numbers


def dicom_int(ds, keyword: str, default: int, path: Path) -> int:
    """An integer attribute (IS/US) with a default when absent or empty."""
    numbers = dicom_numbers(ds.get(keyword), 1, keyword, path)
    if numbers is None:
        return default
    if numbers[0] != round(numbers[0]) or abs(numbers[0]) > 2**31:
        raise InputFileError(f"{path}: DICOM {keyword} = {numbers[0]:g} is not a valid integer; the header "
                             "is damaged")
    return int(numbers[0])


def _dicom_frames(ds, path: Path) -> np.ndarray:
    """Decoded pixel data as (frames, rows, cols[, samples])."""
    if "PixelData" not in ds:
        raise InputFileError(f"{path}: DICOM file has no image (no PixelData); give an image file, not a "
                             "report or DICOMDIR")
    n_frames = dicom_int(ds, "NumberOfFrames", 1, path)
    samples = dicom_int(ds, "SamplesPerPixel", 1, path)
    _check_size(dicom_int(ds, "Columns", 0, path), dicom_int(ds, "Rows", 0, path), path,
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


def _invert_monochrome1(pixels: np.ndarray, ds, path: Path) -> np.ndarray:
    """Map the stored range onto itself reversed: unsigned v -> (2^bits - 1) - v, signed v -> -1 - v."""
    bits = dicom_int(ds, "BitsStored", 16, path)
    if ds.get("PixelRepresentation", 0) == 1:
        return np.float32(-1.0) - pixels
    return np.float32(2**bits - 1) - pixels


def _dicom_bone_dark(ds, modality: str, monochrome1: bool) -> tuple[bool, str]:
    sign = ds.get("PixelIntensityRelationshipSign")
    if isinstance(sign, int) and sign in (1, -1):
        dark = (int(sign) == 1) != monochrome1
        return dark, "DICOM (0028,1041) PixelIntensityRelationshipSign" + (" + MONOCHROME1" if monochrome1
                                                                           else "")
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


def _dicom_geometry(ds, part: _Partial, frame: int, path: Path) -> None:
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


# ---- PNG / TIFF

def _read_raster(path: Path, frame: int | None) -> _Partial:
    """8/16-bit (or float) grey PNG/TIFF/JPEG via Pillow; multi-page TIFF needs ``frame``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            n = int(getattr(image, "n_frames", 1))
            _, frame = _select_frame(np.empty((n, 0)), frame, path)
            image.seek(frame)
            _check_size(*image.size, path)
            mode = image.mode
            pixels = _pil_to_array(image)
    except Image.DecompressionBombError:
        limit = 2 * Image.MAX_IMAGE_PIXELS // 10**6  # Pillow refuses above twice its warning threshold
        raise InputFileError(f"{path}: the image claims more than {limit} million pixels, far more than an "
                             "X-ray detector; the file is damaged or not an X-ray") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, TypeError, KeyError, IndexError,
            struct.error, EOFError, ZeroDivisionError, OverflowError, MemoryError) as exc:
        raise InputFileError(f"{path}: not a readable image ({describe(exc, 100)}); "
                             "the file may be truncated or of another format") from None
    meta = {"format": path.suffix.lower().lstrip("."), "mode": mode, "frame": frame, "n_frames": n}
    if pixels.ndim == 3:
        pixels = _grey_from_channels(pixels, path, meta)
    part = _Partial(pixels.astype(np.float32), True, meta=meta)
    part.sources["bone_dark"] = ("no polarity in PNG/TIFF/JPEG files: bone dark assumed until the registration "
                                 "finds it from the image")
    return part


def _check_size(cols: int, rows: int, path: Path, n_frames: int = 1, bytes_per_pixel: int = 2) -> None:
    """Refuse, before decoding, an image whose frame or whole pixel array is larger than any C-arm's."""
    cols, rows, n_frames = int(cols), int(rows), int(n_frames)
    if cols * rows > MAX_XRAY_PIXELS:
        raise InputFileError(f"{path}: a frame of {cols} x {rows} px is larger than any X-ray detector "
                             f"(limit {MAX_XRAY_PIXELS // 1024**2} Mpx); the header is damaged or this is "
                             "not an X-ray")
    n_bytes = cols * rows * n_frames * int(bytes_per_pixel)
    if n_bytes > MAX_XRAY_BYTES:
        raise InputFileError(f"{path}: {n_frames} frames of {cols} x {rows} px need {n_bytes / 1024**3:.1f} "
                             f"GiB, more than the {MAX_XRAY_BYTES / 1024**3:.0f} GiB limit; export the frame "
                             "you want as a single-frame file")


def _pil_to_array(image) -> np.ndarray:
    """Pillow image -> numpy; palette and 1-bit images expanded; alpha dropped."""
    if image.mode == "P":
        image = image.convert("RGB")
    elif image.mode == "1":
        image = image.convert("L")
    elif image.mode in ("LA", "PA"):
        image = image.convert("RGBA" if image.mode == "PA" else "LA")
        return np.asarray(image)[..., 0]
    pixels = np.asarray(image)
    if pixels.ndim == 3 and pixels.shape[-1] == 4:
        pixels = pixels[..., :3]
    return pixels
