"""CarmRegWidget: the main window. It owns the data, the landmark stores and the views; it calls the logic.

Workflow (left panel, Ctrl+1..5): 1 Data & geometry, 2 CT centroids, 3 X-ray centroids, 4 Register,
5 Check. Views (centre): CT (axial, coronal, sagittal, 3D), X-ray, Result (overlay + 3D with the C-arm).

Rules kept here:
- every computation is a call into ``Logic`` (loading, geometry, registration, export); the widget never
  re-implements it;
- a ``CarmRegError`` from the logic becomes a warning dialog with its one-line message; anything else a
  critical dialog with the traceback under "Show Details" (and in the log) - see ``qt_common.report_errors``;
- the registration runs on a QThread (``worker.RegistrationWorker``) with progress and cancel;
- landmark edits are undoable (one QUndoStack) and autosaved (``Logic.session``) shortly after every change;
  an autosave left by a crashed run is offered for recovery at start; unsaved work is never discarded
  without asking.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np
from qtpy import QtCore, QtGui, QtWidgets

from Logic import session as session_io
from Logic.errors import CancelledError, CarmRegError, InputFileError, LandmarkError, RegistrationError
from Logic.landmarks import read_landmarks_2d, read_landmarks_3d, write_landmarks_2d, write_landmarks_3d

from .panels.geometry_panel import GeometryPanel
from .panels.landmark_panel import LandmarkPanel
from .panels.registration_panel import RegistrationPanel
from .panels.result_panel import ResultPanel
from .point_store import PointStore
from .qt_common import Dialogs, process_events, report_errors, save_widget_png
from .views.overlay_view import OverlayView
from .views.slice_view import WINDOW_PRESETS, SliceView
from .views.view3d import View3D
from .views.xray_view import XrayView
from .worker import RegistrationWorker

LOG = logging.getLogger("carmreg.gui")
STEPS = ("Data", "CT points", "X-ray points", "Register", "Check")
VOLUME_FILTER = "CT volumes (*.nrrd *.nhdr *.nii *.nii.gz *.mha *.mhd *.dcm);;All files (*)"
XRAY_FILTER = "X-ray images (*.dcm *.dicom *.png *.tif *.tiff);;All files (*)"
MRK_FILTER = "Slicer markups (*.mrk.json);;JSON (*.json);;All files (*)"
SESSION_FILTER = "CarmReg session (*.carmreg.json);;JSON (*.json)"
SCREENSHOT_VIEWS = ("window", "axial", "coronal", "sagittal", "ct", "xray", "overlay", "3d", "result")


def _registration_api():
    """The pipeline's names, imported late so the GUI starts even if the logic has an import problem."""
    from Logic import pipeline
    return pipeline


