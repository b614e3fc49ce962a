"""The simulated imaging chain after the line integrals (``simulator`` steps 4-5): image-intensifier distortion
(pincushion and S-distortion, exact inverse for resampling), detection (scatter, automatic exposure, quantum
noise, blur, vignetting, circular collimation) and the fluoroscopy video display (log, range compression,
edge enhancement, burnt-in text). Detector pixels (u, v) = (column, row); images ``image[row, column]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.simulation.options import SimulationOptions

# ----------------------------------------------------------------------------------------------- distortion

@dataclass(frozen=True)
class IntensifierDistortion:
    """Image-intensifier distortion about ``center_px``, in detector mm (x = (u - u0) du, y = (v - v0) dv).

    Ideal point at radius r appears at radius ``r (1 + k r^2)`` (pincushion, k = edge_mm / R^3) rotated by
    ``phi(r) = phi_edge (r / R)^2`` (S-distortion, phi_edge = s_edge_mm / R), R the field radius in mm.
    """

    center_px: tuple[float, float]
    pixel_spacing_mm: tuple[float, float]
    field_radius_mm: float
    pincushion_edge_mm: float = 0.0
    s_distortion_edge_mm: float = 0.0

    @property
    def k_per_mm2(self) -> float:
        return self.pincushion_edge_mm / self.field_radius_mm**3

    @property
    def phi_edge_rad(self) -> float:
        return self.s_distortion_edge_mm / self.field_radius_mm

    def _to_mm(self, uv_px):
        uv = np.asarray(uv_px, float)
        return ((uv[..., 0] - self.center_px[0]) * self.pixel_spacing_mm[0],
                (uv[..., 1] - self.center_px[1]) * self.pixel_spacing_mm[1])

    def _to_px(self, x, y):
        return np.stack([x / self.pixel_spacing_mm[0] + self.center_px[0],
                         y / self.pixel_spacing_mm[1] + self.center_px[1]], -1)

    def _twist(self, x, y, r, sign):
        phi = sign * self.phi_edge_rad * (r / self.field_radius_mm) ** 2
        c, s = np.cos(phi), np.sin(phi)
        return c * x - s * y, s * x + c * y

    def distort(self, uv_px) -> np.ndarray:
        """Ideal (pinhole) pixel positions (..., 2) -> where they appear in the image."""
        x, y = self._to_mm(uv_px)
        r = np.hypot(x, y)
        scale = 1.0 + self.k_per_mm2 * r * r
        x, y = self._twist(x * scale, y * scale, r, 1.0)
        return self._to_px(x, y)

    def undistort(self, uv_px) -> np.ndarray:
        """Image pixel positions (..., 2) -> ideal positions (exact inverse by Newton on the radius)."""
        x, y = self._to_mm(uv_px)
        rd = np.hypot(x, y)
        k = self.k_per_mm2
        r = rd.copy()
        for _ in range(30):
            step = (r + k * r**3 - rd) / (1.0 + 3.0 * k * r * r)
            r = r - step
            if np.all(np.abs(step) < 1e-12):
                break
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        x, y = self._twist(x, y, r, -1.0)
        return self._to_px(x * scale, y * scale)

    @classmethod
    def from_dict(cls, d: dict) -> IntensifierDistortion:
        """Inverse of ``as_dict`` (e.g. from ground_truth.json)."""
        return cls(tuple(d["center_px"]), tuple(d["pixel_spacing_mm"]), float(d["field_radius_mm"]),
                   float(d["pincushion_edge_mm"]), float(d["s_distortion_edge_mm"]))

    def as_dict(self) -> dict:
        return {"model": "pincushion r(1 + k r^2) then twist phi_edge (r/R)^2 about center_px, detector mm",
                "center_px": list(self.center_px), "pixel_spacing_mm": list(self.pixel_spacing_mm),
                "field_radius_mm": self.field_radius_mm,
                "pincushion_edge_mm": self.pincushion_edge_mm, "s_distortion_edge_mm": self.s_distortion_edge_mm,
                "k_per_mm2": self.k_per_mm2, "phi_edge_rad": self.phi_edge_rad}


def resample_distorted(image: np.ndarray, distortion: IntensifierDistortion) -> np.ndarray:
    """Image as seen through the distortion: out(q) = image(D^-1(q)), bilinear, edge values outside."""
    rows, cols = image.shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    ideal = distortion.undistort(np.stack([uu, vv], -1))
    coords = np.stack([ideal[..., 1], ideal[..., 0]])
    return ndimage.map_coordinates(image, coords, order=1, mode="nearest").astype(np.float32)


# ----------------------------------------------------------------------------------------------- detection

def _radius_mm(intr: CarmIntrinsics) -> np.ndarray:
    cols, rows = intr.size_px
    du, dv = intr.pixel_spacing_mm
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    return np.hypot((uu - (cols - 1) / 2.0) * du, (vv - (rows - 1) / 2.0) * dv)


def _wide_blur(image: np.ndarray, sigma_px: float, mode: str = "constant") -> np.ndarray:
    """Gaussian blur with a large sigma (>= 8 px), computed on 8 x 8 block means then upsampled linearly."""
    f = 8
    rows, cols = image.shape
    pad = ((0, -rows % f), (0, -cols % f))
    blocks = np.pad(image, pad, mode="edge").reshape((rows + pad[0][1]) // f, f, (cols + pad[1][1]) // f, f)
    small = ndimage.gaussian_filter(blocks.mean(axis=(1, 3)), sigma_px / f, mode=mode)
    # block b covers pixels [b f, b f + f - 1]: its centre is at pixel b f + (f - 1) / 2
    coords = [(np.arange(n) - (f - 1) / 2.0) / f for n in (rows, cols)]
    grid = np.meshgrid(*coords, indexing="ij")
    return ndimage.map_coordinates(small, grid, order=1, mode="nearest").astype(np.float32)


def detect(line_integrals: np.ndarray, intr: CarmIntrinsics, options: SimulationOptions,
           rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Distorted line integrals -> display values (float, 0..1, bone dark) and the exposure facts."""
    du = float(np.mean(intr.pixel_spacing_mm))
    r = _radius_mm(intr)
    radius = options.field_diameter_mm / 2.0
    field = np.clip((radius - r) / 0.75 + 0.5, 0.0, 1.0)  # ~1.5 mm soft collimator edge
    primary = np.exp(-line_integrals.astype(np.float64)) * field
    g = options.scatter_fraction
    signal = primary if g <= 0 else (1.0 - g) * primary + g * _wide_blur(primary, options.scatter_sigma_mm / du)
    central = r < 0.3 * radius
    n0 = max(options.photons_per_pixel, 1.0) / max(float(signal[central].mean()), 1e-300)
    counts = signal * n0
    if options.photons_per_pixel > 0:
        counts = rng.poisson(counts).astype(np.float64)
    if options.detector_blur_sigma_mm > 0:
        counts = ndimage.gaussian_filter(counts, options.detector_blur_sigma_mm / du)
    counts *= 1.0 - options.vignetting * np.clip(r / radius, 0.0, 1.0) ** 2
    display = video_display(counts / max(options.photons_per_pixel, 1.0), field, central, du, options)
    facts = {"n0_photons_unattenuated": float(n0), "mean_counts_central": float(np.mean(counts[central])),
             "display_mode": options.display_mode}
    return display, facts


