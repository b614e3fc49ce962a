"""Menus, toolbar and the slots behind them. Every slot catches errors and shows them (``report_errors``);
the work itself is done by the window's public methods, which the tests call directly."""

from __future__ import annotations

from qtpy import QtCore, QtGui, QtWidgets

from carmreg.logic.errors import CarmRegError, InputFileError

from .qt_common import report_errors

STEPS = ("Data", "CT points", "X-ray points", "Register", "Check")
VOLUME_FILTER = "CT volumes (*.nrrd *.nhdr *.nii *.nii.gz *.mha *.mhd *.dcm);;All files (*)"
XRAY_FILTER = "X-ray images (*.dcm *.dicom *.png *.tif *.tiff *.jpg *.jpeg);;All files (*)"
MRK_FILTER = "Slicer markups (*.mrk.json);;JSON (*.json);;All files (*)"
SESSION_FILTER = "CarmReg session (*.carmreg.json);;JSON (*.json)"


class WindowActions:
    """Mixin of CarmRegWidget: QActions, menus, toolbar and their slots."""

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
        self.act_name_levels = action("&Name the X-ray levels", lambda on: self.xray_store.set_naming(on), "N",
                                      "Off: X-ray clicks stay unnamed and CarmReg identifies their levels")
        self.act_name_levels.setCheckable(True)
        self.act_name_levels.setChecked(True)
        self.act_accept_names = action("&Accept assigned level names", self._action_accept_names, None,
                                       "Name the X-ray clicks as the level identification assigned them")
        self.act_accept_names.setEnabled(False)
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
        for a in (self.act_undo, self.act_redo, None, self.act_delete, self.act_place, self.act_name_levels):
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
        reg_menu.addSeparator()
        reg_menu.addAction(self.act_accept_names)
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
            self.geometry_panel.set_xray(self.xray_as_stored, self.geometry_overrides)  # what is really in force
            raise

    @report_errors
    def _action_orientation(self, index: int):
        try:
            self.set_xray_orientation(self.orientation_combo.itemData(index))
        except CarmRegError:
            self._show_xray(pixels_changed=False)  # the combo shows the orientation really in force
            raise

    @report_errors
    def _action_measure_distortion(self, *_):
        path = self.dialogs.open_file("Bead-grid X-ray of this C-arm", XRAY_FILTER)
        if path:
            cal = self.measure_distortion(path)
            text = cal.summary()
            self.dialogs.info("Pincushion measured", f"{text[0].upper()}{text[1:]}. It is now this X-ray's Pincushion.")

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
    def _action_accept_names(self, *_):
        self.accept_assigned_names(ask=True)

    @report_errors
    def _action_turn_and_register(self, orientation: str):
        self.turn_and_register(orientation)

    @report_errors
    def _action_next_stage(self, *_):
        self.run_next_stage()

    @report_errors
    def _action_export_result(self, *_):
        path = self.dialogs.open_dir("Export result into folder")
        if path:
            self.export_result(path)

    @report_errors
    def _action_report_pdf(self, *_):
        path = self.dialogs.save_file("Save the one-page report", "PDF (*.pdf)", "carmreg_report.pdf")
        if path:
            self.export_report(path)

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
        from carmreg.logic import __version__
        self.dialogs.info("About CarmReg",
                          f"CarmReg {__version__}\nRegisters a preoperative CT to an intraoperative C-arm X-ray "
                          "by vertebral centroids (hierarchical 3D-2D registration).\nWorld frame: CT patient "
                          "LPS mm. Detector pixels (u, v) = (column, row), centres at integers.\n"
                          "Research software: not for clinical decisions.")

    def _action_keys(self, *_):
        self.dialogs.info("Mouse and keys", KEYS_HELP)



KEYS_HELP = """Slice and X-ray views
  Left click: place the level shown in the picker (moves it if already placed);
              X-ray with "Name the levels" off: an unnamed click (?1, ?2, ... from the top)
  Left drag on a point: move it        Right click on a point: rename / delete
  Delete: delete the selected point    Esc: clear the selection
  Right drag: window / level            Middle drag or Shift+left drag: pan
  Wheel: next/previous slice (CT), zoom (X-ray)    Ctrl+wheel: zoom (CT)
  Up/Down, PageUp/PageDown: slices      F: fit the image
Window
  Ctrl+1..5: workflow steps   P: place mode   N: name the X-ray levels (off: unnamed clicks)
  B / T: bone / soft-tissue window
  Ctrl+Z / Ctrl+Shift+Z: undo / redo   Ctrl+S: save session   Ctrl+R: register
  F12: screenshot of the window        Shift+F12: screenshot of the current view"""

