"""Qt plumbing shared by the widgets: the application object, dialogs, error reporting, image conversion.

Every dialog goes through a ``Dialogs`` object so tests can script the answers (``ScriptedDialogs``).
``report_errors`` turns a ``CarmRegError`` raised by the logic into a warning dialog with its one-line
message, and any other exception into a critical dialog with the traceback under "Show Details" (also
logged).
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import traceback

import numpy as np
from qtpy import QtCore, QtGui, QtWidgets

from carmreg.logic.errors import CancelledError, CarmRegError

LOG = logging.getLogger("carmreg.gui")
# the level answer's colours and the overlay's marker colours: carmreg.logic.report.style (one table)
ACCENT = "#3fa7ff"
POINT_COLOR = "#39d0ff"
SELECTED_COLOR = "#ffd43b"


# ---------------------------------------------------------------------------------------- application

def headless() -> bool:
    """True when no display is available (then Qt must use the offscreen platform)."""
    if sys.platform.startswith("linux"):
        return not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return False


def ensure_app(offscreen: bool | None = None) -> QtWidgets.QApplication:
    """The QApplication, created once; offscreen when asked or when there is no display."""
    app = QtWidgets.QApplication.instance()
    if app is not None:
        return app
    if offscreen or (offscreen is None and headless()):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    app = QtWidgets.QApplication(sys.argv[:1])
    app.setApplicationName("CarmReg")
    app.setOrganizationName("CarmReg")
    apply_style(app)
    return app


def is_offscreen() -> bool:
    return QtGui.QGuiApplication.platformName() in ("offscreen", "minimal")


def apply_style(app: QtWidgets.QApplication) -> None:
    """A dark, low-glare Fusion palette (images read best against dark surroundings)."""
    app.setStyle("Fusion")
    pal = QtGui.QPalette()
    c = QtGui.QColor
    roles = QtGui.QPalette.ColorRole
    for role, color in ((roles.Window, c(45, 48, 52)), (roles.WindowText, c(225, 228, 232)),
                        (roles.Base, c(30, 32, 35)), (roles.AlternateBase, c(40, 43, 47)),
                        (roles.ToolTipBase, c(250, 250, 250)), (roles.ToolTipText, c(20, 20, 20)),
                        (roles.Text, c(225, 228, 232)), (roles.Button, c(55, 59, 64)),
                        (roles.ButtonText, c(225, 228, 232)), (roles.BrightText, c(255, 80, 80)),
                        (roles.Highlight, c(ACCENT)), (roles.HighlightedText, c(10, 10, 10)),
                        (roles.Link, c(ACCENT)), (roles.PlaceholderText, c(130, 134, 140))):
        pal.setColor(role, color)
    for role in (roles.Text, roles.WindowText, roles.ButtonText):
        pal.setColor(QtGui.QPalette.ColorGroup.Disabled, role, c(120, 124, 130))
    app.setPalette(pal)
    app.setStyleSheet(
        "QToolTip { color: #141414; background: #fafafa; border: 1px solid #888; }"
        "QGroupBox { font-weight: 600; border: 1px solid #555a60; border-radius: 4px; margin-top: 10px; "
        "padding-top: 6px; }"
        "QGroupBox::title { subcontrol-origin: margin; left: 8px; padding: 0 4px; color: #9fd0ff; }"
        "QTabBar::tab { padding: 6px 14px; }"
        "QTabBar::tab:selected { color: #ffffff; border-bottom: 2px solid " + ACCENT + "; }"
        "QPushButton#primary { background: #1c7ed6; color: white; font-weight: 600; padding: 6px 12px; }"
        "QPushButton#primary:disabled { background: #3b4a5a; color: #9aa; }"
        "QLabel#hint { color: #9aa0a6; }"
        "QLabel#heading { font-size: 13pt; font-weight: 600; color: #e9ecef; }"
        "QLabel#warning { color: #ffa94d; }"
        "QLabel#ok { color: #69db7c; }")


# ---------------------------------------------------------------------------------------- dialogs

class Dialogs:
    """Every modal interaction of the app, so tests can replace them (see ScriptedDialogs)."""

    def __init__(self, parent: QtWidgets.QWidget | None = None):
        self.parent = parent

    def error(self, title: str, message: str, details: str | None = None) -> None:
        box = QtWidgets.QMessageBox(self.parent)
        box.setIcon(QtWidgets.QMessageBox.Icon.Critical if details else QtWidgets.QMessageBox.Icon.Warning)
        box.setWindowTitle(title)
        box.setText(message)
        if details:
            box.setDetailedText(details)
        box.exec()

    def info(self, title: str, message: str) -> None:
        QtWidgets.QMessageBox.information(self.parent, title, message)

    def question(self, title: str, message: str, choices: tuple[str, ...]) -> str:
        """Ask; returns the chosen label (the last choice = the safe one, returned on Escape)."""
        box = QtWidgets.QMessageBox(self.parent)
        box.setIcon(QtWidgets.QMessageBox.Icon.Question)
        box.setWindowTitle(title)
        box.setText(message)
        buttons = [box.addButton(c, QtWidgets.QMessageBox.ButtonRole.ActionRole) for c in choices]
        box.setEscapeButton(buttons[-1])
        box.setDefaultButton(buttons[0])
        box.exec()
        clicked = box.clickedButton()
        return choices[buttons.index(clicked)] if clicked in buttons else choices[-1]

    def open_file(self, title: str, filters: str, directory: str = "") -> str | None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self.parent, title, directory, filters)
        return path or None

    def open_dir(self, title: str, directory: str = "") -> str | None:
        return QtWidgets.QFileDialog.getExistingDirectory(self.parent, title, directory) or None

    def save_file(self, title: str, filters: str, directory: str = "") -> str | None:
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self.parent, title, directory, filters)
        return path or None

    def choose(self, title: str, label: str, items: list[str], current: int = 0) -> str | None:
        item, ok = QtWidgets.QInputDialog.getItem(self.parent, title, label, items, current, False)
        return item if ok else None


class ScriptedDialogs(Dialogs):
    """Non-interactive dialogs for tests and headless runs: answers come from queues, messages are kept."""

    def __init__(self, answers: dict | None = None):
        super().__init__(None)
        self.answers = {k: list(v) for k, v in (answers or {}).items()}
        self.messages: list[tuple[str, str, str | None]] = []

    def _next(self, kind: str, default):
        queue = self.answers.get(kind) or []
        return queue.pop(0) if queue else default

    def error(self, title, message, details=None):
        self.messages.append((title, message, details))

    def info(self, title, message):
        self.messages.append((title, message, None))

    def question(self, title, message, choices):
        self.messages.append((title, message, None))
        return self._next("question", choices[-1])

    def open_file(self, title, filters, directory=""):
        return self._next("open_file", None)

    def open_dir(self, title, directory=""):
        return self._next("open_dir", None)

    def save_file(self, title, filters, directory=""):
        return self._next("save_file", None)

    def choose(self, title, label, items, current=0):
        return self._next("choose", None)


def report_errors(method):
    """Decorator for slots of objects with a ``dialogs`` attribute: errors become dialogs, never crashes."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except CancelledError as exc:
            _status(self, str(exc))
        except CarmRegError as exc:
            LOG.warning("%s", exc)
            _dialogs(self).error("CarmReg", str(exc))
        except Exception as exc:  # noqa: BLE001 - the last line of defence of a GUI slot
            details = traceback.format_exc()
            LOG.error("unexpected error in %s\n%s", method.__qualname__, details)
            _dialogs(self).error("CarmReg - unexpected error",
                                 f"Unexpected error: {exc.__class__.__name__}: {exc}\n\nYour work is autosaved. "
                                 "Please report this with the details below.", details)
        return None
    return wrapper