class CarmRegWidget(QtWidgets.QMainWindow):
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
        self.xray = None
        self.xray_path: str | None = None
        self.geometry_overrides: dict = {}
        self.result = None
        self.result_stale = False
        self.last_result_summary: dict | None = None
        self.session_path: str | None = None
        self._dirty = False
        self._reg_state = None
        self._worker: RegistrationWorker | None = None
        self._closing_ok = False
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
        result_page.setSizes([900, 450])
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
            self.xray_store, "Label the same vertebrae on the X-ray",
            "Click on the centre of each vertebral body. Wheel: zoom, middle-drag or Shift+drag: pan, "
            "right-drag: contrast. Name at least 3 levels that are also labelled on the CT.",
            "(u, v) px")
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
        box = QtWidgets.QGroupBox("X-ray display")
        row = QtWidgets.QHBoxLayout(box)
        auto = QtWidgets.QPushButton("Auto contrast")
        auto.clicked.connect(self.xray_view.auto_window)
        self.invert_check = QtWidgets.QCheckBox("Invert")
        self.invert_check.toggled.connect(self.xray_view.set_invert)
        fit = QtWidgets.QPushButton("Fit")
        fit.clicked.connect(self.xray_view.fit)
        for w in (auto, self.invert_check, fit):
            row.addWidget(w)
        row.addStretch(1)
        return box

    def _build_actions(self) -> None:
        menu = self.menuBar()
        style = self.style()
        icon = QtWidgets.QStyle.StandardPixmap

        def action(text, slot, shortcut=None, tip=None, std_icon=None):
            act = QtGui.QAction(text, self)
            if shortcut:
                act.setShortcut(QtGui.QKeySequence(shortcut))
            if tip:
                act.setStatusTip(tip)
                act.setToolTip(tip)
            if std_icon is not None:
                act.setIcon(style.standardIcon(std_icon))
            act.triggered.connect(slot)
            return act

        self.act_new = action("&New session", self._action_new, "Ctrl+N", "Close everything and start again")
        self.act_open = action("&Open session...", self._action_open_session, "Ctrl+O",
                               "Open a .carmreg.json session", icon.SP_DialogOpenButton)
        self.act_save = action("&Save session", self._action_save, "Ctrl+S", "Save the session",
                               icon.SP_DialogSaveButton)
        self.act_save_as = action("Save session &as...", self._action_save_as, "Ctrl+Shift+S")
        self.act_load_ct = action("Load &CT...", self._action_load_ct, "Ctrl+L", "Load a CT volume")
        self.act_load_xray = action("Load &X-ray...", self._action_load_xray, "Ctrl+Shift+L", "Load an X-ray")
        self.act_sample = action("Load sa&mple case", self._action_load_sample, None,
                                 "Load the embedded sample CT, X-ray and centroids")
        self.act_import_ct = action("Import CT centroids...", self._action_import_ct)
        self.act_import_xray = action("Import X-ray centroids...", self._action_import_xray)
        self.act_export_ct = action("Export CT centroids...", self._action_export_ct)
        self.act_export_xray = action("Export X-ray centroids...", self._action_export_xray)
        self.act_export_result = action("&Export result folder...", self._action_export_result, "Ctrl+E",
                                        "result.json, overlay, DRR, transform")
        self.act_shot_window = action("Screenshot of the &window...", self._action_screenshot_window, "F12")
        self.act_shot_view = action("Screenshot of the current &view...", self._action_screenshot_view,
                                    "Shift+F12")
        self.act_quit = action("&Quit", self.close, "Ctrl+Q")
        self.act_undo = self.undo_stack.createUndoAction(self, "&Undo")
        self.act_undo.setShortcut(QtGui.QKeySequence.StandardKey.Undo)
        self.act_undo.setIcon(style.standardIcon(icon.SP_ArrowBack))
        self.act_redo = self.undo_stack.createRedoAction(self, "&Redo")
        self.act_redo.setShortcuts([QtGui.QKeySequence.StandardKey.Redo, QtGui.QKeySequence("Ctrl+Y")])
        self.act_redo.setIcon(style.standardIcon(icon.SP_ArrowForward))
        self.act_delete = action("&Delete selected point", self._action_delete_selected, "Del")
        self.act_place = action("&Place points", lambda on: self.set_place_mode(on), "P",
                                "Left click places the level shown in the picker")
        self.act_place.setCheckable(True)
        self.act_place.setChecked(True)
        self.act_register = action("&Register", self._action_register, "Ctrl+R",
                                   "Run every registration stage", icon.SP_MediaPlay)
        self.act_cancel = action("&Cancel registration", self.cancel_registration, "Esc",
                                 None, icon.SP_MediaStop)
        self.act_bone = action("Bone window", lambda: self.set_ct_window("Bone"), "B")
        self.act_soft = action("Soft-tissue window", lambda: self.set_ct_window("Soft tissue"), "T")
        self.act_about = action("&About CarmReg", self._action_about)
        self.act_keys = action("&Mouse and keys", self._action_keys, "F1")

        file_menu = menu.addMenu("&File")
        for a in (self.act_new, self.act_open, self.act_save, self.act_save_as, None, self.act_load_ct,
                  self.act_load_xray, self.act_sample, None, self.act_import_ct, self.act_import_xray,
                  self.act_export_ct, self.act_export_xray, self.act_export_result, None, self.act_shot_window,
                  self.act_shot_view, None, self.act_quit):
            file_menu.addSeparator() if a is None else file_menu.addAction(a)
        edit_menu = menu.addMenu("&Edit")
        for a in (self.act_undo, self.act_redo, None, self.act_delete, self.act_place):
            edit_menu.addSeparator() if a is None else edit_menu.addAction(a)
        view_menu = menu.addMenu("&View")
        for i, title in enumerate(STEPS):
            view_menu.addAction(action(f"Step {i + 1}: {title}", lambda _=False, n=i: self.set_step(n),
                                       f"Ctrl+{i + 1}"))
        view_menu.addSeparator()
        view_menu.addAction(self.act_bone)
        view_menu.addAction(self.act_soft)
        reg_menu = menu.addMenu("&Registration")
        reg_menu.addAction(self.act_register)
        reg_menu.addAction(self.act_cancel)
        help_menu = menu.addMenu("&Help")
        help_menu.addAction(self.act_keys)
        help_menu.addAction(self.act_about)

        bar = self.addToolBar("Main")
        bar.setObjectName("main_toolbar")
        bar.setMovable(False)
        bar.setToolButtonStyle(QtCore.Qt.ToolButtonStyle.ToolButtonTextBesideIcon)
        bar.setIconSize(QtCore.QSize(16, 16))
        for a in (self.act_open, self.act_save, None, self.act_undo, self.act_redo, None, self.act_place,
                  None, self.act_register, self.act_cancel, None, self.act_shot_window):
            bar.addSeparator() if a is None else bar.addAction(a)
        self.act_cancel.setEnabled(False)

    def _connect(self) -> None:
        for store in (self.ct_store, self.xray_store):
            store.changed.connect(self._landmarks_changed)
        self.ct_store.selection_changed.connect(self._ct_selected)
        self.undo_stack.cleanChanged.connect(lambda _clean: self._update_title())
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
        self.step_tabs.currentChanged.connect(self._step_changed)

    # =========================================================================================== data
    def load_ct(self, path: str | Path) -> None:
        """Load a CT through ``Logic.io_volume.load_volume`` (raises CarmRegError on bad input)."""
        from Logic.io_volume import load_volume

        self._busy(f"Loading CT {Path(path).name}...")
        try:
            volume = load_volume(path)
        finally:
            self._idle()
        self.set_ct_volume(volume, str(path))

    def set_ct_volume(self, volume, path: str | None = None) -> None:
        self.ct_volume, self.ct_path = volume, path
        for view in self.slice_views:
            view.set_volume(volume)
        self._busy("Building the bone surface for the 3D view...")
        try:
            self.view3d.set_volume(volume)
            self.view3d_result.set_volume(volume, surface=self.view3d.surface())
        finally:
            self._idle()
        self._update_3d_points()
        if volume is not None:
            n = volume.shape
            sp = volume.spacing_mm
            self.ct_info.setText(f"{Path(path).name if path else 'CT (in memory)'}<br>"
                                 f"{n[0]} x {n[1]} x {n[2]} voxels, {sp[0]:.2f} x {sp[1]:.2f} x {sp[2]:.2f} mm<br>"
                                 f"HU {float(np.min(volume.hu)):.0f} to {float(np.max(volume.hu)):.0f}")
        else:
            self.ct_info.setText("No CT loaded")
        self._inputs_changed()

    def load_xray(self, path: str | Path, overrides: dict | None = None) -> None:
        """Load an X-ray through ``Logic.xray.load_xray`` with the geometry overrides (raises CarmRegError)."""
        from Logic.xray import load_xray

        overrides = dict(self.geometry_overrides if overrides is None else overrides)
        xray = load_xray(path, **_geometry_kwargs(overrides))
        self.set_xray_image(xray, str(path), overrides)

    def set_xray_image(self, xray, path: str | None = None, overrides: dict | None = None) -> None:
        first = self.xray is None or self.xray_path != path
        self.xray, self.xray_path = xray, path
        self.geometry_overrides = dict(overrides or {})
        if first or xray is None:
            self.xray_view.set_pixels(None if xray is None else xray.pixels)
        intr = getattr(xray, "intrinsics", None)
        self.xray_view.pixel_spacing_mm = intr.pixel_spacing_mm if intr else None
        self.geometry_panel.set_xray(xray, self.geometry_overrides)
        if xray is not None:
            cols, rows = xray.size_px
            modality = xray.meta.get("modality", "") if isinstance(xray.meta, dict) else ""
            geometry = (f"SDD {intr.sdd_mm:.0f} mm, {intr.pixel_spacing_mm[0]:.3f} mm pixels"
                        if intr else "<span style='color:#ffa94d'>geometry incomplete: see below</span>")
            self.xray_info.setText(f"{Path(path).name if path else 'X-ray (in memory)'}  {modality}<br>"
                                   f"{cols} x {rows} px, bone {'dark' if xray.bone_dark else 'bright'}<br>"
                                   f"{geometry}")
        else:
            self.xray_info.setText("No X-ray loaded")
        self._inputs_changed()

    def apply_geometry(self, overrides: dict) -> None:
        """Re-read the X-ray with new geometry overrides (the logic decides and records the sources)."""
        if self.xray is None:
            raise InputFileError("load an X-ray before setting its geometry")
        if self.xray_path:
            self.load_xray(self.xray_path, overrides)
            return
        from Logic.camera import CarmIntrinsics  # in-memory image (tests, scripts): same rules, no file

        intr = self.xray.intrinsics
        kw = _geometry_kwargs(overrides)
        spacing = kw.get("pixel_spacing_mm") or (intr.pixel_spacing_mm if intr else None)
        sdd = kw.get("sdd_mm") or (intr.sdd_mm if intr else None)
        new_intr = None
        if spacing is not None and sdd is not None:
            new_intr = CarmIntrinsics(float(sdd), tuple(spacing), self.xray.size_px, kw.get("principal_point_px"),
                                      sources={k: "manual" for k in kw})
        xray = dataclasses.replace(self.xray, intrinsics=new_intr, sod_mm=kw.get("sod_mm", self.xray.sod_mm))
        self.set_xray_image(xray, None, overrides)

    def load_sample_case(self) -> None:
        """Load the embedded sample: CT, X-ray (DICOM with geometry) and the centroids on both."""
        from Logic.resources import sample_case

        paths = sample_case()
        self.new_session(ask=False)
        self.load_ct(paths["ct"])
        self.geometry_overrides = {}
        self.load_xray(paths["xray"], {})
        self.import_ct_landmarks(paths["ct_landmarks"], undoable=False)
        self.import_xray_landmarks(paths["xray_landmarks"], undoable=False)
        self.undo_stack.clear()
        self._dirty = False
        self._update_title()
        self.statusBar().showMessage("Sample case loaded: CT T1-L1, simulated C-arm image, centroids on both", 8000)

    # =========================================================================================== landmarks
    def import_ct_landmarks(self, path: str | Path, undoable: bool = True) -> None:
        marks = read_landmarks_3d(path)
        self.ct_store.replace_all(marks.labels, marks.points_lps_mm, f"Import {Path(path).name}", undoable)

    def import_xray_landmarks(self, path: str | Path, undoable: bool = True) -> None:
        spacing = self.xray.intrinsics.pixel_spacing_mm if getattr(self.xray, "intrinsics", None) else None
        marks = read_landmarks_2d(path, spacing)
        self.xray_store.replace_all(marks.labels, marks.uv_px, f"Import {Path(path).name}", undoable)

    def export_ct_landmarks(self, path: str | Path) -> Path:
        marks = self.ct_store.to_landmarks()
        if not marks.labels:
            raise LandmarkError("there are no named CT centroids to export; place some first (step 2)")
        return write_landmarks_3d(path, marks)

    def export_xray_landmarks(self, path: str | Path) -> Path:
        marks = self.xray_store.to_landmarks()
        if not len(marks.labels):
            raise LandmarkError("there are no X-ray centroids to export; place some first (step 3)")
        spacing = self.xray.intrinsics.pixel_spacing_mm if getattr(self.xray, "intrinsics", None) else None
        return write_landmarks_2d(path, marks, spacing)

    def propose_centroids(self, label_map_path: str | Path, mode: str = "replace") -> list[str]:
        """Centroids of the complete vertebrae of a label map on this CT (``Logic.vertebrae``)."""
        from Logic.io_volume import load_volume
        from Logic.vertebrae import CARMREG_VERTEBRAE, TOTALSEGMENTATOR_V2_VERTEBRAE, centroids_from_labels

        labels_volume = load_volume(label_map_path)
        labels = np.rint(np.asarray(labels_volume.hu, np.float32)).astype(np.int32)
        convention = CARMREG_VERTEBRAE if labels.max() <= max(CARMREG_VERTEBRAE) else TOTALSEGMENTATOR_V2_VERTEBRAE
        marks = centroids_from_labels(labels, labels_volume.ijk_to_lps, convention, source=str(label_map_path))
        if mode == "add":
            have = set(self.ct_store.labels())
            existing = [(p.label, p.position) for p in self.ct_store.points()]
            new = [(lb, p) for lb, p in zip(marks.labels, marks.points_lps_mm, strict=True) if lb not in have]
            merged = existing + new
            self.ct_store.replace_all([m[0] for m in merged], [m[1] for m in merged], "Add proposed centroids")
        else:
            self.ct_store.replace_all(marks.labels, marks.points_lps_mm, "Propose centroids from label map")
        return list(marks.labels)

    def set_place_mode(self, on: bool) -> None:
        for panel in (self.ct_panel, self.xray_panel):
            panel.place_check.setChecked(bool(on))
        self.act_place.setChecked(bool(on))

    def set_ct_window(self, name: str) -> None:
        for view in self.slice_views:
            view.set_window_preset(name)

    def _landmarks_changed(self) -> None:
        self._points3d_timer.start()
        self._inputs_changed(reset_overlay=False)
        if self.result is not None:
            self.overlay_view.clicks = self.xray_store.to_landmarks().as_dict()
            self.overlay_view.refresh_markers()

    def _ct_selected(self, point_id) -> None:
        point = self.ct_store.get(point_id) if point_id is not None else None
        if point is not None:
            self._go_to(point.position)
        self._points3d_timer.start()

    def _go_to(self, lps) -> None:
        for view in self.slice_views:
            view.go_to(lps)

    def _update_3d_points(self) -> None:
        points = [(p.label, p.position) for p in self.ct_store.points() if p.label]
        sel = self.ct_store.get(self.ct_store.selected) if self.ct_store.selected else None
        self.view3d.set_points(points, sel.label if sel else None)

    # =========================================================================================== registration
    def _stages(self) -> tuple[str, ...]:
        try:
            return tuple(_registration_api().STAGES)
        except Exception:  # noqa: BLE001 - the panel still shows; running will report the problem
            return ("database", "spatial", "depth", "fine", "final_drr")

    def _metrics(self) -> tuple[str, ...]:
        try:
            from Logic.similarity import METRICS
            return tuple(METRICS)
        except Exception:  # noqa: BLE001
            return ("gc",)

    def registration_inputs(self):
        """(ct, ct_landmarks, xray, xray_landmarks) or a CarmRegError saying what is missing."""
        from Logic.errors import GeometryError

        if self.ct_volume is None:
            raise InputFileError("load a CT first (step 1)")
        if self.xray is None:
            raise InputFileError("load an X-ray first (step 1)")
        if self.xray.intrinsics is None:
            raise GeometryError("the X-ray geometry is incomplete: choose a device preset or enter the SDD and "
                                "pixel spacing (step 1)")
        return self.ct_volume, self.ct_store.to_landmarks(), self.xray, self.xray_store.to_landmarks()

    def registration_parameters(self):
        from Logic.resources import cache_dir

        api = _registration_api()
        chosen = self.registration_panel.parameters()
        return api.RegistrationParameters(metric=chosen["metric"],
                                          cache_dir=str(cache_dir()) if chosen["use_cache"] else None)

    def run_registration(self, wait: bool = False) -> None:
        """Run every stage on a worker thread; ``wait`` blocks until done (scripts, tests)."""
        api = _registration_api()
        inputs, params = self.registration_inputs(), self.registration_parameters()

        def job(logic, stage_done):
            state = logic.prepare(*inputs, params)
            for name in api.STAGES:
                stage_done(logic.run_stage(state, name))
            return state, logic.result(state)
        self.registration_panel.reset()
        self._start_worker(api.CarmRegLogic(), job, wait)

    def run_next_stage(self, wait: bool = False) -> None:
        """Run only the next stage (prepares the inputs on the first call)."""
        api = _registration_api()
        name = self.registration_panel.next_stage()
        if name is None:
            return
        state = self._reg_state
        inputs = None if state is not None else self.registration_inputs()
        params = None if state is not None else self.registration_parameters()

        def job(logic, stage_done):
            st = state if state is not None else logic.prepare(*inputs, params)
            stage_done(logic.run_stage(st, name))
            last = name == api.STAGES[-1]
            return st, (logic.result(st) if last else None)
        self._start_worker(api.CarmRegLogic(), job, wait)

    def cancel_registration(self) -> None:
        if self._worker is not None and self._worker.isRunning():
            self._worker.cancel()
            self.statusBar().showMessage("Cancelling after the current step...", 5000)

    def reset_registration(self) -> None:
        self._reg_state = None
        self.registration_panel.reset()
        self._update_readiness()

    def is_running(self) -> bool:
        return self._worker is not None and self._worker.isRunning()

    def _start_worker(self, logic, job, wait: bool) -> None:
        if self.is_running():
            raise RegistrationError("a registration is already running; wait for it or cancel it")
        worker = RegistrationWorker(logic, job, self)
        worker.progress.connect(self.registration_panel.set_progress)
        worker.stage_done.connect(self.registration_panel.stage_done)
        worker.succeeded.connect(self._worker_succeeded)
        worker.failed.connect(self._worker_failed)
        worker.finished.connect(self._worker_finished)
        self._worker = worker
        self.registration_panel.set_running(True)
        self.act_cancel.setEnabled(True)
        self.act_register.setEnabled(False)
        self.set_step(3)
        worker.start()
        if wait:
            self.wait_for_registration()

    def wait_for_registration(self, timeout_s: float = 600.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self._worker is not None and time.monotonic() < deadline:
            self._worker.wait(50)
            process_events()

    def _worker_succeeded(self, value) -> None:
        state, result = value
        self._reg_state = state
        if result is not None:
            self.set_result(result)
        else:
            self.registration_panel.set_running(False)

    @report_errors
    def _worker_failed(self, exc, details: str) -> None:
        self.registration_panel.set_running(False)
        if isinstance(exc, CancelledError):
            self.registration_panel.set_cancelled(str(exc))
            self._reg_state = None
            self.registration_panel.reset()
            self.statusBar().showMessage("Registration cancelled", 6000)
            return
        self.registration_panel.set_cancelled("failed")
        if isinstance(exc, CarmRegError):
            self.dialogs.error("CarmReg - registration", str(exc))
        else:
            LOG.error("registration failed\n%s", details)
            self.dialogs.error("CarmReg - unexpected error",
                               f"The registration failed unexpectedly: {exc.__class__.__name__}: {exc}", details)

    def _worker_finished(self) -> None:
        worker, self._worker = self._worker, None
        self.act_cancel.setEnabled(False)
        self.act_register.setEnabled(True)
        self._update_readiness()
        if worker is not None:
            worker.deleteLater()
        self.registration_finished.emit(self.result is not None and not self.result_stale)

    def set_result(self, result) -> None:
        """Show a RegistrationResult: overlay, per-level PDE, stage figures, C-arm in 3D."""
        self.result, self.result_stale = result, False
        clicks = self.xray_store.to_landmarks().as_dict()
        fine = next((s for s in result.stages if s.name == "fine"), None)
        summary = (f"mPDE {fine.mpde_mm:.2f} mm   " if fine and fine.mpde_mm is not None else "") + \
                  f"magnification {result.magnification:.2f}" + ("" if result.ok else "   CHECK FAILED")
        self.overlay_view.set_result(self.xray.pixels, self.xray.bone_dark, result.drr_line_integral,
                                     result.levels, clicks, summary)
        self.result_panel.set_result(result)
        self.registration_panel.set_result(result)
        g = result.geometry
        self.view3d_result.set_points([(p.label, p.position) for p in self.ct_store.points() if p.label])
        self.view3d_result.set_carm(g.source_lps_mm(result.pose), g.detector_corners_lps_mm(result.pose))
        self.last_result_summary = session_io.summarize_result(result)
        self._mark_dirty()
        self.set_step(4)
        self.result_ready.emit(result)

    def export_result(self, out_dir: str | Path) -> dict:
        """Write result.json, overlay.png, DRR, .tfm and figures through the logic; returns {name: path}."""
        if self.result is None:
            raise RegistrationError("there is no result to export yet: run the registration (step 4)")
        api = _registration_api()
        clicks = self.xray_store.to_landmarks().as_dict()
        saver = getattr(api.CarmRegLogic, "save_result", None)
        if saver is not None:
            try:
                paths = api.CarmRegLogic().save_result(self.result, out_dir, xray_pixels=self.xray.pixels,
                                                       clicked=clicks)
            except TypeError:
                paths = api.CarmRegLogic().save_result(self.result, out_dir)
        else:
            from Logic.report import save_result
            paths = save_result(self.result, out_dir, self.xray.pixels, clicks)
        if self.last_result_summary is not None:
            self.last_result_summary["out_dir"] = str(out_dir)
        self.statusBar().showMessage(f"Result written to {out_dir}", 8000)
        return dict(paths or {})

    # =========================================================================================== session
    def current_session(self) -> session_io.Session:
        return session_io.Session(
            ct_path=self.ct_path, xray_path=self.xray_path,
            geometry_overrides={k: v for k, v in self.geometry_overrides.items()},
            ct_points=self.ct_store.to_records(), xray_points=self.xray_store.to_records(),
            parameters=self.registration_panel.parameters(), last_result=self.last_result_summary)

    def save_session(self, path: str | Path) -> Path:
        path = Path(path)
        if not path.name.endswith(".json"):
            path = path.with_name(path.name + session_io.SESSION_SUFFIX)
        session_io.save_session(path, self.current_session())
        self.session_path = str(path)
        self._dirty = False
        self.undo_stack.setClean()
        self._update_title()
        self.statusBar().showMessage(f"Session saved to {path}", 6000)
        return path

    def open_session(self, path: str | Path) -> None:
        self.restore_session(session_io.load_session(path), str(path))

    def restore_session(self, session: session_io.Session, path: str | None, dirty: bool = False) -> None:
        """Load data and points from a Session; missing data files are reported, points are kept."""
        self.new_session(ask=False)
        problems = []
        if session.ct_path:
            try:
                self.load_ct(session.ct_path)
            except CarmRegError as exc:
                problems.append(str(exc))
        if session.xray_path:
            try:
                self.load_xray(session.xray_path, session.geometry_overrides)
            except CarmRegError as exc:
                problems.append(str(exc))
        self.geometry_overrides = dict(session.geometry_overrides)
        self.ct_store.replace_all([p["label"] for p in session.ct_points],
                                  [p["position_lps_mm"] for p in session.ct_points], undoable=False)
        self.xray_store.replace_all([p["label"] for p in session.xray_points],
                                    [p["uv_px"] for p in session.xray_points], undoable=False)
        metric = session.parameters.get("metric")
        if metric:
            self.registration_panel.metric_combo.setCurrentText(metric)
        self.last_result_summary = session.last_result
        self.undo_stack.clear()
        self.session_path = path
        self._dirty = dirty
        self._update_title()
        if problems:
            self.dialogs.error("CarmReg - session", "The session opened, but:\n" + "\n".join(problems))

    def new_session(self, ask: bool = True) -> bool:
        if ask and not self.maybe_save("Start a new session"):
            return False
        if self.is_running():
            self.cancel_registration()
            self.wait_for_registration(30)
        self.set_ct_volume(None)
        self.set_xray_image(None)
        self.geometry_overrides = {}
        for store in (self.ct_store, self.xray_store):
            store.replace_all([], [], undoable=False)
        self.undo_stack.clear()
        self.result, self.last_result_summary, self.session_path = None, None, None
        self.overlay_view.clear()
        self.result_panel.set_result(None)
        self.view3d_result.set_carm(None, None)
        self.reset_registration()
        self._dirty = False
        self._update_title()
        return True

    def is_dirty(self) -> bool:
        return self._dirty or not self.undo_stack.isClean()

    def maybe_save(self, what: str) -> bool:
        """Ask before discarding unsaved work: True to go on (saved or discarded), False to stop."""
        if not self.is_dirty():
            return True
        choice = self.dialogs.question("CarmReg", f"{what}: the session has unsaved changes. Save them first?",
                                       ("Save", "Discard", "Cancel"))
        if choice == "Save":
            return self._action_save() is not None
        return choice == "Discard"

    # ------------------------------------------------------------------------------------- autosave
    def autosave_now(self) -> Path | None:
        if not self.autosave_enabled:
            return None
        try:
            path = session_io.write_autosave(self.current_session(), folder=self.state_folder)
        except OSError as exc:
            self.autosave_label.setText(f"autosave failed: {exc}")
            return None
        self.autosave_label.setText(f"Autosaved {time.strftime('%H:%M:%S')}")
        return path

    def offer_recovery(self) -> bool:
        """If a previous run crashed, offer its autosave. Returns True when work was recovered."""
        found = session_io.find_recoverable(self.state_folder)
        if not found:
            return False
        newest = found[0]
        try:
            session = session_io.load_session(newest)
        except CarmRegError as exc:
            LOG.warning("unreadable autosave %s: %s", newest, exc)
            newest.unlink(missing_ok=True)
            return False
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(newest.stat().st_mtime))
        text = (f"CarmReg did not close normally ({when}). Recover the unsaved work?\n\n"
                f"CT: {session.ct_path or '-'}\nX-ray: {session.xray_path or '-'}\n"
                f"{len(session.ct_points)} CT point(s), {len(session.xray_points)} X-ray point(s)")
        choice = self.dialogs.question("CarmReg - recover work", text, ("Recover", "Discard", "Later"))
        if choice == "Later":
            return False
        if choice == "Recover":
            self.restore_session(session, None, dirty=True)
            self.autosave_now()
        for path in found:
            path.unlink(missing_ok=True)
        return choice == "Recover"

    def _mark_dirty(self) -> None:
        self._dirty = True
        self._update_title()
        if self.autosave_enabled:
            self._autosave_timer.start()

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
        if self._reg_state is not None and not self.is_running():
            self._reg_state = None
            self.registration_panel.reset()
        if self.result is not None and not self.result_stale:
            self.result_stale = True
            self.overlay_view.summary = "inputs changed since this result: register again"
            self.overlay_view.viewport().update()
        self._update_readiness()
        self._mark_dirty()

    def _update_readiness(self) -> None:
        missing = []
        if self.ct_volume is None:
            missing.append("a CT")
        if self.xray is None:
            missing.append("an X-ray")
        elif self.xray.intrinsics is None:
            missing.append("the X-ray geometry (step 1)")
        common = sorted(set(self.ct_store.labels()) & set(self.xray_store.labels()),
                        key=lambda lb: self.ct_store.labels().index(lb))
        if len(common) < 3:
            missing.append(f"at least 3 levels named on both CT and X-ray (now {len(common)}"
                           + (f": {', '.join(common)}" if common else "") + ")")
        if missing:
            self.registration_panel.set_ready(False, "Needs " + "; ".join(missing) + ".")
        else:
            self.registration_panel.set_ready(True, f"Ready: {len(common)} levels on both ({', '.join(common)}).")

    def _update_title(self) -> None:
        name = Path(self.session_path).name if self.session_path else "untitled session"
        self.setWindowTitle(f"CarmReg - {name}{' *' if self.is_dirty() else ''}")
        self.setWindowModified(self.is_dirty())

    def _busy(self, message: str) -> None:
        self.statusBar().showMessage(message)
        QtWidgets.QApplication.setOverrideCursor(QtCore.Qt.CursorShape.WaitCursor)
        process_events()

    def _idle(self) -> None:
        QtWidgets.QApplication.restoreOverrideCursor()
        self.statusBar().clearMessage()

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        if self.is_running():
            choice = self.dialogs.question("CarmReg", "A registration is running. Cancel it and quit?",
                                           ("Cancel and quit", "Keep running"))
            if choice != "Cancel and quit":
                event.ignore()
                return
            self.cancel_registration()
            self.wait_for_registration(30)
        if not self.maybe_save("Quit"):
            event.ignore()
            return
        self._autosave_timer.stop()
        if self.autosave_enabled:
            session_io.clear_autosave(folder=self.state_folder)
        for v3 in (self.view3d, self.view3d_result):
            v3.close_plotter()
        event.accept()

    def discard_and_close(self) -> None:
        """Close without asking and without keeping an autosave (scripts, screenshots, tests)."""
        if self.is_running():
            self.cancel_registration()
            self.wait_for_registration(30)
        self._dirty = False
        self.undo_stack.clear()
        self.close()

    # =========================================================================================== action slots
    @report_errors
    def _action_new(self, *_):
        self.new_session(ask=True)

    @report_errors
    def _action_open_session(self, *_):
        if not self.maybe_save("Open a session"):
            return
        path = self.dialogs.open_file("Open session", SESSION_FILTER)
        if path:
            self.open_session(path)

    @report_errors
    def _action_save(self, *_):
        if self.session_path:
            return self.save_session(self.session_path)
        return self._action_save_as()

    @report_errors
    def _action_save_as(self, *_):
        path = self.dialogs.save_file("Save session", SESSION_FILTER, self.session_path or "case.carmreg.json")
        return self.save_session(path) if path else None

    @report_errors
    def _action_load_ct(self, *_):
        path = self.dialogs.open_file("Load CT", VOLUME_FILTER)
        if path:
            self.load_ct(path)
            self.set_step(0)

    @report_errors
    def _action_load_ct_folder(self, *_):
        path = self.dialogs.open_dir("Load CT DICOM series folder")
        if path:
            self.load_ct(path)

    @report_errors
    def _action_load_xray(self, *_):
        path = self.dialogs.open_file("Load X-ray", XRAY_FILTER)
        if path:
            self.geometry_overrides = {}
            self.load_xray(path, {})

    @report_errors
    def _action_load_sample(self, *_):
        if self.maybe_save("Load the sample case"):
            self.load_sample_case()

    @report_errors
    def _action_geometry(self, overrides: dict):
        try:
            self.apply_geometry(overrides)
        except CarmRegError:
            self.geometry_panel.set_xray(self.xray, self.geometry_overrides)  # show what is really in force
            raise

    @report_errors
    def _action_import_ct(self, *_):
        path = self.dialogs.open_file("Import CT centroids", MRK_FILTER)
        if path:
            self.import_ct_landmarks(path)

    @report_errors
    def _action_import_xray(self, *_):
        path = self.dialogs.open_file("Import X-ray centroids", MRK_FILTER)
        if path:
            self.import_xray_landmarks(path)

    @report_errors
    def _action_export_ct(self, *_):
        path = self.dialogs.save_file("Export CT centroids", MRK_FILTER, "ct_centroids.mrk.json")
        if path:
            self.export_ct_landmarks(path)

    @report_errors
    def _action_export_xray(self, *_):
        path = self.dialogs.save_file("Export X-ray centroids", MRK_FILTER, "xray_centroids.mrk.json")
        if path:
            self.export_xray_landmarks(path)

    @report_errors
    def _action_propose_centroids(self, *_):
        if self.ct_volume is None:
            raise InputFileError("load the CT before proposing centroids from its label map")
        path = self.dialogs.open_file("Vertebra label map on this CT", VOLUME_FILTER)
        if not path:
            return
        mode = "replace"
        if len(self.ct_store):
            choice = self.dialogs.question("CarmReg", "Replace the CT points, or add only the missing levels?",
                                           ("Add missing", "Replace", "Cancel"))
            if choice == "Cancel":
                return
            mode = "add" if choice == "Add missing" else "replace"
        names = self.propose_centroids(path, mode)
        self.statusBar().showMessage(f"Proposed centroids: {', '.join(names)} (check each, Ctrl+Z undoes)", 8000)

    @report_errors
    def _action_delete_selected(self, *_):
        store = self.xray_store if self.view_tabs.currentIndex() == 1 else self.ct_store
        store.remove_selected()

    @report_errors
    def _action_register(self, *_):
        self.run_registration()

    @report_errors
    def _action_next_stage(self, *_):
        self.run_next_stage()

    @report_errors
    def _action_export_result(self, *_):
        path = self.dialogs.open_dir("Export result into folder")
        if path:
            self.export_result(path)

    @report_errors
    def _action_overlay_png(self, *_):
        path = self.dialogs.save_file("Save overlay view", "PNG image (*.png)", "overlay_view.png")
        if path:
            self.save_screenshot(path, "overlay")

    @report_errors
    def _action_screenshot_window(self, *_):
        path = self.dialogs.save_file("Save window screenshot", "PNG image (*.png)", "carmreg_window.png")
        if path:
            self.save_screenshot(path, "window")

    @report_errors
    def _action_screenshot_view(self, *_):
        view = {0: "ct", 1: "xray", 2: "result"}[self.view_tabs.currentIndex()]
        path = self.dialogs.save_file("Save view screenshot", "PNG image (*.png)", f"carmreg_{view}.png")
        if path:
            self.save_screenshot(path, view)

    def _action_about(self, *_):
        from Logic import __version__
        self.dialogs.info("About CarmReg",
                          f"CarmReg {__version__}\nRegisters a preoperative CT to an intraoperative C-arm X-ray "
                          "by vertebral centroids (hierarchical 3D-2D registration).\nWorld frame: CT patient "
                          "LPS mm. Detector pixels (u, v) = (column, row), centres at integers.\n"
                          "Research software: not for clinical decisions.")

    def _action_keys(self, *_):
        self.dialogs.info("Mouse and keys", KEYS_HELP)


KEYS_HELP = """Slice and X-ray views
  Left click: place the level shown in the picker (moves it if already placed)
  Left drag on a point: move it        Right click on a point: rename / delete
  Delete: delete the selected point    Esc: clear the selection
  Right drag: window / level            Middle drag or Shift+left drag: pan
  Wheel: next/previous slice (CT), zoom (X-ray)    Ctrl+wheel: zoom (CT)
  Up/Down, PageUp/PageDown: slices      F: fit the image
Window
  Ctrl+1..5: workflow steps   P: place mode   B / T: bone / soft-tissue window
  Ctrl+Z / Ctrl+Shift+Z: undo / redo   Ctrl+S: save session   Ctrl+R: register
  F12: screenshot of the window        Shift+F12: screenshot of the current view"""


def _geometry_kwargs(overrides: dict) -> dict:
    """The override fields ``load_xray`` takes (presets and bookkeeping keys left out)."""
    out = {}
    for name in session_io.GEOMETRY_FIELDS:
        value = overrides.get(name)
        if value is not None:
            out[name] = tuple(float(x) for x in value) if isinstance(value, (list, tuple)) else float(value)
    return out


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
