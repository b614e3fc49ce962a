"""An X-ray frame as read: ``XrayImage`` (pixels, intrinsics, where each geometry value came from) and
the checks every reader shares (``XrayParts.finish``: pixels finite and not blank, geometry valid, one frame,
grey channels). The formats are read by ``xray_dicom`` and ``xray_raster``; ``xray.load_xray`` chooses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carmreg.logic.errors import GeometryError, InputFileError
from carmreg.logic.geometry.camera import CarmIntrinsics

SOP_CLASS_UIDS = {
    "XA": "1.2.840.10008.5.1.4.1.1.12.1",  # X-Ray Angiographic Image Storage
    "RF": "1.2.840.10008.5.1.4.1.1.12.2",  # X-Ray Radiofluoroscopic Image Storage
    "DX": "1.2.840.10008.5.1.4.1.1.1.1",   # Digital X-Ray Image Storage - For Presentation
    "CR": "1.2.840.10008.5.1.4.1.1.1",     # Computed Radiography Image Storage
}
PRIVATE_GROUP = 0x0029
PRIVATE_CREATOR = "CarmReg"
PRIVATE_PRINCIPAL_POINT = 0x01  # (0029,xx01) DS: u0 \ v0 in px (column, row)
EXPLICIT_POLARITY_SOURCE = "DICOM (0028,1041) PixelIntensityRelationshipSign"
"""``XrayImage.sources["bone_dark"]`` of a file that states its polarity (the rest are defaults for the type)."""
LINEAR_INTENSITY_SOURCE = "DICOM (0028,1040) PixelIntensityRelationship LIN, sign +1"
"""``XrayImage.sources["storage"]`` of a file that states it stores the X-ray intensity itself (linear intensity)."""
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
    def polarity_stated(self) -> bool:
        """The file states which way bone is shown (DICOM PixelIntensityRelationshipSign), rather than CarmReg
        assuming a default for its type; ``image.appearance`` weighs a stated polarity as evidence."""
        return self.sources.get("bone_dark", "").startswith(EXPLICIT_POLARITY_SOURCE)

    @property
    def stated_storage(self) -> str | None:
        """The storage the file states: "linear-intensity" when it stores the X-ray intensity itself (DICOM
        PixelIntensityRelationship LIN with sign +1, ``sources["storage"]``), else None (``image.appearance`` then
        finds it from the image)."""
        return "linear-intensity" if self.sources.get("storage") == LINEAR_INTENSITY_SOURCE else None

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
            missing.append("the detector pixel spacing (give --pixel-spacing-mm, e.g. 0.3, or 0.3 0.3 as "
                           "column then row)")
        what = " and ".join(missing) or "the C-arm geometry"
        verb = "are" if len(missing) > 1 else "is"
        damaged = self.meta.get("warning_unreadable_elements")
        note = f" (unreadable header elements were ignored: {damaged})" if damaged else ""
        raise GeometryError(f"{self.source or 'X-ray'}: {what} {verb} not in the file{note}")


@dataclass
class XrayParts:
    """An X-ray being assembled: pixels plus geometry values found so far (with their sources)."""

    pixels: np.ndarray
    bone_dark: bool
    geometry: dict = field(default_factory=dict)
    sources: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def finish(self, path: Path) -> XrayImage:
        pixels = checked_pixels(self.pixels, path)
        g = self.geometry
        rows, cols = pixels.shape
        intrinsics = None
        if g.get("sdd_mm") is not None and g.get("pixel_spacing_mm") is not None:
            if g.get("principal_point_px") is None:
                self.sources["principal_point_px"] = "default (detector centre)"
            if g.get("distortion_mm") is None:
                self.sources["distortion_mm"] = "default (none)"
            try:
                spacing = tuple(float(x) for x in g["pixel_spacing_mm"])
                intrinsics = CarmIntrinsics(float(g["sdd_mm"]), spacing, (cols, rows),
                                            _optional_pair(g.get("principal_point_px")),
                                            sources=dict(self.sources),
                                            distortion_mm=float(g.get("distortion_mm") or 0.0))
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
                            ("principal point", "principal_point_px"), ("distortion", "distortion_mm")):
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


def checked_pixels(pixels: np.ndarray, path: Path) -> np.ndarray:
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


def select_frame(stack: np.ndarray, frame: int | None, path: Path) -> tuple[np.ndarray, int]:
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


def grey_from_channels(pixels: np.ndarray, path: Path, meta: dict) -> np.ndarray:
    """(rows, cols, c) -> (rows, cols) if the colour channels are equal; refuse a real colour image."""
    colour = pixels[..., :3] if pixels.shape[-1] >= 3 else pixels[..., :1]
    if not all(np.array_equal(colour[..., 0], colour[..., c]) for c in range(1, colour.shape[-1])):
        raise InputFileError(f"{path}: is a colour image (its channels differ); export the X-ray as "
                             "greyscale (DICOM, or 8/16-bit grey PNG/TIFF)")
    meta["note_channels"] = f"{pixels.shape[-1]}-channel image with equal colour channels: used the first"
    return colour[..., 0]

def check_frame_size(cols: int, rows: int, path: Path, n_frames: int = 1, bytes_per_pixel: int = 2) -> None:
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
