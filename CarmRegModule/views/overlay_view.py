"""The overlay view: X-ray and DRR at the found pose, plus every CT-labelled level projected with its name.

Scene coordinates are detector pixels (u, v) as in the X-ray view. Marker styles:
- filled circle (green): a level used by the fit (labelled on CT and X-ray), text "T12  1.8 mm" = its PDE;
  red with a "?" ("T12?  1.8 mm") when the image contradicts the given level names;
- ring (yellow): a CT-labelled level not used by the fit: where the registration says it is;
- cross (red): the user's click on the X-ray, so the distance to the projection is visible.
The level answer (confirmed, proposed, ambiguous, contradicted, checks failed) is a coloured banner across the
top; the header under it gives the mPDE of the pose drawn (the final pose, not an intermediate stage's) and the
magnification. (The same colours and composite as the report page that ``Logic.report.page`` writes.)
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore, QtGui

from carmreg.logic.report import composite as overlay_images
from carmreg.logic.report.style import (
    CHECK_COLOUR,
    CLICK_COLOUR,
    FITTED_COLOUR,
    UNSURE_WORDS,
    level_marker,
    status_ink,
)

from .image_canvas import ImageCanvas
from .markers import MarkerSpec

LEGEND_HEIGHT_PX = 62.0


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
        self.banner: tuple[str, str, str] | None = None  # (headline, reason, colour) of the level answer
        self.status: str | None = None  # the level answer's status: the markers' style (style.level_marker)
        self.names_withheld = False  # the answer names no level (the X-ray refused): markers without names

    def set_result(self, xray_pixels: np.ndarray, bone_dark: bool, drr_line_integral: np.ndarray | None,
                   levels: list[dict], clicks: dict[str, np.ndarray], summary: str = "",
                   banner: tuple[str, str, str] | None = None, status: str | None = None,
                   names_withheld: bool = False, mask: np.ndarray | None = None) -> None:
        """``summary``: the header line (mPDE of the pose drawn, magnification); ``banner``: the level answer
        (headline, reason, colour) drawn across the top; ``status``: the level answer's status (ambiguous or
        contradicted: every name drawn with a "?", ``style.level_marker``); ``names_withheld``: the answer names
        no level (``style.names_shown``), so no name is drawn, whatever "Names" says; ``mask``: the exposed field
        the registration used (``RegistrationResult.field_mask``; default: found, ``image.field.field_mask``), as
        ``overlay.png`` and the report page take it."""
        from carmreg.logic.image.field import field_mask

        self.banner, self.status, self.names_withheld = banner, status, bool(names_withheld)

        if mask is None or np.shape(mask) != np.shape(xray_pixels):
            mask = field_mask(xray_pixels)
        self._xray01 = overlay_images.xray_bone_bright(xray_pixels, bone_dark, mask)
        self._drr01 = (overlay_images.normalise(drr_line_integral, mask) if drr_line_integral is not None
                       else np.zeros_like(self._xray01))
        self.levels, self.clicks, self.summary = list(levels), dict(clicks), summary
        self._fitted_once = False
        self._recomposite()

    def clear(self) -> None:
        self._xray01 = self._drr01 = None
        self.levels, self.clicks, self.summary, self.banner, self.status = [], {}, "", None, None
        self.names_withheld = False
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
            marker = level_marker(level, self.status,  # the report page's style
                                  self.show_names and not self.names_withheld)
            specs.append(MarkerSpec(("level", level["label"]), u, v, marker.text,
                                    "fitted" if marker.fitted else "check", 1.0, marker.colour))
        for label, uv in self.clicks.items():
            specs.append(MarkerSpec(("click", label), float(uv[0]), float(uv[1]), "", "click", 0.9, CLICK_COLOUR))
        return specs

    def level_names(self) -> list[str]:
        """Names of the projected levels currently drawn (what the user reads on the overlay)."""
        return [spec.key[1] for spec in self.markers().values() if spec.key[0] == "level"]

    def describe(self, scene: QtCore.QPointF) -> str:
        if self._image is None:
            return ""
        return f"Overlay  (u, v) = ({scene.x():.1f}, {scene.y():.1f}) px"

    def corner_text(self) -> dict[str, str]:
        """The header is stacked on the left (never two texts on one line, so nothing overprints when the
        view is narrow): the overlay mode, the mPDE of the pose drawn and magnification, levels outside."""
        texts = super().corner_text()
        if self._image is not None:
            mode = {"blend": f"blend  X-ray {100 - self.alpha * 100:.0f} % / DRR {self.alpha * 100:.0f} %",
                    "checkerboard": f"checkerboard  {self.tiles} tiles",
                    "edges": "DRR bone edges on X-ray"}[self.mode]
            lines = [f"Overlay: {mode}"] + ([self.summary] if self.summary else [])
            outside = [lv["label"] for lv in self.levels if not lv.get("in_image", True)]
            if outside and not self.names_withheld:
                lines.append(f"outside the image: {', '.join(outside)}")
            texts["tl"], texts["tr"], texts["bl"] = "\n".join(lines), "", ""
        return texts

    def banner_rect(self, view: QtCore.QRectF) -> QtCore.QRectF:
        """Where the level-answer banner goes (top of the view, full width); empty without a banner."""
        if self.banner is None or self._image is None:
            return QtCore.QRectF()
        return QtCore.QRectF(view.left(), view.top(), view.width(), self._banner_height(view.width()))

    def _banner_parts(self, width: float) -> tuple[float, float]:
        """Heights (px) of the wrapped headline and reason in a banner ``width`` px wide."""
        head, body = self._banner_fonts()
        flags = int(QtCore.Qt.TextFlag.TextWordWrap)
        box = QtCore.QRectF(0, 0, max(width - 20, 50), 1000)
        headline, reason = (self.banner[0], self.banner[1]) if self.banner else ("", "")
        h1 = QtGui.QFontMetricsF(head).boundingRect(box, flags, headline).height()
        h2 = QtGui.QFontMetricsF(body).boundingRect(box, flags, reason).height() if reason else 0.0
        return h1, h2

    def _banner_height(self, width: float) -> float:
        h1, h2 = self._banner_parts(width)
        return 8.0 + h1 + (4.0 + h2 if h2 else 0.0) + 6.0

    def _banner_fonts(self) -> tuple[QtGui.QFont, QtGui.QFont]:
        head = QtGui.QFont(self.font())
        head.setPointSizeF(12.5)
        head.setBold(True)
        body = QtGui.QFont(self.font())
        body.setPointSizeF(9.5)
        return head, body

    def draw_banner(self, painter: QtGui.QPainter, view: QtCore.QRectF) -> float:
        """The level answer across the top: headline and reason in white on its colour (black on yellow)."""
        rect = self.banner_rect(view)
        if rect.isEmpty():
            return 0.0
        headline, reason, colour = self.banner
        painter.setPen(QtCore.Qt.PenStyle.NoPen)
        painter.setBrush(QtGui.QColor(colour))
        painter.drawRect(rect)
        ink = QtGui.QColor(0, 0, 0) if QtGui.QColor(colour).lightnessF() > 0.6 else QtGui.QColor(255, 255, 255)
        head, body = self._banner_fonts()
        painter.setPen(ink)
        painter.setFont(head)
        text_rect = rect.adjusted(10, 8, -10, -6)
        wrap = int(QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop
                   | QtCore.Qt.TextFlag.TextWordWrap)
        painter.drawText(text_rect, wrap, headline)
        if reason:
            painter.setFont(body)
            painter.drawText(text_rect.adjusted(0, self._banner_parts(rect.width())[0] + 4, 0, 0), wrap, reason)
        return rect.height()

    def fit(self) -> None:
        """Show the whole image between the banner and header lines above and the legend below (they never
        cover the image)."""
        super().fit()
        rect = self.image_rect()
        view_h = float(self.viewport().height())
        top = self._banner_height(self.viewport().width()) if self.banner is not None else 0.0
        top += 18.0 * (2 + any(not lv.get("in_image", True) for lv in self.levels)) if self.levels else 0.0
        bottom = LEGEND_HEIGHT_PX + 8.0 if self._image is not None else 0.0
        free = view_h - top - bottom
        if rect.isEmpty() or top + bottom <= 0 or free <= 50:
            return
        target = rect.adjusted(0, -rect.height() * top / free, 0, rect.height() * bottom / free)
        self.resetTransform()
        self.fitInView(target, QtCore.Qt.AspectRatioMode.KeepAspectRatio)
        self.centerOn(target.center())
        self._auto_fit = True

    def draw_annotations(self, painter: QtGui.QPainter, view: QtCore.QRectF) -> None:
        top = self.draw_banner(painter, view)
        super().draw_annotations(painter, view.adjusted(0, top, 0, 0))
        fitted = (status_ink(self.status), f"fitted level, {UNSURE_WORDS[self.status]}") \
            if self.status in UNSURE_WORDS else (FITTED_COLOUR, "fitted level (PDE to click)")
        entries = [("fitted", *fitted),
                   ("check", CHECK_COLOUR, "CT level not fitted (projected)"),
                   ("click", CLICK_COLOUR, "X-ray click")]
        font = painter.font()
        font.setBold(False)
        font.setPointSizeF(9.0)
        painter.setFont(font)
        box = QtCore.QRectF(view.left() + 8, view.bottom() - LEGEND_HEIGHT_PX - 8, 230, LEGEND_HEIGHT_PX)
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
