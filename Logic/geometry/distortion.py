"""Radial distortion of an image-intensifier C-arm: where a pinhole (ideal) detector point really shows.

An image intensifier's electron optics stretch the image more toward its rim (pincushion). The model is the
first radial term about the principal point ``c`` of ``camera.CarmIntrinsics`` (px), written from the image
to the ideal (pinhole) detector, in detector mm::

    d' = ((u - c_u) du, (v - c_v) dv)       a point of the image, mm from the centre
    d  = d' (1 - k |d'|^2)                  the ideal point whose ray shows there (k > 0: pincushion)

``k`` (1/mm^2) is reported as ``shift_at_100_mm = k 100^3``: how far (mm) a point the image shows 100 mm from
the centre lies outward of where a pinhole would put it. A flat panel has k = 0. This direction is the
explicit one because it is what the DRR renderer needs (the ray of each image pixel, ``drr.cpu``) and what
clicks need (the ideal point of a clicked pixel); the other direction (``distort``, the image position of a
projected point) is solved by fixed-point iteration. The projection matrix ``P`` stays the pinhole camera.
Pixel order (column, row), 0-based pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REFERENCE_RADIUS_MM = 100.0
"""``shift_at_100_mm`` is the shift of a point this far from the centre."""
DISTORTION_MODEL = ("ideal d = d' (1 - k |d'|^2), d' the image point in detector mm from the principal point; "
                    "distortion_mm = k 100^3")
"""The model in words, as result.json records it."""


@dataclass(frozen=True)
class RadialDistortion:
    """``d = d' (1 - k |d'|^2)`` about ``centre_px`` (module docstring); ``k_per_mm2`` = 0 is the pinhole."""

    k_per_mm2: float
    centre_px: tuple[float, float]
    pixel_spacing_mm: tuple[float, float]

    @classmethod
    def from_shift(cls, shift_at_100_mm: float, centre_px, pixel_spacing_mm) -> RadialDistortion:
        return cls(float(shift_at_100_mm) / REFERENCE_RADIUS_MM**3, tuple(map(float, centre_px)),
                   tuple(map(float, pixel_spacing_mm)))

    @property
    def shift_at_100_mm(self) -> float:
        return self.k_per_mm2 * REFERENCE_RADIUS_MM**3

    def _mm(self, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv = np.asarray(uv_px, float)
        return ((uv[..., 0] - self.centre_px[0]) * self.pixel_spacing_mm[0],
                (uv[..., 1] - self.centre_px[1]) * self.pixel_spacing_mm[1])

    def _px(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        return np.stack([x_mm / self.pixel_spacing_mm[0] + self.centre_px[0],
                         y_mm / self.pixel_spacing_mm[1] + self.centre_px[1]], -1)

    def undistort(self, image_uv_px: np.ndarray) -> np.ndarray:
        """Image pixel positions (..., 2) -> the ideal (pinhole) positions whose rays show there (..., 2)."""
        if self.k_per_mm2 == 0.0:
            return np.array(image_uv_px, float)
        x, y = self._mm(image_uv_px)
        s = 1.0 - self.k_per_mm2 * (x * x + y * y)
        return self._px(x * s, y * s)

    def distort(self, ideal_uv_px: np.ndarray) -> np.ndarray:
        """Ideal positions (..., 2) (``project`` with P) -> where the image shows them (..., 2): ``d' = d / (1 -
        k |d'|^2)`` by fixed-point iteration, which contracts while 2 k |d'|^2 < 1 (an intensifier's k |d'|^2 is
        a few per cent)."""
        if self.k_per_mm2 == 0.0:
            return np.array(ideal_uv_px, float)
        x, y = self._mm(ideal_uv_px)
        xd, yd = x.copy(), y.copy()
        for _ in range(30):
            s = 1.0 - self.k_per_mm2 * (xd * xd + yd * yd)
            xd, yd = x / s, y / s
        return self._px(xd, yd)