def _dialogs(obj) -> Dialogs:
    return getattr(obj, "dialogs", None) or Dialogs(obj if isinstance(obj, QtWidgets.QWidget) else None)


def _status(obj, text: str) -> None:
    window = obj.window() if isinstance(obj, QtWidgets.QWidget) else None
    if isinstance(window, QtWidgets.QMainWindow):
        window.statusBar().showMessage(text, 5000)


# ---------------------------------------------------------------------------------------- images

def window_to_uint8(image: np.ndarray, window: float, level: float, invert: bool = False) -> np.ndarray:
    """Map values to 0..255 with a window/level: 0 at level - window/2, 255 at level + window/2."""
    lo = level - window / 2.0
    scaled = (np.asarray(image, np.float32) - np.float32(lo)) * np.float32(255.0 / max(window, 1e-6))
    out = np.clip(scaled, 0, 255).astype(np.uint8)
    return 255 - out if invert else out


def gray_qimage(gray_u8: np.ndarray) -> QtGui.QImage:
    """QImage (owning a copy) of a (rows, cols) uint8 array."""
    data = np.ascontiguousarray(gray_u8, dtype=np.uint8)
    rows, cols = data.shape
    return QtGui.QImage(data.data, cols, rows, cols, QtGui.QImage.Format.Format_Grayscale8).copy()


def rgb_qimage(rgb_u8: np.ndarray) -> QtGui.QImage:
    """QImage (owning a copy) of a (rows, cols, 3) uint8 array."""
    data = np.ascontiguousarray(rgb_u8, dtype=np.uint8)
    rows, cols, _ = data.shape
    return QtGui.QImage(data.data, cols, rows, 3 * cols, QtGui.QImage.Format.Format_RGB888).copy()


def robust_range(image: np.ndarray, low_pct: float = 1.0, high_pct: float = 99.5) -> tuple[float, float]:
    """Percentile range of a whole image (``image.field.display_range`` without a field, clipped pixels kept)."""
    from carmreg.logic.image.field import display_range

    return display_range(image, None, (low_pct, high_pct), drop_clipped=False)


def save_widget_png(widget: QtWidgets.QWidget, path) -> str:
    """Grab a widget (works offscreen) and write it as PNG atomically."""
    from carmreg.logic.io.atomic import atomic_write

    pixmap = widget.grab()

    def writer(tmp):
        if not pixmap.save(str(tmp), "PNG"):
            raise OSError(f"could not write {path}")
    return str(atomic_write(path, writer))


def process_events(ms: int = 0) -> None:
    app = QtWidgets.QApplication.instance()
    if app is None:
        return
    if ms <= 0:
        app.processEvents()
        return
    loop = QtCore.QEventLoop()
    QtCore.QTimer.singleShot(ms, loop.quit)
    loop.exec()