def video_display(relative: np.ndarray, field: np.ndarray, central: np.ndarray, du_mm: float,
                  options: SimulationOptions) -> np.ndarray:
    """Detected signal (1 = the AEC target) -> display value 0..1, bone dark.

    linear: ``mid * relative`` (for tests). log (the usual II-TV chain with its image processing):
    ``y = log(relative)``; dynamic range compression ``y - b G_wide * y`` (b = range_compression); edge
    enhancement ``y + a (y - G_edge * y)``; then ``mid + contrast * (y - median of the AEC disc)`` (the AEC
    region at mid grey; lungs may saturate white as in real thoracic fluoroscopy).
    """
    mid = options.display_mid_grey
    if options.display_mode == "linear":
        return np.clip(mid * relative * field, 0.0, 1.0)
    y = np.log(np.clip(relative, 1e-4, None))
    y = np.where(field > 0.5, y, float(np.median(y[central])))  # no collimator edge ringing
    if options.range_compression > 0:
        y = y - options.range_compression * _wide_blur(y, options.range_sigma_mm / du_mm, "nearest")
    if options.edge_enhancement > 0:
        y = y + options.edge_enhancement * (y - ndimage.gaussian_filter(y, options.edge_sigma_mm / du_mm))
    y -= float(np.median(y[central]))
    return np.clip(mid + options.display_contrast * y, 0.0, 1.0) * field


def burn_in_text(pixels: np.ndarray, lines: dict[str, list[str]], value: int) -> np.ndarray:
    """Draw text into the corners ('tl', 'tr', 'bl', 'br') of a uint16 image (in place) with PIL."""
    from PIL import Image, ImageDraw, ImageFont

    rows, cols = pixels.shape
    size = max(10, rows // 40)
    font = ImageFont.load_default(size=size)
    canvas = Image.new("L", (cols, rows), 0)
    draw = ImageDraw.Draw(canvas)
    pad, step = rows // 60, int(size * 1.3)
    for corner, text in lines.items():
        for n, line in enumerate(text):
            width = draw.textlength(line, font=font)
            x = pad if corner[1] == "l" else cols - pad - width
            y = pad + n * step if corner[0] == "t" else rows - pad - (len(text) - n) * step
            draw.text((x, y), line, fill=255, font=font)
    mask = np.asarray(canvas) > 127
    pixels[mask] = value
    return pixels


def tube_kv(bone_contrast_factor: float) -> float:
    """Tube voltage matching a bone contrast factor (x1.7 at 60 kV, x1 at 90 kV, x0.76 at 120 kV; linear)."""
    return float(np.interp(bone_contrast_factor, [0.76, 1.0, 1.7], [120.0, 90.0, 60.0]))


def text_lines(options: SimulationOptions, seed: int) -> dict[str, list[str]]:
    kv = tube_kv(options.bone_contrast_factor)
    return {"tl": ["CARMREG SIMULATION", f"SEED {seed}"],
            "tr": [f"{kv:.0f} kV  {1.0 + 2.0 * min(options.photons_per_pixel / 1e4, 1.0):.1f} mA", "PULSED 8 p/s"],
            "bl": ["AP", "NOT FOR DIAGNOSIS"],
            "br": ["SAVED 1/1", "9\" FIELD"]}
