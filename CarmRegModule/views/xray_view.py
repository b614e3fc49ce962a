"""The X-ray view: detector pixels as scene coordinates, so a scene point (x, y) is (u, v) = (column, row).

Pixel centres sit at integer (u, v); the image spans [-0.5, columns - 0.5] x [-0.5, rows - 0.5].
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore

from ..qt_common import robust_range
from .image_canvas import ImageCanvas


class XrayView(ImageCanvas):
    """The intraoperative image with the X-ray centroid store's points."""

    def __init__(self, store=None, parent=None):
        super().__init__(store, parent)
        self.title = "X-ray"
        self.placeholder = "Load an X-ray (File > Load X-ray... or Load sample case)"
        self.setObjectName("xray_view")
        self.pixel_spacing_mm: tuple[float, float] | None = None

    def set_pixels(self, pixels: np.ndarray | None) -> None:
        self._fitted_once = False
        self._field = None
        self.set_image(None if pixels is None else np.asarray(pixels, np.float32))
        if pixels is not None:
            from Logic.xray_prep import field_mask

            lo, hi = float(np.nanmin(pixels)), float(np.nanmax(pixels))
            self._data_range = (lo, hi if hi > lo else lo + 1.0)
            self._field = field_mask(pixels)  # the exposed field: burnt-in text and collimator left out
            self.auto_window()

    def auto_window(self) -> None:
        """Window/level from the 1st-99.5th percentiles inside the exposed field."""
        if self._image is None:
            return
        field = getattr(self, "_field", None)
        values = self._image[field] if field is not None and field.any() else self._image
        lo, hi = robust_range(values)
        self.set_window_level(hi - lo, (hi + lo) / 2)

    def size_px(self) -> tuple[int, int] | None:
        if self._image is None:
            return None
        rows, cols = self._image.shape[:2]
        return cols, rows

    def scene_to_position(self, scene: QtCore.QPointF) -> np.ndarray | None:
        size = self.size_px()
        if size is None:
            return None
        u, v = scene.x(), scene.y()
        if not (-0.5 <= u <= size[0] - 0.5 and -0.5 <= v <= size[1] - 0.5):
            return None
        return np.array([u, v])

    def position_to_scene(self, position: np.ndarray):
        return float(position[0]), float(position[1]), 1.0

    def describe(self, scene: QtCore.QPointF) -> str:
        uv = self.scene_to_position(scene)
        if uv is None:
            return ""
        value = self.value_at(scene)
        text = f"X-ray  (u, v) = ({uv[0]:.1f}, {uv[1]:.1f}) px"
        if self.pixel_spacing_mm:
            text += f"   detector ({uv[0] * self.pixel_spacing_mm[0]:.1f}, {uv[1] * self.pixel_spacing_mm[1]:.1f}) mm"
        return text + (f"   value {value:.0f}" if value is not None else "")

    def corner_text(self) -> dict[str, str]:
        texts = super().corner_text()
        size = self.size_px()
        if size is not None:
            texts["tr"] = f"{size[0]} x {size[1]} px"
            texts["left"], texts["right"], texts["top"], texts["bottom"] = "R", "L", "S", "I"
        return texts
