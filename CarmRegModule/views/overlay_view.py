"""The overlay view: X-ray and DRR at the found pose, plus every CT-labelled level projected with its name.

Scene coordinates are detector pixels (u, v) as in the X-ray view. Marker styles:
- filled circle (green): a level used by the fit (labelled on CT and X-ray), text "T12  1.8 mm" = its PDE;
- ring (yellow): a CT-labelled level not used by the fit: where the registration says it is;
- cross (red): the user's click on the X-ray, so the distance to the projection is visible.
(The same colours as the overlay.png that ``Logic.report`` writes.)
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore, QtGui

from .. import overlay_images
from ..qt_common import CHECK_COLOR, CLICK_COLOR, FITTED_COLOR
from .image_canvas import ImageCanvas, MarkerSpec


class OverlayView(ImageCanvas):
    """Blend / checkerboard / edge composite with projected, named centroids."""

    def __init__(self, parent=None):
        super().__init__(None, parent)
        self.title = "Overlay"
        self.placeholder = "Run the registration to see the X-ray and DRR overlay"
        self.setObjectName("overlay_view")
        self.mode, self.alpha, self.tiles = "blend", 0.5, 8
        self._xray01: np.ndarray | None = None
        self._drr01: np.ndarray | None = None
        self.levels: list[dict] = []
        self.clicks: dict[str, np.ndarray] = {}
        self.show_names = True
        self.summary = ""

    def set_result(self, xray_pixels: np.ndarray, bone_dark: bool, drr_line_integral: np.ndarray | None,
                   levels: list[dict], clicks: dict[str, np.ndarray], summary: str = "") -> None:
        from carmreg.logic.image.field import field_mask

        mask = field_mask(xray_pixels)  # the exposed (collimated) field, as the logic sees it
        self._xray01 = overlay_images.xray_bone_bright(xray_pixels, bone_dark, mask)
        self._drr01 = (overlay_images.normalise(drr_line_integral, mask) if drr_line_integral is not None
                       else np.zeros_like(self._xray01))
        self.levels, self.clicks, self.summary = list(levels), dict(clicks), summary
        self._fitted_once = False
        self._recomposite()

    def clear(self) -> None:
        self._xray01 = self._drr01 = None
        self.levels, self.clicks, self.summary = [], {}, ""
        self.set_image(None)

    def set_mode(self, mode: str) -> None:
        self.mode = mode
        self._recomposite()

    def set_alpha(self, alpha: float) -> None:
        self.alpha = float(alpha)
        self._recomposite()

    def set_tiles(self, tiles: int) -> None:
        self.tiles = int(tiles)
        self._recomposite()

    def _recomposite(self) -> None:
        if self._xray01 is None:
            return
        rgb = overlay_images.composite(self.mode, self._xray01, self._drr01, self.alpha, self.tiles)
        self.set_image(rgb)

    def composite_rgb(self) -> np.ndarray | None:
        return None if self._image is None else self._image.copy()

    # ------------------------------------------------------------------------------------- markers
    def marker_specs(self) -> list[MarkerSpec]:
        specs = []
        for level in self.levels:
            if not level.get("in_image", True):
                continue  # listed in the corner text instead
            u, v = level["uv_px"]
            fitted = bool(level.get("fitted"))
            pde = level.get("pde_mm")
            text = level["label"] + (f"  {pde:.1f} mm" if pde is not None else "") if self.show_names else ""
            specs.append(MarkerSpec(("level", level["label"]), u, v, text, "fitted" if fitted else "check",
                                    1.0, FITTED_COLOR if fitted else CHECK_COLOR))
        for label, uv in self.clicks.items():
            specs.append(MarkerSpec(("click", label), float(uv[0]), float(uv[1]), "", "click", 0.9, CLICK_COLOR))
        return specs

    def level_names(self) -> list[str]:
        """Names of the projected levels currently drawn (what the user reads on the overlay)."""
        return [spec.key[1] for spec in self.markers().values() if spec.key[0] == "level"]

    def describe(self, scene: QtCore.QPointF) -> str:
        if self._image is None:
            return ""
        return f"Overlay  (u, v) = ({scene.x():.1f}, {scene.y():.1f}) px"

    def corner_text(self) -> dict[str, str]:
        texts = super().corner_text()
        if self._image is not None:
            mode = {"blend": f"blend  X-ray {100 - self.alpha * 100:.0f} % / DRR {self.alpha * 100:.0f} %",
                    "checkerboard": f"checkerboard  {self.tiles} tiles",
                    "edges": "DRR bone edges on X-ray"}[self.mode]
            texts["tl"] = f"Overlay: {mode}"
            texts["tr"] = self.summary
            outside = [lv["label"] for lv in self.levels if not lv.get("in_image", True)]
            texts["bl"] = ""
            if outside:
                texts["tl"] += f"\nprojected outside the image: {', '.join(outside)}"
        return texts

    def draw_annotations(self, painter: QtGui.QPainter, view: QtCore.QRectF) -> None:
        super().draw_annotations(painter, view)
        entries = [("fitted", FITTED_COLOR, "fitted level (PDE to click)"),
                   ("check", CHECK_COLOR, "CT level not fitted (projected)"),
                   ("click", CLICK_COLOR, "X-ray click")]
        font = painter.font()
        font.setBold(False)
        font.setPointSizeF(9.0)
        painter.setFont(font)
        box = QtCore.QRectF(view.left() + 8, view.bottom() - 70, 230, 62)
        painter.setPen(QtCore.Qt.PenStyle.NoPen)
        painter.setBrush(QtGui.QColor(0, 0, 0, 150))
        painter.drawRoundedRect(box, 4, 4)
        for row, (style, color, text) in enumerate(entries):
            y = box.top() + 12 + row * 18
            pen = QtGui.QPen(QtGui.QColor(color), 1.8)
            painter.setPen(pen)
            painter.setBrush(QtCore.Qt.BrushStyle.NoBrush)
            c = QtCore.QPointF(box.left() + 14, y)
            if style == "fitted":
                painter.setBrush(QtGui.QColor(color))
                painter.drawEllipse(c, 4, 4)
            elif style == "check":
                painter.drawEllipse(c, 5, 5)
            else:
                painter.drawLine(c + QtCore.QPointF(-6, 0), c + QtCore.QPointF(6, 0))
                painter.drawLine(c + QtCore.QPointF(0, -6), c + QtCore.QPointF(0, 6))
            painter.setPen(QtGui.QColor(230, 230, 230))
            painter.drawText(QtCore.QPointF(box.left() + 28, y + 4), text)
