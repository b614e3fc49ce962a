"""A named point marker of the 2D views: ``MarkerSpec`` (what to draw) and ``MarkerItem`` (a Qt graphics item of
constant size on screen: a glyph at the point and its label beside it)."""

from __future__ import annotations

from dataclasses import dataclass

from qtpy import QtCore, QtGui, QtWidgets

from ..qt_common import POINT_COLOR, SELECTED_COLOR

HIT_RADIUS_PX = 10.0


@dataclass
class MarkerSpec:
    """One marker to draw: scene position, text and style."""

    key: object
    x: float
    y: float
    text: str
    style: str = "point"      # point | selected | fitted | check | click
    alpha: float = 1.0
    color: str | None = None


class MarkerItem(QtWidgets.QGraphicsItem):
    """A landmark glyph and its label, constant size on screen."""

    def __init__(self, spec: MarkerSpec):
        super().__init__()
        self.setFlag(QtWidgets.QGraphicsItem.GraphicsItemFlag.ItemIgnoresTransformations, True)
        self.setZValue(10)
        self.spec = spec
        self.update_spec(spec)

    def update_spec(self, spec: MarkerSpec) -> None:
        self.prepareGeometryChange()
        self.spec = spec
        self.setPos(spec.x, spec.y)
        self.setOpacity(spec.alpha)
        self.update()

    show_text = True  # False when the view's decluttering hides this label (it would overprint another)

    def boundingRect(self) -> QtCore.QRectF:
        return QtCore.QRectF(-14, -14, 200, 30)

    def label_rect(self) -> QtCore.QRectF:
        """The label's box relative to the glyph centre, in screen px (an estimate from the text length)."""
        return QtCore.QRectF(12, -8, 8.5 * len(self.spec.text) + 4, 17) if self.spec.text else QtCore.QRectF()

    def paint(self, painter: QtGui.QPainter, option, widget=None) -> None:
        spec = self.spec
        painter.setRenderHint(QtGui.QPainter.RenderHint.Antialiasing, True)
        color = QtGui.QColor(spec.color or (SELECTED_COLOR if spec.style == "selected" else POINT_COLOR))
        dark = QtGui.QPen(QtGui.QColor(0, 0, 0, 200), 3.5)
        pen = QtGui.QPen(color, 1.8)
        for p in (dark, pen):
            painter.setPen(p)
            painter.setBrush(QtCore.Qt.BrushStyle.NoBrush)
            self._glyph(painter, spec.style)
        if spec.style == "fitted":
            painter.setPen(QtCore.Qt.PenStyle.NoPen)
            painter.setBrush(color)
            painter.drawEllipse(QtCore.QPointF(0, 0), 3.0, 3.0)
        if spec.text and self.show_text:
            self._label(painter, spec.text, color)

    @staticmethod
    def _glyph(painter: QtGui.QPainter, style: str) -> None:
        if style == "check":
            painter.drawEllipse(QtCore.QPointF(0, 0), 7.0, 7.0)
        elif style == "click":
            painter.drawLine(QtCore.QPointF(-9, 0), QtCore.QPointF(9, 0))
            painter.drawLine(QtCore.QPointF(0, -9), QtCore.QPointF(0, 9))
        else:
            radius = 8.0 if style == "selected" else 6.5
            painter.drawEllipse(QtCore.QPointF(0, 0), radius, radius)
            painter.drawLine(QtCore.QPointF(-11, 0), QtCore.QPointF(-radius + 2, 0))
            painter.drawLine(QtCore.QPointF(radius - 2, 0), QtCore.QPointF(11, 0))
            painter.drawLine(QtCore.QPointF(0, -11), QtCore.QPointF(0, -radius + 2))
            painter.drawLine(QtCore.QPointF(0, radius - 2), QtCore.QPointF(0, 11))

    @staticmethod
    def _label(painter: QtGui.QPainter, text: str, color: QtGui.QColor) -> None:
        font = QtGui.QFont(painter.font())
        font.setPointSizeF(10.0)
        font.setBold(True)
        path = QtGui.QPainterPath()
        path.addText(QtCore.QPointF(13, 5), font, text)
        painter.setBrush(QtCore.Qt.BrushStyle.NoBrush)
        painter.setPen(QtGui.QPen(QtGui.QColor(0, 0, 0, 220), 3.0))
        painter.drawPath(path)
        painter.setPen(QtCore.Qt.PenStyle.NoPen)
        painter.setBrush(color)
        painter.drawPath(path)
