"""CarmRegWidget: the main window. It owns the data, the landmark stores and the views; it calls the logic.

Workflow (left panel, Ctrl+1..5): 1 Data & geometry, 2 CT centroids, 3 X-ray centroids, 4 Register,
5 Check. Views (centre): CT (axial, coronal, sagittal, 3D), X-ray, Result (overlay + 3D with the C-arm).

Rules kept here:
- every computation is a call into ``Logic`` (loading, geometry, registration, export); the widget never
  re-implements it;
- a ``CarmRegError`` from the logic becomes a warning dialog with its one-line message; anything else a
  critical dialog with the traceback under "Show Details" (and in the log) - see ``qt_common.report_errors``;
- the registration runs on a QThread (``worker.RegistrationWorker``) with progress and cancel;
- landmark edits are undoable (one QUndoStack) and autosaved (``carmreg.logic.io.session``) shortly after every change;
  an autosave left by a crashed run is offered for recovery at start; unsaved work is never discarded
  without asking.
"""

from __future__ import annotations

import logging
from pathlib import Path

from qtpy import QtCore, QtGui, QtWidgets

from carmreg.logic.errors import InputFileError
from carmreg.logic.image.turn import ORIENTATIONS
from carmreg.logic.resources import ICON_PATH

from .panels.geometry_panel import GeometryPanel
from .panels.landmark_panel import LandmarkPanel
from .panels.registration_panel import RegistrationPanel
from .panels.result_panel import ResultPanel
from .point_store import PointStore
from .qt_common import Dialogs, process_events, save_widget_png
from .views.overlay_view import OverlayView
from .views.slice_view import WINDOW_PRESETS, SliceView
from .views.view3d import View3D
from .views.xray_view import XrayView
from .window_actions import STEPS, WindowActions
from .window_data import WindowData
from .window_registration import WindowRegistration
from .window_session import WindowSession

LOG = logging.getLogger("carmreg.gui")
SCREENSHOT_VIEWS = ("window", "axial", "coronal", "sagittal", "ct", "xray", "overlay", "3d", "result")


