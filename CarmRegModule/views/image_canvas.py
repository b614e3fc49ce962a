"""A 2D image view drawn with plain Qt (works offscreen): zoom, pan, window/level, named point markers.

Scene coordinates: the image pixel (column j, row i) has its centre at scene
``(origin_x + j * spacing_x, origin_y + i * spacing_y)``; subclasses choose the units (mm in a CT slice
plane, detector px for the X-ray). Markers keep a constant size on screen.

Mouse (when a PointStore is attached):
- left click on empty image, place mode on: place the pending level (or move it there if already placed);
- left drag on a point: move it (one undo step); left drag elsewhere (place mode off) or middle drag: pan;
- right drag: window/level (horizontal = window, vertical = level); right click on a point: rename/delete;
- wheel: zoom about the cursor (slice views scroll slices instead, Ctrl+wheel zooms);
- Delete/Backspace: delete the selected point; Escape: clear the selection; F or Home: fit the image.
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore, QtGui, QtWidgets

from carmreg.logic.io.landmarks import LEVEL_NAMES

from ..qt_common import gray_qimage, rgb_qimage, robust_range, window_to_uint8
from .markers import MarkerItem, MarkerSpec

HIT_RADIUS_PX = 10.0


class ImageCanvas(QtWidgets.QGraphicsView):
    """Base 2D view; subclasses map scene coordinates to point positions (see module docstring)."""

    hover_text = QtCore.Signal(str)
    status_message = QtCore.Signal(str)
    point_activated = QtCore.Signal(object)  # position of a placed/selected point
    window_changed = QtCore.Signal(float, float)  # window, level (image values)

    def __init__(self, store=None, parent=None):
        super().__init__(parent)
        self.store = store
        self.place_enabled = lambda: True
        self.setScene(QtWidgets.QGraphicsScene(self))
        self.setBackgroundBrush(QtGui.QColor(0, 0, 0))
        self.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        self.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.setVerticalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.setTransformationAnchor(QtWidgets.QGraphicsView.ViewportAnchor.NoAnchor)
        self.setResizeAnchor(QtWidgets.QGraphicsView.ViewportAnchor.AnchorViewCenter)
        self.setRenderHints(QtGui.QPainter.RenderHint.Antialiasing | QtGui.QPainter.RenderHint.SmoothPixmapTransform)
        self.setViewportUpdateMode(QtWidgets.QGraphicsView.ViewportUpdateMode.FullViewportUpdate)
        self.setMouseTracking(True)
        self.setFocusPolicy(QtCore.Qt.FocusPolicy.StrongFocus)
        self.setMinimumSize(160, 160)
        self._pixmap_item = QtWidgets.QGraphicsPixmapItem()
        self._pixmap_item.setTransformationMode(QtCore.Qt.TransformationMode.SmoothTransformation)
        self.scene().addItem(self._pixmap_item)
        self._image: np.ndarray | None = None
        self._rgb = False
        self._spacing = (1.0, 1.0)
        self._origin = (0.0, 0.0)
        self.window, self.level, self.invert = 1.0, 0.5, False
        self._data_range = (0.0, 1.0)
        self._markers: dict[object, MarkerItem] = {}
        self._drag: dict | None = None
        self._fitted_once = False
        self.placeholder = "No image loaded"
        self.title = ""
        if store is not None:
            store.changed.connect(self.refresh_markers)
            store.selection_changed.connect(lambda _id: self.refresh_markers())

    # ------------------------------------------------------------------------------------- image
    def has_image(self) -> bool:
        return self._image is not None

    def set_image(self, image: np.ndarray | None, spacing=(1.0, 1.0), origin=(0.0, 0.0),
                  keep_window: bool = False) -> None:
        """Show a (rows, cols) float image, or a (rows, cols, 3) uint8 RGB image."""
        self._image = None if image is None else np.asarray(image)
        self._rgb = self._image is not None and self._image.ndim == 3
        self._spacing, self._origin = (float(spacing[0]), float(spacing[1])), (float(origin[0]), float(origin[1]))
        if self._image is not None and not self._rgb and not keep_window:
            lo, hi = self.default_range()
            self._data_range = self.drag_range()
            self.window, self.level = hi - lo, (hi + lo) / 2.0
        self._render()
        if self._image is not None and not self._rgb and not keep_window:
            self.window_changed.emit(self.window, self.level)
        if self._image is not None and not self._fitted_once:
            self._fitted_once = True
            QtCore.QTimer.singleShot(0, self.fit)
        self.refresh_markers()

    def image_rect(self) -> QtCore.QRectF:
        if self._image is None:
            return QtCore.QRectF()
        rows, cols = self._image.shape[:2]
        sx, sy = self._spacing
        return QtCore.QRectF(self._origin[0] - sx / 2, self._origin[1] - sy / 2, cols * sx, rows * sy)

    def set_window_level(self, window: float, level: float) -> None:
        self.window, self.level = max(float(window), 1e-6), float(level)
        self._render()
        self.window_changed.emit(self.window, self.level)

    def default_range(self) -> tuple[float, float]:
        """(low, high) image values of the default window: the image's 1st-99.5th percentiles (subclasses
        choose better, e.g. the X-ray's exposed field)."""
        return robust_range(self._image)

    def drag_range(self) -> tuple[float, float]:
        """The value span a right-drag across 400 screen px moves the window or level by (default: the
        default window's range)."""
        return self.default_range()

    def auto_window(self) -> None:
        """Back to the default window (``default_range``)."""
        if self._image is not None and not self._rgb:
            lo, hi = self.default_range()
            self.set_window_level(hi - lo, (hi + lo) / 2)

    def set_invert(self, invert: bool) -> None:
        self.invert = bool(invert)
        self._render()

    def _render(self) -> None:
        if self._image is None:
            self._pixmap_item.setPixmap(QtGui.QPixmap())
            self.viewport().update()
            return
        if self._rgb:
            qimage = rgb_qimage(self._image)
        else:
            qimage = gray_qimage(window_to_uint8(self._image, self.window, self.level, self.invert))
        self._pixmap_item.setPixmap(QtGui.QPixmap.fromImage(qimage))
        sx, sy = self._spacing
        self._pixmap_item.setTransform(QtGui.QTransform.fromScale(sx, sy))
        self._pixmap_item.setPos(self._origin[0] - sx / 2, self._origin[1] - sy / 2)
        rect = self.image_rect()
        margin = max(rect.width(), rect.height()) * 4
        self.setSceneRect(rect.adjusted(-margin, -margin, margin, margin))
        self.viewport().update()

    def fit(self) -> None:
        """Show the whole image; the view then keeps fitting on resize until the user zooms or pans."""
        self._auto_fit = True
        rect = self.image_rect()
        if rect.isEmpty():
            return
        self.resetTransform()
        self.fitInView(rect, QtCore.Qt.AspectRatioMode.KeepAspectRatio)
        self.centerOn(rect.center())

    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        if getattr(self, "_auto_fit", True) and self._image is not None:
            self.fit()

    def zoom(self, factor: float, anchor: QtCore.QPoint | None = None) -> None:
        """Scale by ``factor`` keeping the scene point under ``anchor`` (viewport px; default: the view's
        centre) where it is on screen. Done explicitly, not with Qt's AnchorUnderMouse: that anchor uses the
        last mouse position Qt saw, which is stale in a view that handles mouse moves itself."""
        self._auto_fit = False
        if anchor is None:
            anchor = self.viewport().rect().center()
        before = self.mapToScene(anchor)
        old_anchor = self.transformationAnchor()
        self.setTransformationAnchor(QtWidgets.QGraphicsView.ViewportAnchor.NoAnchor)
        self.scale(factor, factor)
        self.setTransformationAnchor(old_anchor)
        self.keep_scene_point_at(before, anchor)

    def keep_scene_point_at(self, scene: QtCore.QPointF, anchor: QtCore.QPoint) -> None:
        """Scroll so that ``scene`` is drawn at viewport position ``anchor``."""
        after = self.mapFromScene(scene)
        h, v = self.horizontalScrollBar(), self.verticalScrollBar()
        h.setValue(h.value() + after.x() - anchor.x())
        v.setValue(v.value() + after.y() - anchor.y())

    def zoom_level(self) -> float:
        return float(self.transform().m11())

    def value_at(self, scene: QtCore.QPointF) -> float | None:
        """Image value under a scene point (nearest pixel), None outside."""
        if self._image is None or self._rgb:
            return None
        j = int(round((scene.x() - self._origin[0]) / self._spacing[0]))
        i = int(round((scene.y() - self._origin[1]) / self._spacing[1]))
        rows, cols = self._image.shape[:2]
        return float(self._image[i, j]) if 0 <= i < rows and 0 <= j < cols else None

    # ------------------------------------------------------------------------------------- markers
    def marker_specs(self) -> list[MarkerSpec]:
        """Markers to draw; the default draws the attached store's points."""
        if self.store is None:
            return []
        specs = []
        for point in self.store.points():
            placed = self.position_to_scene(point.position)
            if placed is None:
                continue
            x, y, alpha = placed
            style = "selected" if point.id == self.store.selected else "point"
            specs.append(MarkerSpec(point.id, x, y, point.label or "?", style, alpha))
        return specs

    def refresh_markers(self) -> None:
        specs = {s.key: s for s in self.marker_specs()} if self._image is not None else {}
        for key in list(self._markers):
            if key not in specs:
                self.scene().removeItem(self._markers.pop(key))
        for key, spec in specs.items():
            if key in self._markers:
                self._markers[key].update_spec(spec)
            else:
                item = MarkerItem(spec)
                self._markers[key] = item
                self.scene().addItem(item)
        self.viewport().update()

    def declutter(self) -> list[object]:
        """Hide the labels that would overprint a label already placed on screen, the most important first
        (selected, then in-plane, then fitted/clicked order); returns the keys whose label is hidden. Their
        glyphs stay, and hovering or zooming in shows the name again."""
        placed: list[QtCore.QRectF] = []
        hidden = []
        order = sorted(self._markers.items(), key=lambda kv: (kv[1].spec.style != "selected", -kv[1].spec.alpha))
        for key, item in order:
            box = item.label_rect()
            if box.isEmpty():
                continue
            centre = self.mapFromScene(QtCore.QPointF(item.spec.x, item.spec.y))
            box = box.translated(centre.x(), centre.y())
            item.show_text = not any(box.intersects(other) for other in placed)
            if item.show_text:
                placed.append(box)
            else:
                hidden.append(key)
        return hidden

    def paintEvent(self, event) -> None:
        self.declutter()
        super().paintEvent(event)

    def markers(self) -> dict[object, MarkerSpec]:
        return {k: item.spec for k, item in self._markers.items()}

    def hit_point(self, view_pos: QtCore.QPoint) -> object | None:
        """Key of the in-plane marker nearest to a viewport position within HIT_RADIUS_PX."""
        best, best_d = None, HIT_RADIUS_PX
        for key, item in self._markers.items():
            if item.spec.alpha < 0.6:
                continue
            p = self.mapFromScene(QtCore.QPointF(item.spec.x, item.spec.y))
            d = float(np.hypot(p.x() - view_pos.x(), p.y() - view_pos.y()))
            if d <= best_d:
                best, best_d = key, d
        return best

    # subclass hooks ------------------------------------------------------------------------
    def scene_to_position(self, scene: QtCore.QPointF) -> np.ndarray | None:
        """Point position (LPS mm or uv px) under a scene point, or None outside the image."""
        return None

    def position_to_scene(self, position: np.ndarray) -> tuple[float, float, float] | None:
        """(x, y, alpha) of a point in this view, or None if not shown."""
        return None

    def describe(self, scene: QtCore.QPointF) -> str:
        return ""

    # ------------------------------------------------------------------------------------- mouse
    def mousePressEvent(self, event: QtGui.QMouseEvent) -> None:
        pos = event.position().toPoint()
        button = event.button()
        hit = self.hit_point(pos) if self.store is not None else None
        if button == QtCore.Qt.MouseButton.LeftButton and hit is not None:
            point = self.store.get(hit)
            self.store.select(hit)
            self.point_activated.emit(point.position.copy())
            self._drag = {"kind": "move", "id": hit, "start": point.position.copy(), "moved": False}
        elif button == QtCore.Qt.MouseButton.LeftButton and self._can_place(event):
            position = self.scene_to_position(self.mapToScene(pos))
            if position is not None:
                self._place(position)
            else:
                self.status_message.emit("Click inside the image to place a point")
        elif button == QtCore.Qt.MouseButton.RightButton and hit is not None:
            self.store.select(hit)
            self._point_menu(hit, event.globalPosition().toPoint())
        elif button == QtCore.Qt.MouseButton.RightButton and self._image is not None and not self._rgb:
            self._drag = {"kind": "window", "origin": pos, "wl": (self.window, self.level)}
        elif button in (QtCore.Qt.MouseButton.LeftButton, QtCore.Qt.MouseButton.MiddleButton):
            self._drag = {"kind": "pan", "last": pos}
            self.viewport().setCursor(QtCore.Qt.CursorShape.ClosedHandCursor)
        event.accept()

    def mouseMoveEvent(self, event: QtGui.QMouseEvent) -> None:
        pos = event.position().toPoint()
        scene = self.mapToScene(pos)
        drag = self._drag
        if drag and drag["kind"] == "move":
            position = self.scene_to_position(scene)
            if position is not None:
                drag["moved"] = True
                self.store.move_live(drag["id"], position)
        elif drag and drag["kind"] == "pan":
            self._auto_fit = False
            delta = pos - drag["last"]
            drag["last"] = pos
            self.horizontalScrollBar().setValue(self.horizontalScrollBar().value() - delta.x())
            self.verticalScrollBar().setValue(self.verticalScrollBar().value() - delta.y())
        elif drag and drag["kind"] == "window":
            w0, l0 = drag["wl"]
            span = max(self._data_range[1] - self._data_range[0], 1e-6)
            dx, dy = pos.x() - drag["origin"].x(), pos.y() - drag["origin"].y()
            self.set_window_level(max(w0 + dx * span / 400.0, span / 1000.0), l0 - dy * span / 400.0)
        text = self.describe(scene)
        if text:
            self.hover_text.emit(text)
        event.accept()

    def mouseReleaseEvent(self, event: QtGui.QMouseEvent) -> None:
        drag, self._drag = self._drag, None
        if drag and drag["kind"] == "move" and drag["moved"]:
            point = self.store.get(drag["id"])
            if point is not None:
                self.store.move(drag["id"], point.position.copy(), drag["start"])
                self.point_activated.emit(point.position.copy())
        self.viewport().setCursor(self._idle_cursor())
        event.accept()

    def mouseDoubleClickEvent(self, event: QtGui.QMouseEvent) -> None:
        event.accept()

    def wheelEvent(self, event: QtGui.QWheelEvent) -> None:
        steps = event.angleDelta().y() / 120.0
        if steps:
            self.zoom(1.15 ** steps, event.position().toPoint())
        event.accept()

    def keyPressEvent(self, event: QtGui.QKeyEvent) -> None:
        key = event.key()
        if key in (QtCore.Qt.Key.Key_Delete, QtCore.Qt.Key.Key_Backspace) and self.store is not None:
            self.store.remove_selected()
        elif key == QtCore.Qt.Key.Key_Escape and self.store is not None:
            self.store.select(None)
        elif key in (QtCore.Qt.Key.Key_F, QtCore.Qt.Key.Key_Home):
            self.fit()
        elif key in (QtCore.Qt.Key.Key_Plus, QtCore.Qt.Key.Key_Equal):
            self.zoom(1.25)
        elif key == QtCore.Qt.Key.Key_Minus:
            self.zoom(0.8)
        else:
            super().keyPressEvent(event)

    def enterEvent(self, event) -> None:
        self.viewport().setCursor(self._idle_cursor())
        super().enterEvent(event)

    def _idle_cursor(self) -> QtCore.Qt.CursorShape:
        return QtCore.Qt.CursorShape.CrossCursor if self._can_place(None) else QtCore.Qt.CursorShape.ArrowCursor

    def _can_place(self, event) -> bool:
        if self.store is None or self._image is None or not self.place_enabled():
            return False
        return event is None or not (event.modifiers() & QtCore.Qt.KeyboardModifier.ShiftModifier)

    def _place(self, position: np.ndarray) -> None:
        level = self.store.pending_level
        existed = self.store.find(level) is not None
        self.store.place(position)
        self.point_activated.emit(np.asarray(position, float).copy())
        self.status_message.emit(f"{level} {'moved' if existed else 'placed'} on the {self.store.name}; "
                                f"next level: {self.store.pending_level}")

    def _point_menu(self, point_id, global_pos: QtCore.QPoint) -> None:
        point = self.store.get(point_id)
        menu = QtWidgets.QMenu(self)
        rename = menu.addMenu("Rename to")
        used = set(self.store.labels())
        for name in LEVEL_NAMES:
            action = rename.addAction(name)
            action.setEnabled(name not in used or name == point.label)
            action.triggered.connect(lambda _=False, n=name: self._rename(point_id, n))
        menu.addSeparator()
        menu.addAction("Delete point", lambda: self.store.remove(point_id))
        menu.exec(global_pos)

    def _rename(self, point_id, name: str) -> None:
        try:
            self.store.rename(point_id, name)
        except Exception as exc:  # noqa: BLE001 - shown to the user, nothing to recover
            self.status_message.emit(str(exc))

    # ------------------------------------------------------------------------------------- painting
    def drawForeground(self, painter: QtGui.QPainter, rect: QtCore.QRectF) -> None:
        super().drawForeground(painter, rect)
        self.draw_scene_overlay(painter)
        painter.save()
        painter.resetTransform()
        view = QtCore.QRectF(self.viewport().rect())
        painter.setRenderHint(QtGui.QPainter.RenderHint.TextAntialiasing, True)
        if self._image is None:
            painter.setPen(QtGui.QColor(150, 155, 160))
            font = painter.font()
            font.setPointSizeF(11)
            painter.setFont(font)
            painter.drawText(view, QtCore.Qt.AlignmentFlag.AlignCenter, self.placeholder)
        else:
            self.draw_annotations(painter, view)
        painter.restore()

    def draw_scene_overlay(self, painter: QtGui.QPainter) -> None:
        """Hook: draw in scene coordinates (crosshairs)."""

    def corner_text(self) -> dict[str, str]:
        """Hook: text per corner ('tl', 'tr', 'bl', 'br') and edge ('left', 'right', 'top', 'bottom')."""
        texts = {"tl": self.title}
        if self._image is not None and not self._rgb:
            texts["bl"] = f"W {self.window:.0f}  L {self.level:.0f}" + ("  inverted" if self.invert else "")
        texts["br"] = f"zoom {self.zoom_level():.2f}"
        return texts

    def draw_annotations(self, painter: QtGui.QPainter, view: QtCore.QRectF) -> None:
        font = painter.font()
        font.setPointSizeF(9.5)
        painter.setFont(font)
        align = QtCore.Qt.AlignmentFlag
        places = {"tl": align.AlignLeft | align.AlignTop, "tr": align.AlignRight | align.AlignTop,
                  "bl": align.AlignLeft | align.AlignBottom, "br": align.AlignRight | align.AlignBottom,
                  "left": align.AlignLeft | align.AlignVCenter, "right": align.AlignRight | align.AlignVCenter,
                  "top": align.AlignHCenter | align.AlignTop, "bottom": align.AlignHCenter | align.AlignBottom}
        inner = view.adjusted(6, 4, -6, -4)
        for where, text in self.corner_text().items():
            if not text:
                continue
            bold = where in ("left", "right", "top", "bottom")
            font.setBold(bold)
            font.setPointSizeF(11 if bold else 9.5)
            painter.setFont(font)
            if not bold:  # a dark box keeps the text legible over burnt-in image text
                box = painter.boundingRect(inner, places[where], text).adjusted(-3, -1, 3, 1)
                painter.setPen(QtCore.Qt.PenStyle.NoPen)
                painter.setBrush(QtGui.QColor(0, 0, 0, 170))
                painter.drawRoundedRect(box, 3, 3)
                painter.setBrush(QtCore.Qt.BrushStyle.NoBrush)
            painter.setPen(QtGui.QColor(0, 0, 0))
            painter.drawText(inner.translated(1, 1), places[where], text)
            painter.setPen(QtGui.QColor(255, 214, 102) if bold else QtGui.QColor(220, 224, 228))
            painter.drawText(inner, places[where], text)
