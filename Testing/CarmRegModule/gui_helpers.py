"""Simulated mouse and keyboard input for the GUI tests (QTest on the views' viewports)."""

from __future__ import annotations

import numpy as np
from qtpy import QtCore
from qtpy.QtTest import QTest

from carmreg.qt_common import process_events

LEFT = QtCore.Qt.MouseButton.LeftButton
RIGHT = QtCore.Qt.MouseButton.RightButton
NO_MOD = QtCore.Qt.KeyboardModifier.NoModifier


def view_pos(view, scene_xy) -> QtCore.QPoint:
    return view.mapFromScene(QtCore.QPointF(float(scene_xy[0]), float(scene_xy[1])))


def click(view, scene_xy, button=LEFT, modifier=NO_MOD) -> None:
    QTest.mouseClick(view.viewport(), button, modifier, view_pos(view, scene_xy))
    process_events()


def drag(view, from_xy, to_xy, button=LEFT, steps: int = 4) -> None:
    start, end = view_pos(view, from_xy), view_pos(view, to_xy)
    QTest.mousePress(view.viewport(), button, NO_MOD, start)
    for t in np.linspace(0, 1, steps + 1)[1:]:
        p = QtCore.QPoint(int(round(start.x() + t * (end.x() - start.x()))),
                          int(round(start.y() + t * (end.y() - start.y()))))
        QTest.mouseMove(view.viewport(), p)
        process_events()
    QTest.mouseRelease(view.viewport(), button, NO_MOD, end)
    process_events()


def key(view, qt_key) -> None:
    view.setFocus()
    QTest.keyClick(view.viewport(), qt_key)
    process_events()


def wheel(view, scene_xy, notches: int, modifier=NO_MOD) -> None:
    """Send wheel notches (120 units each) at a scene point."""
    from qtpy import QtGui, QtWidgets

    pos = QtCore.QPointF(view_pos(view, scene_xy))
    event = QtGui.QWheelEvent(pos, QtCore.QPointF(view.viewport().mapToGlobal(pos.toPoint())), QtCore.QPoint(0, 0),
                              QtCore.QPoint(0, 120 * notches), QtCore.Qt.MouseButton.NoButton, modifier,
                              QtCore.Qt.ScrollPhase.NoScrollPhase, False)
    QtWidgets.QApplication.sendEvent(view.viewport(), event)
    process_events()


def scene_tolerance(view) -> float:
    """One screen pixel in scene units (mm for slices, px for the X-ray), plus rounding."""
    return 1.5 / view.zoom_level()


def ready(view) -> None:
    """Let the view fit its image (fit is queued) and settle."""
    process_events(30)
    view.fit()
    process_events()