class CarmRegWidget(WindowActions, WindowData, WindowRegistration, WindowSession, QtWidgets.QMainWindow):
    """The CarmReg desktop window (see module docstring)."""

    result_ready = QtCore.Signal(object)
    registration_finished = QtCore.Signal(bool)

    def __init__(self, dialogs: Dialogs | None = None, autosave: bool = True,
                 state_folder: str | Path | None = None, view3d_mode: str | None = None):
        super().__init__()
        self.setObjectName("carmreg_main")
        self.dialogs = dialogs or Dialogs(self)
        if self.dialogs.parent is None and type(self.dialogs) is Dialogs:
            self.dialogs.parent = self
        self.autosave_enabled = autosave
        self.state_folder = Path(state_folder) if state_folder else None
        self.ct_volume = None
        self.ct_path: str | None = None
        self.xray_as_stored = None  # XrayImage as read from its file, with the geometry overrides
        self.xray_orientation = "as-stored"  # image.turn.ORIENTATIONS: how the window turns it (set_xray_orientation)
        self.xray = None  # the X-ray turned so: what is shown, clicked and registered
        self.xray_path: str | None = None
        self.geometry_overrides: dict = {}
        self.result = None
        self.result_stale = False
        self.quit_code: int | None = None  # set by a termination signal (``close_for_signal``)
        self.last_result_summary: dict | None = None
        self.session_path: str | None = None
        self._dirty = False
        self._reg_state = None
        self._worker = None  # RegistrationWorker while a registration runs
        self._accepting_names = False  # True while "Accept assigned names" renames the clicks
        self._input_click_ids: list[int] = []  # X-ray point ids in the order the registration got them
        self.assigned_names: dict[int, str] = {}  # X-ray point id -> level assigned by the last result
        self.inputs_version = 0  # bumped on every change of data, geometry or landmarks
        self.parameter_overrides: dict = {}  # RegistrationParameters fields forced by scripts and tests
        self.undo_stack = QtGui.QUndoStack(self)
        self.ct_store = PointStore("CT", 3, self.undo_stack, self)
        self.xray_store = PointStore("X-ray", 2, self.undo_stack, self)
        self._build_views(view3d_mode)
        self._build_panels()
        self._build_actions()
        self._connect()
        self._autosave_timer = QtCore.QTimer(self, singleShot=True, interval=700)
        self._autosave_timer.timeout.connect(self.autosave_now)
        self._points3d_timer = QtCore.QTimer(self, singleShot=True, interval=250)
        self._points3d_timer.timeout.connect(self._update_3d_points)
        icon = ICON_PATH
        if icon.is_file():
            self.setWindowIcon(QtGui.QIcon(str(icon)))
        self.resize(1560, 960)
        self._update_title()
        self._update_readiness()
        self.set_step(0)

    # =========================================================================================== layout
    def _build_views(self, view3d_mode: str | None) -> None:
        self.axial = SliceView("axial", self.ct_store)
        self.coronal = SliceView("coronal", self.ct_store)
        self.sagittal = SliceView("sagittal", self.ct_store)
        self.slice_views = (self.axial, self.coronal, self.sagittal)
        self.view3d = View3D(mode=view3d_mode)
        self.xray_view = XrayView(self.xray_store)
        self.overlay_view = OverlayView()
        self.view3d_result = View3D(mode=self.view3d.mode if view3d_mode is None else view3d_mode)
        self.view3d_result.setObjectName("view3d_result")

        ct_page = QtWidgets.QWidget()
        ct_page.setObjectName("ct_page")
        grid = QtWidgets.QGridLayout(ct_page)
        grid.setContentsMargins(0, 0, 0, 0)
        grid.setSpacing(2)
        for view, (r, c) in zip((self.axial, self.view3d, self.coronal, self.sagittal),
                                ((0, 0), (0, 1), (1, 0), (1, 1)), strict=True):
            grid.addWidget(_framed(view), r, c)
        result_page = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        result_page.setObjectName("result_page")
        result_page.addWidget(_framed(self.overlay_view))
        result_page.addWidget(_framed(self.view3d_result))
        result_page.setStretchFactor(0, 3)  # the overlay gets most of the room, the 3D view keeps a fair share
        result_page.setStretchFactor(1, 2)
        result_page.setSizes([600, 400])
        self.ct_page, self.result_page = ct_page, result_page
        self.view_tabs = QtWidgets.QTabWidget()
        self.view_tabs.setDocumentMode(True)
        self.view_tabs.addTab(ct_page, "CT")
        self.view_tabs.addTab(_framed(self.xray_view), "X-ray")
        self.view_tabs.addTab(result_page, "Result")
        self.setCentralWidget(self.view_tabs)

    def _build_panels(self) -> None:
        self.geometry_panel = GeometryPanel()
        self.data_page = self._data_page()
        self.ct_panel = LandmarkPanel(
            self.ct_store, "Label vertebral centroids on the CT",
            "Click in any slice to place the level shown; the picker then proposes the next level. Drag a point "
            "to move it, right-click it to rename or delete, Delete removes the selected point. Wheel: slices, "
            "Ctrl+wheel: zoom, right-drag: window/level, middle-drag: pan.",
            "Position LPS (mm)", propose=True)
        self.xray_panel = LandmarkPanel(
            self.xray_store, "Click the vertebrae on the X-ray",
            "Click on the centre of each vertebral body. Wheel: zoom, middle-drag or Shift+drag: pan, "
            "right-drag: contrast. Name at least 3 levels that are also labelled on the CT, or untick "
            "'Name the levels' and click at least 3 vertebrae: CarmReg then identifies the levels from the "
            "image (you may name only those you are sure of). With no clicks at all it identifies them from "
            "the image alone.",
            "(u, v) px", allow_unnamed=True)
        self.registration_panel = RegistrationPanel(self._stages(), self._metrics())
        self.result_panel = ResultPanel(self.overlay_view)
        for panel in (self.ct_panel, self.xray_panel):
            panel.dialogs = self.dialogs
        ct_display = self._ct_display_box()
        xray_display = self._xray_display_box()
        pages = [self.data_page, _stack(self.ct_panel, ct_display), _stack(self.xray_panel, xray_display),
                 self.registration_panel, self.result_panel]
        self.step_tabs = QtWidgets.QTabWidget()
        self.step_tabs.setObjectName("workflow")
        for i, (page, title) in enumerate(zip(pages, STEPS, strict=True)):
            scroll = QtWidgets.QScrollArea()
            scroll.setWidgetResizable(True)
            scroll.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
            page.setContentsMargins(8, 8, 8, 8)
            scroll.setWidget(page)
            self.step_tabs.addTab(scroll, f"{i + 1} {title}")
        dock = QtWidgets.QDockWidget("Workflow", self)
        dock.setObjectName("workflow_dock")
        dock.setFeatures(QtWidgets.QDockWidget.DockWidgetFeature.DockWidgetMovable)
        dock.setWidget(self.step_tabs)
        dock.setMinimumWidth(430)
        self.addDockWidget(QtCore.Qt.DockWidgetArea.LeftDockWidgetArea, dock)
        self.autosave_label = QtWidgets.QLabel("")
        self.autosave_label.setObjectName("hint")
        self.statusBar().addPermanentWidget(self.autosave_label)

    def _data_page(self) -> QtWidgets.QWidget:
        page = QtWidgets.QWidget()
        layout = QtWidgets.QVBoxLayout(page)
        layout.setContentsMargins(0, 0, 0, 0)
        heading = QtWidgets.QLabel("Load the CT and the X-ray")
        heading.setObjectName("heading")
        layout.addWidget(heading)
        box = QtWidgets.QGroupBox("Data")
        grid = QtWidgets.QGridLayout(box)
        self.ct_info = QtWidgets.QLabel("No CT loaded")
        self.xray_info = QtWidgets.QLabel("No X-ray loaded")
        for label in (self.ct_info, self.xray_info):
            label.setWordWrap(True)
            label.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        load_ct = QtWidgets.QPushButton("Load CT...")
        load_ct.setToolTip("DICOM series folder (choose any file in it), NIfTI, NRRD or MetaImage")
        load_ct.clicked.connect(self._action_load_ct)
        load_ct_dir = QtWidgets.QPushButton("DICOM folder...")
        load_ct_dir.clicked.connect(self._action_load_ct_folder)
        load_xray = QtWidgets.QPushButton("Load X-ray...")
        load_xray.setToolTip("DICOM (XA, RF, DX, CR) or PNG/TIFF; give the geometry below if the file lacks it")
        load_xray.clicked.connect(self._action_load_xray)
        sample = QtWidgets.QPushButton("Load sample case")
        sample.setToolTip("A real chest CT (T1-L1) with a simulated C-arm image and centroids on both")
        sample.clicked.connect(self._action_load_sample)
        grid.addWidget(QtWidgets.QLabel("<b>CT</b>"), 0, 0)
        grid.addWidget(self.ct_info, 1, 0, 1, 3)
        grid.addWidget(load_ct, 2, 0)
        grid.addWidget(load_ct_dir, 2, 1)
        grid.addWidget(QtWidgets.QLabel("<b>X-ray</b>"), 3, 0)
        grid.addWidget(self.xray_info, 4, 0, 1, 3)
        grid.addWidget(load_xray, 5, 0)
        self.orientation_combo = QtWidgets.QComboBox()
        self.orientation_combo.setObjectName("xray_orientation")
        for name in ORIENTATIONS:
            self.orientation_combo.addItem(f"shown {name.replace('-', ' ')}", name)
        self.orientation_combo.setToolTip(
            "How the X-ray file is turned before it is shown, clicked and registered. Leave it as stored unless "
            "CarmReg refuses the image as mirrored or rotated and names the turn: choose that turn here. Placed "
            "points turn with the image; exported points and sessions stay on the image as stored.")
        self.orientation_combo.activated.connect(self._action_orientation)
        self.orientation_combo.setEnabled(False)  # until an X-ray is loaded (``_show_xray``)
        grid.addWidget(self.orientation_combo, 5, 1, 1, 2)
        grid.addWidget(sample, 6, 0, 1, 3)
        layout.addWidget(box)
        layout.addWidget(self.geometry_panel)
        layout.addStretch(1)
        return page

    def _ct_display_box(self) -> QtWidgets.QGroupBox:
        box = QtWidgets.QGroupBox("CT display")
        row = QtWidgets.QHBoxLayout(box)
        row.addWidget(QtWidgets.QLabel("Window"))
        for name in WINDOW_PRESETS:
            button = QtWidgets.QPushButton(name)
            button.clicked.connect(lambda _=False, n=name: self.set_ct_window(n))
            row.addWidget(button)
        fit = QtWidgets.QPushButton("Fit")
        fit.clicked.connect(lambda: [v.fit() for v in self.slice_views])
        row.addWidget(fit)
        return box

    def _xray_display_box(self) -> QtWidgets.QGroupBox:
        """Contrast of the X-ray: window and level (also right-drag in the view), auto, invert, fit."""
        box = QtWidgets.QGroupBox("X-ray display")
        grid = QtWidgets.QGridLayout(box)
        self.xray_window_spin, self.xray_level_spin = QtWidgets.QDoubleSpinBox(), QtWidgets.QDoubleSpinBox()
        for spin, name in ((self.xray_window_spin, "Window"), (self.xray_level_spin, "Level")):
            spin.setRange(-1e7, 1e7)
            spin.setDecimals(0)
            spin.setKeyboardTracking(False)
            spin.setToolTip(f"{name} of the X-ray display (pixel values); right-drag in the view changes both")
            spin.valueChanged.connect(self._xray_window_edited)
        self.xray_view.window_changed.connect(self._xray_window_shown)
        auto = QtWidgets.QPushButton("Auto contrast")
        auto.setToolTip("Window the exposed field's 1st-99th percentiles, clipped pixels left out")
        auto.clicked.connect(self.xray_view.auto_window)
        self.invert_check = QtWidgets.QCheckBox("Invert")
        self.invert_check.toggled.connect(self.xray_view.set_invert)
        fit = QtWidgets.QPushButton("Fit")
        fit.clicked.connect(self.xray_view.fit)
        grid.addWidget(QtWidgets.QLabel("Window"), 0, 0)
        grid.addWidget(self.xray_window_spin, 0, 1)
        grid.addWidget(QtWidgets.QLabel("Level"), 0, 2)
        grid.addWidget(self.xray_level_spin, 0, 3)
        grid.addWidget(auto, 1, 0, 1, 2)
        grid.addWidget(self.invert_check, 1, 2)
        grid.addWidget(fit, 1, 3)
        return box

    def _xray_window_shown(self, window: float, level: float) -> None:
        for spin, value in ((self.xray_window_spin, window), (self.xray_level_spin, level)):
            spin.blockSignals(True)
            spin.setValue(value)
            spin.blockSignals(False)

    def _xray_window_edited(self, _value: float) -> None:
        self.xray_view.set_window_level(self.xray_window_spin.value(), self.xray_level_spin.value())

    def _connect(self) -> None:
        for store in (self.ct_store, self.xray_store):
            store.changed.connect(self._landmarks_changed)
        self.ct_store.selection_changed.connect(self._ct_selected)
        self.undo_stack.cleanChanged.connect(self._clean_changed)
        for view in self.slice_views:
            view.point_activated.connect(self._go_to)
        for view in (*self.slice_views, self.xray_view, self.overlay_view):
            view.hover_text.connect(lambda text: self.statusBar().showMessage(text, 4000))
            view.status_message.connect(lambda text: self.statusBar().showMessage(text, 6000))
        for view in self.slice_views:
            view.place_enabled = lambda: self.ct_panel.place_check.isChecked()
        self.xray_view.place_enabled = lambda: self.xray_panel.place_check.isChecked()
        self.ct_panel.place_check.toggled.connect(lambda on: self.act_place.setChecked(
            on or self.xray_panel.place_check.isChecked()))
        self.geometry_panel.overrides_changed.connect(self._action_geometry)
        self.geometry_panel.measure_distortion_requested.connect(self._action_measure_distortion)
        self.ct_panel.import_requested.connect(self._action_import_ct)
        self.ct_panel.export_requested.connect(self._action_export_ct)
        self.ct_panel.propose_requested.connect(self._action_propose_centroids)
        self.xray_panel.import_requested.connect(self._action_import_xray)
        self.xray_panel.export_requested.connect(self._action_export_xray)
        self.registration_panel.run_all_requested.connect(self._action_register)
        self.registration_panel.run_next_requested.connect(self._action_next_stage)
        self.registration_panel.cancel_requested.connect(self.cancel_registration)
        self.registration_panel.reset_requested.connect(self.reset_registration)
        self.result_panel.export_requested.connect(self._action_export_result)
        self.result_panel.overlay_png_requested.connect(self._action_overlay_png)
        self.result_panel.report_requested.connect(self._action_report_pdf)
        self.result_panel.accept_names_requested.connect(self._action_accept_names)
        self.result_panel.turn_requested.connect(self._action_turn_and_register)
        self.xray_store.naming_changed.connect(self.act_name_levels.setChecked)
        self.step_tabs.currentChanged.connect(self._step_changed)

    # =========================================================================================== screenshots
    def screenshot_widget(self, view: str) -> QtWidgets.QWidget:
        widgets = {"window": self, "axial": self.axial, "coronal": self.coronal, "sagittal": self.sagittal,
                   "ct": self.ct_page, "xray": self.xray_view, "overlay": self.overlay_view, "3d": self.view3d,
                   "result": self.result_page}
        if view not in widgets:
            raise InputFileError(f"unknown view {view!r}; choose one of {', '.join(SCREENSHOT_VIEWS)}")
        return widgets[view]

    def save_screenshot(self, path: str | Path, view: str = "window") -> Path:
        """PNG of a view or of the whole window (works offscreen)."""
        widget = self.screenshot_widget(view)
        tab = {"axial": 0, "coronal": 0, "sagittal": 0, "ct": 0, "3d": 0, "xray": 1, "overlay": 2,
               "result": 2}.get(view)
        if tab is not None:
            self.view_tabs.setCurrentIndex(tab)
        process_events()
        for v3 in (self.view3d, self.view3d_result):
            v3.prepare_grab()
        try:
            process_events()
            return Path(save_widget_png(widget, path))
        finally:
            for v3 in (self.view3d, self.view3d_result):
                v3.finish_grab()

    # =========================================================================================== UI state
    def set_step(self, index: int) -> None:
        self.step_tabs.setCurrentIndex(index)
        self._step_changed(index)

    def _step_changed(self, index: int) -> None:
        tab = {0: 0, 1: 0, 2: 1, 3: 1, 4: 2}.get(index, 0)
        if index == 3 and self.result is not None:
            tab = 2
        self.view_tabs.setCurrentIndex(tab)

    def _inputs_changed(self, reset_overlay: bool = True) -> None:
        self.inputs_version += 1
        if self._reg_state is not None and not self.is_running():
            self._reg_state = None
            self.registration_panel.reset()
        if self._accepting_names:
            pass  # the clicks now carry the names this result assigned: it still describes them
        elif self.result is not None and not self.result_stale:
            self.mark_result_stale("inputs changed since this result")
        self._update_readiness()
        self._mark_dirty()

    def mark_result_stale(self, why: str) -> None:
        """The result shown no longer describes the inputs: both banners turn grey and say so (``stale_banner``;
        its answer, green or amber, is no longer shown as an answer), the overlay's header line says why, and
        the names it assigned to the clicks are withdrawn."""
        from carmreg.logic.report.style import stale_banner

        self.result_stale = True
        banner = stale_banner(why)
        self.overlay_view.summary = f"{why}: register again"
        self.overlay_view.banner = banner
        self.overlay_view.viewport().update()
        self.result_panel.set_stale(banner)
        self.clear_assigned_names()

    def _update_readiness(self) -> None:
        """The Register button and the ready line, from the logic's rules (``registration.preflight``)."""
        from carmreg.logic.registration.preflight import preflight

        readiness = preflight(self.ct_store.to_landmarks(), self.xray_store.to_landmarks(),
                              ct_loaded=self.ct_volume is not None, xray_loaded=self.xray is not None,
                              geometry_known=self.xray is not None and self.xray.intrinsics is not None,
                              xray_size_px=None if self.xray is None else self.xray.size_px)
        if readiness.problems:
            self.registration_panel.set_ready(False, "Not ready: " + "; ".join(readiness.problems) + ".",
                                              readiness.mode)
        else:
            self.registration_panel.set_ready(True, self._ready_text(readiness.mode, readiness.common_levels),
                                              readiness.mode)

    def _ready_text(self, mode: str, common: list[str]) -> str:
        """The ready line: what will be registered and which level identification runs."""
        n, unnamed = len(self.xray_store), self.xray_store.unnamed_count()
        named = self.xray_store.labels()
        if mode == "named":
            return (f"Ready: {len(common)} levels on both ({', '.join(common)}). Level names given: the image "
                    "checks them (mode: named).")
        if mode == "partly_named":
            return (f"Ready: {n} X-ray clicks, {n - unnamed} named ({', '.join(named)}) and {unnamed} unnamed: "
                    "CarmReg names the unnamed clicks from the image (mode: partly named).")
        if mode == "unnamed":
            return (f"Ready: {n} unnamed X-ray clicks: CarmReg identifies their levels from the image "
                    "(mode: unnamed).")
        return ("Ready: no X-ray clicks: CarmReg identifies the levels from the image alone (mode: image only; "
                "slower and less sure than with clicks).")

    def _clean_changed(self, _clean: bool) -> None:
        self._update_title()

    def _update_title(self) -> None:
        name = Path(self.session_path).name if self.session_path else "untitled session"
        self.setWindowTitle(f"CarmReg - {name}[*]")
        self.setWindowModified(self.is_dirty())

    def _busy(self, message: str) -> None:
        self.statusBar().showMessage(message)
        QtWidgets.QApplication.setOverrideCursor(QtCore.Qt.CursorShape.WaitCursor)
        process_events()

    def _idle(self) -> None:
        QtWidgets.QApplication.restoreOverrideCursor()
        self.statusBar().clearMessage()


def _framed(widget: QtWidgets.QWidget) -> QtWidgets.QFrame:
    frame = QtWidgets.QFrame()
    frame.setObjectName("viewframe")
    frame.setStyleSheet("QFrame#viewframe { border: 1px solid #3a3f45; }")
    layout = QtWidgets.QVBoxLayout(frame)
    layout.setContentsMargins(1, 1, 1, 1)
    layout.addWidget(widget)
    return frame


def _stack(*widgets: QtWidgets.QWidget) -> QtWidgets.QWidget:
    page = QtWidgets.QWidget()
    layout = QtWidgets.QVBoxLayout(page)
    layout.setContentsMargins(0, 0, 0, 0)
    for w in widgets:
        layout.addWidget(w)
    return page
