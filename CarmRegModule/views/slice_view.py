"""CT slice views (axial, coronal, sagittal) resliced in the LPS patient frame.

Each view is a plane spanned by two orthonormal LPS directions ``axis_u`` (screen right) and ``axis_v``
(screen down) at a depth ``d`` along ``normal``; scene coordinates are millimetres ``x = axis_u . p``,
``y = axis_v . p``, so a scene point maps back to ``p = x axis_u + y axis_v + d normal`` (LPS mm). The CT is
sampled there trilinearly through ``lps_to_ijk``: oblique volumes are shown in true anatomical planes.

Radiological display: axial seen from the feet (patient Right on screen left, Anterior up), coronal seen
from the front (Right on the left, Superior up), sagittal with Anterior on the left and Superior up.
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore, QtGui

from carmreg.logic.geometry.volume import Volume

from ..qt_common import SELECTED_COLOR
from .image_canvas import ImageCanvas

ORIENTATIONS = {
    # name: (axis_u, axis_v, normal, edge labels left/right/top/bottom)
    "axial": ((1, 0, 0), (0, 1, 0), (0, 0, 1), ("R", "L", "A", "P")),
    "coronal": ((1, 0, 0), (0, 0, -1), (0, -1, 0), ("R", "L", "S", "I")),
    "sagittal": ((0, 1, 0), (0, 0, -1), (-1, 0, 0), ("A", "P", "S", "I")),
}
MAX_SLICE_PX = 640
NEAR_MM = 15.0
WINDOW_PRESETS = {"Bone": (1800.0, 400.0), "Soft tissue": (400.0, 40.0), "Lung": (1500.0, -600.0)}


class SliceGeometry:
    """Plane sampling of one orientation over a volume (see module docstring)."""

    def __init__(self, volume: Volume, orientation: str):
        axis_u, axis_v, normal, self.edges = ORIENTATIONS[orientation]
        self.axis_u, self.axis_v, self.normal = (np.asarray(a, float) for a in (axis_u, axis_v, normal))
        self.volume = volume
        corners = volume.corners_lps_mm()
        proj = corners @ np.stack([self.axis_u, self.axis_v, self.normal], 1)
        self.lo, self.hi = proj.min(0), proj.max(0)
        spacing = float(max(volume.spacing_mm.min(), 0.25))
        extent = float(max(self.hi[0] - self.lo[0], self.hi[1] - self.lo[1]))
        self.pixel_mm = max(spacing, extent / MAX_SLICE_PX)
        self.cols = int(np.ceil((self.hi[0] - self.lo[0]) / self.pixel_mm))
        self.rows = int(np.ceil((self.hi[1] - self.lo[1]) / self.pixel_mm))
        self.origin = (self.lo[0] + self.pixel_mm / 2, self.lo[1] + self.pixel_mm / 2)
        rows_ijk = volume.lps_to_ijk[:3, :3] @ self.normal
        self.step_mm = float(1.0 / max(np.abs(rows_ijk).max(), 1e-9))

    def sample(self, depth_mm: float) -> np.ndarray:
        """HU image (rows, cols) float32 of the plane at ``depth_mm``; -1024 outside the CT."""
        from scipy import ndimage

        xs = self.origin[0] + self.pixel_mm * np.arange(self.cols)
        ys = self.origin[1] + self.pixel_mm * np.arange(self.rows)
        a = self.volume.lps_to_ijk
        base = a[:3, :3] @ (self.normal * depth_mm) + a[:3, 3]
        du, dv = a[:3, :3] @ self.axis_u, a[:3, :3] @ self.axis_v
        ijk = (base[:, None, None] + du[:, None, None] * xs[None, None, :]
               + dv[:, None, None] * ys[None, :, None]).astype(np.float32)
        return ndimage.map_coordinates(self.volume.hu, ijk, order=1, mode="constant", cval=-1024.0,
                                       prefilter=False, output=np.float32)

    def to_lps(self, x: float, y: float, depth_mm: float) -> np.ndarray:
        return x * self.axis_u + y * self.axis_v + depth_mm * self.normal

    def from_lps(self, p: np.ndarray) -> tuple[float, float, float]:
        p = np.asarray(p, float)
        return float(p @ self.axis_u), float(p @ self.axis_v), float(p @ self.normal)


class SliceView(ImageCanvas):
    """One CT slice orientation with the CT centroid store's points."""

    depth_changed = QtCore.Signal(float)

    def __init__(self, orientation: str, store=None, parent=None):
        super().__init__(store, parent)
        self.orientation = orientation
        self.title = orientation.capitalize()
        self.placeholder = "Load a CT (File > Load CT... or Load sample case)"
        self.geometry_: SliceGeometry | None = None
        self.depth_mm = 0.0
        self.cursor_lps: np.ndarray | None = None
        self.setObjectName(f"slice_{orientation}")
        self.window, self.level = WINDOW_PRESETS["Bone"]

    def set_volume(self, volume: Volume | None) -> None:
        if volume is None:
            self.geometry_ = None
            self.set_image(None)
            return
        self.geometry_ = SliceGeometry(volume, self.orientation)
        self.depth_mm = float(volume.center_lps_mm() @ self.geometry_.normal)
        self._fitted_once = False
        self._reslice(keep_window=True)

    def set_depth(self, depth_mm: float) -> None:
        if self.geometry_ is None:
            return
        g = self.geometry_
        depth_mm = float(np.clip(depth_mm, g.lo[2], g.hi[2]))
        if abs(depth_mm - self.depth_mm) > 1e-6:
            self.depth_mm = depth_mm
            self._reslice(keep_window=True)
            self.depth_changed.emit(depth_mm)

    def scroll_slices(self, steps: float) -> None:
        if self.geometry_ is not None:
            self.set_depth(self.depth_mm + steps * self.geometry_.step_mm)

    def go_to(self, lps: np.ndarray) -> None:
        """Put the slice through ``lps`` and mark it with the crosshair."""
        self.cursor_lps = np.asarray(lps, float).copy()
        if self.geometry_ is not None:
            self.set_depth(self.geometry_.from_lps(lps)[2])
        self.viewport().update()

    def set_window_preset(self, name: str) -> None:
        self.set_window_level(*WINDOW_PRESETS[name])

    def _reslice(self, keep_window: bool) -> None:
        g = self.geometry_
        self.set_image(g.sample(self.depth_mm), (g.pixel_mm, g.pixel_mm), g.origin, keep_window=keep_window)
        self._data_range = (-1024.0, 3000.0)

    # ------------------------------------------------------------------------------------- mapping
    def scene_to_position(self, scene: QtCore.QPointF) -> np.ndarray | None:
        if self.geometry_ is None or not self.image_rect().contains(scene):
            return None
        return self.geometry_.to_lps(scene.x(), scene.y(), self.depth_mm)

    def position_to_scene(self, position: np.ndarray):
        if self.geometry_ is None:
            return None
        x, y, depth = self.geometry_.from_lps(position)
        distance = abs(depth - self.depth_mm)
        if distance <= 0.5 * self.geometry_.step_mm + 0.25:
            return x, y, 1.0
        if distance <= NEAR_MM:
            return x, y, 0.35
        return None

    def describe(self, scene: QtCore.QPointF) -> str:
        position = self.scene_to_position(scene)
        if position is None:
            return ""
        hu = self.value_at(scene)
        return (f"{self.title}  LPS ({position[0]:.1f}, {position[1]:.1f}, {position[2]:.1f}) mm"
                + (f"   {hu:.0f} HU" if hu is not None else ""))

    # ------------------------------------------------------------------------------------- interaction
    def wheelEvent(self, event: QtGui.QWheelEvent) -> None:
        steps = event.angleDelta().y() / 120.0
        if event.modifiers() & QtCore.Qt.KeyboardModifier.ControlModifier:
            super().wheelEvent(event)
            return
        if steps:
            self.scroll_slices(np.sign(steps) * max(1, round(abs(steps))))
        event.accept()

    def keyPressEvent(self, event: QtGui.QKeyEvent) -> None:
        key = event.key()
        steps = {QtCore.Qt.Key.Key_Up: 1, QtCore.Qt.Key.Key_Down: -1, QtCore.Qt.Key.Key_PageUp: 10,
                 QtCore.Qt.Key.Key_PageDown: -10}.get(key)
        if steps is not None:
            self.scroll_slices(steps)
        else:
            super().keyPressEvent(event)

    # ------------------------------------------------------------------------------------- painting
    def corner_text(self) -> dict[str, str]:
        texts = super().corner_text()
        if self.geometry_ is not None:
            left, right, top, bottom = self.geometry_.edges
            texts.update(left=left, right=right, top=top, bottom=bottom)
            # the slice position as the LPS coordinate it fixes (the tables are in LPS too, not RAS)
            k = int(np.argmax(np.abs(self.geometry_.normal)))
            coordinate = self.depth_mm * float(self.geometry_.normal[k])
            # one stacked corner (the bottom edge carries the orientation letter: nothing beside it)
            texts["tr"] = f"LPS {'xyz'[k]} {coordinate:+.1f} mm\nstep {self.geometry_.step_mm:.2f} mm\nzoom " \
                          f"{self.zoom_level():.2f}"
            texts["br"] = ""
        return texts

    def draw_scene_overlay(self, painter: QtGui.QPainter) -> None:
        if self.cursor_lps is None or self.geometry_ is None:
            return
        x, y, _ = self.geometry_.from_lps(self.cursor_lps)
        rect = self.image_rect()
        pen = QtGui.QPen(QtGui.QColor(SELECTED_COLOR), 0)
        pen.setCosmetic(True)
        pen.setStyle(QtCore.Qt.PenStyle.DashLine)
        color = pen.color()
        color.setAlpha(110)
        pen.setColor(color)
        painter.setPen(pen)
        painter.drawLine(QtCore.QPointF(rect.left(), y), QtCore.QPointF(rect.right(), y))
        painter.drawLine(QtCore.QPointF(x, rect.top()), QtCore.QPointF(x, rect.bottom()))
