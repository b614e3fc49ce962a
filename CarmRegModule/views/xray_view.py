"""The X-ray view: detector pixels as scene coordinates, so a scene point (x, y) is (u, v) = (column, row).

Pixel centres sit at integer (u, v); the image spans [-0.5, columns - 0.5] x [-0.5, rows - 0.5].

Clicks without a level name are drawn ``?1``, ``?2``, ... (top of the image first, ``PointStore.unnamed_numbers``).
After a registration that identified the levels, ``set_assigned`` adds the assigned name: ``?1 → T11`` (or
``T10 → T11`` when the image disagrees with a given name), coloured by how sure the identification is.
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore, QtWidgets

from carmreg.logic.io.landmarks import LEVEL_NAMES
from carmreg.logic.report.style import status_ink

from .image_canvas import ImageCanvas
from .markers import MarkerSpec

ARROW = "\u2192"


class XrayView(ImageCanvas):
    """The intraoperative image with the X-ray centroid store's points."""

    def __init__(self, store=None, parent=None):
        super().__init__(store, parent)
        self.title = "X-ray"
        self.placeholder = "Load an X-ray (File > Load X-ray... or Load sample case)"
        self.setObjectName("xray_view")
        self.pixel_spacing_mm: tuple[float, float] | None = None
        self.assigned: dict[int, str] = {}   # point id -> level assigned by the registration
        self.assigned_status: str | None = None

    # ------------------------------------------------------------------------------------- level names
    def set_assigned(self, assigned: dict[int, str], status: str | None = None) -> None:
        """Show the registration's level for each click ({point id: level}); {} clears."""
        self.assigned, self.assigned_status = dict(assigned), status
        self.refresh_markers()

    def marker_text(self, point_id: int) -> str:
        """``T11``, ``?1``, ``?1 → T11`` or ``T10 → T11`` (given name, then the assigned one if it differs)."""
        point = self.store.get(point_id)
        shown = self.store.display_name(point_id)
        assigned = self.assigned.get(point_id)
        return shown if not assigned or assigned == point.label else f"{shown} {ARROW} {assigned}"

    def marker_specs(self) -> list[MarkerSpec]:
        specs = super().marker_specs()
        for spec in specs:
            spec.text = self.marker_text(spec.key)
            assigned = self.assigned.get(spec.key)
            if assigned and assigned != self.store.get(spec.key).label and spec.style != "selected":
                spec.color = status_ink(self.assigned_status) if self.assigned_status else None
        return specs

    def _place(self, position: np.ndarray) -> None:
        if self.store.naming:
            super()._place(position)
            return
        point_id = self.store.place(position)
        self.point_activated.emit(np.asarray(position, float).copy())
        self.status_message.emit(f"Unnamed click {self.store.display_name(point_id)} placed on the X-ray "
                                 f"({self.store.unnamed_count()} unnamed); CarmReg identifies the levels")

    def _point_menu(self, point_id, global_pos: QtCore.QPoint) -> None:
        point = self.store.get(point_id)
        menu = QtWidgets.QMenu(self)
        rename = menu.addMenu("Rename to")
        used = set(self.store.labels())
        assigned = self.assigned.get(point_id)
        if assigned and assigned != point.label:
            menu.addAction(f"Name it {assigned} (identified)", lambda: self._rename(point_id, assigned))
        for name in LEVEL_NAMES:
            action = rename.addAction(name)
            action.setEnabled(name not in used or name == point.label)
            action.triggered.connect(lambda _=False, n=name: self._rename(point_id, n))
        if point.label:
            menu.addAction("Clear the name (unnamed click)", lambda: self._rename(point_id, None))
        menu.addSeparator()
        menu.addAction("Delete point", lambda: self.store.remove(point_id))
        menu.exec(global_pos)

    def set_pixels(self, pixels: np.ndarray | None) -> None:
        """Show the X-ray (pixels[row, column], as the window turns it: ``set_xray_orientation``) with the default
        window (``default_range``)."""
        from carmreg.logic.image.field import field_mask

        self._fitted_once = False
        # the exposed field: collimator, blanked corners and burnt-in text outside it
        self._field = None if pixels is None else field_mask(pixels)
        self.set_image(None if pixels is None else np.asarray(pixels, np.float32))

    def default_range(self) -> tuple[float, float]:
        """The X-ray's display range (``image.field.display_range``): the exposed field's 1st-99th percentiles,
        clipped pixels (burned-out air, zero-filled metal) left out, so neither the collimator's black nor
        saturated air flattens the bone."""
        from carmreg.logic.image.field import display_range

        return display_range(self._image, getattr(self, "_field", None))

    def drag_range(self) -> tuple[float, float]:
        """A right-drag moves the window over the whole stored range (min to max)."""
        lo, hi = float(np.nanmin(self._image)), float(np.nanmax(self._image))
        return lo, hi if hi > lo else lo + 1.0

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
