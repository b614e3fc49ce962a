"""C-arm geometry editor: SDD, detector pixel spacing, principal point, SOD, an image intensifier's calibrated
pincushion, device presets, value sources.

Values shown are those the X-ray carries after the user's overrides; the right-hand column says where each
came from (DICOM tag, preset, entered by hand, default). Editing a field or choosing a preset emits
``overrides_changed(dict)``; the window then reloads the X-ray through ``carmreg.logic.io.xray.load_xray`` with those
overrides, so the logic, not the widget, decides what the geometry is.
"""

from __future__ import annotations

from qtpy import QtCore, QtWidgets

from carmreg.logic.geometry.camera import DEFAULT_SOD_FRACTION, MAX_DISTORTION_MM, nominal_sod_mm

from ..presets import DevicePreset, list_presets

NOT_SET = "not set"


def _spin(minimum: float, maximum: float, decimals: int, suffix: str, special: str | None = None):
    box = QtWidgets.QDoubleSpinBox()
    box.setRange(minimum, maximum)
    box.setDecimals(decimals)
    box.setSuffix(suffix)
    box.setKeyboardTracking(False)
    box.setAccelerated(True)
    box.setButtonSymbols(QtWidgets.QAbstractSpinBox.ButtonSymbols.NoButtons)
    box.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight)
    if special:
        box.setSpecialValueText(special)
    box.setMinimumWidth(92)
    return box


class GeometryPanel(QtWidgets.QGroupBox):
    """The C-arm geometry form (see module docstring)."""

    overrides_changed = QtCore.Signal(dict)
    measure_distortion_requested = QtCore.Signal()

    def __init__(self, parent=None):
        super().__init__("C-arm geometry", parent)
        self.setObjectName("geometry_panel")
        self._presets: list[DevicePreset] = []
        try:
            self._presets = list_presets()
        except Exception:  # noqa: BLE001 - a broken preset file must not stop the app
            self._presets = []
        self._overrides: dict = {}
        self._xray = None
        self._updating = False
        self._build()
        self.set_xray(None, {})

    # ------------------------------------------------------------------------------------- layout
    def _build(self) -> None:
        grid = QtWidgets.QGridLayout(self)
        grid.setHorizontalSpacing(8)
        grid.setVerticalSpacing(5)
        self.preset_combo = QtWidgets.QComboBox()
        self.preset_combo.addItem("Choose a device preset...", None)
        for preset in self._presets:
            self.preset_combo.addItem(preset.name, preset.key)
            self.preset_combo.setItemData(self.preset_combo.count() - 1, preset.description,
                                          QtCore.Qt.ItemDataRole.ToolTipRole)
        self.preset_combo.activated.connect(self._preset_chosen)
        grid.addWidget(QtWidgets.QLabel("Device"), 0, 0)
        grid.addWidget(self.preset_combo, 0, 1, 1, 3)

        self.sdd = _spin(0.0, 3000.0, 1, " mm", NOT_SET)
        self.du = _spin(0.0, 10.0, 4, " mm", NOT_SET)
        self.dv = _spin(0.0, 10.0, 4, " mm", NOT_SET)
        self.u0 = _spin(-1.0, 20000.0, 1, " px")
        self.v0 = _spin(-1.0, 20000.0, 1, " px")
        self.pp_centre = QtWidgets.QCheckBox("detector centre")
        self.sod = _spin(0.0, 3000.0, 1, " mm", "auto (0.6 x SDD)")
        self.distortion = _spin(-MAX_DISTORTION_MM, MAX_DISTORTION_MM, 2, " mm")
        self.distortion.setToolTip("An image intensifier's pincushion, from the C-arm's distortion calibration: how "
                                   "far an image point 100 mm from the centre lies outward of where a distortion-"
                                   "free camera would show it. 0: none given; on a round field (an intensifier's) "
                                   "the registration then estimates it from the image and says so.")
        self.sources: dict[str, QtWidgets.QLabel] = {}
        rows = [("sdd_mm", "Source-detector (SDD)", [self.sdd]),
                ("pixel_spacing_mm", "Pixel spacing col, row", [self.du, self.dv]),
                ("principal_point_px", "Principal point u0, v0", [self.u0, self.v0]),
                ("sod_mm", "Source-isocentre (SOD)", [self.sod]),
                ("distortion_mm", "Pincushion at 100 mm (calibration)", [self.distortion])]
        for r, (name, text, boxes) in enumerate(rows, start=1):
            beside_title = name == "principal_point_px"  # its value row holds the 'detector centre' box
            grid.addWidget(QtWidgets.QLabel(text), 2 * r - 1, 0, 1, 2 if beside_title else 4)
            for c, box in enumerate(boxes):
                grid.addWidget(box, 2 * r, c)
                box.editingFinished.connect(lambda n=name: self._edited(n))
            source = QtWidgets.QLabel()
            source.setObjectName("hint")
            source.setWordWrap(True)
            self.sources[name] = source
            grid.addWidget(source, 2 * r - 1 if beside_title else 2 * r, 2, 1, 2)
        grid.addWidget(self.pp_centre, 6, 2, 1, 2)
        self.pp_centre.toggled.connect(self._centre_toggled)
        self.measure_button = QtWidgets.QPushButton("Measure the pincushion on a bead-grid X-ray...")
        self.measure_button.setToolTip("An X-ray of a plate of beads on a square grid at the intensifier's input, "
                                       "taken with this C-arm (carmreg calibrate-distortion)")
        self.measure_button.clicked.connect(self.measure_distortion_requested)
        grid.addWidget(self.measure_button, 11, 0, 1, 4)
        self.size_label = QtWidgets.QLabel()
        self.size_label.setObjectName("hint")
        self.size_label.setWordWrap(True)
        self.magnification_label = QtWidgets.QLabel()
        self.magnification_label.setObjectName("hint")
        grid.addWidget(self.size_label, 13, 0, 1, 4)
        grid.addWidget(self.magnification_label, 14, 0, 1, 4)
        self.reset_button = QtWidgets.QPushButton("Reset to values from the file")
        self.reset_button.clicked.connect(self.reset_overrides)
        grid.addWidget(self.reset_button, 15, 0, 1, 4)
        grid.setColumnStretch(2, 1)

    # ------------------------------------------------------------------------------------- state
    def presets(self) -> list[DevicePreset]:
        return list(self._presets)

    def overrides(self) -> dict:
        return dict(self._overrides)

    def set_xray(self, xray, overrides: dict) -> None:
        """Show the geometry of ``xray`` (an XrayImage or None) with the overrides that produced it."""
        self._xray, self._overrides = xray, dict(overrides or {})
        self._updating = True
        try:
            self._fill()
        finally:
            self._updating = False
        self.setEnabled(xray is not None)

    def _fill(self) -> None:
        xray, intr = self._xray, getattr(self._xray, "intrinsics", None)
        ov = self._overrides
        sdd = ov.get("sdd_mm", intr.sdd_mm if intr else 0.0)
        du, dv = ov.get("pixel_spacing_mm", intr.pixel_spacing_mm if intr else (0.0, 0.0))
        self.sdd.setValue(float(sdd or 0.0))
        self.du.setValue(float(du or 0.0))
        self.dv.setValue(float(dv or 0.0))
        size = xray.size_px if xray is not None else (0, 0)
        centre = ((size[0] - 1) / 2.0, (size[1] - 1) / 2.0)
        pp = ov.get("principal_point_px") or (intr.principal_point_px if intr else centre)
        self.u0.setValue(float(pp[0]))
        self.v0.setValue(float(pp[1]))
        at_centre = "principal_point_px" not in ov and (intr is None or
                                                         "principal_point_px" not in (intr.sources or {}))
        self.pp_centre.setChecked(bool(at_centre and abs(pp[0] - centre[0]) < 1e-6))
        self.u0.setEnabled(not self.pp_centre.isChecked())
        self.v0.setEnabled(not self.pp_centre.isChecked())
        sod = ov.get("sod_mm", getattr(xray, "sod_mm", None))
        self.sod.setValue(float(sod or 0.0))
        self.distortion.setValue(float(ov.get("distortion_mm", intr.distortion_mm if intr else 0.0) or 0.0))
        index = self.preset_combo.findData(ov.get("preset")) if ov.get("preset") else 0
        self.preset_combo.setCurrentIndex(max(index, 0))
        for name, label in self.sources.items():
            label.setText(self._source_text(name))
        self.size_label.setText(f"Detector: {size[0]} x {size[1]} px (columns x rows), from the image; every value "
                                "here is the file's as stored, whatever turn the X-ray is shown in"
                                if xray is not None else "Load an X-ray to see its geometry")
        if sdd and (sod or sdd):
            sod_eff = nominal_sod_mm(sdd, sod or None)  # 0 here = not set
            self.magnification_label.setText(f"Magnification at the isocentre: SDD / SOD = {sdd / sod_eff:.2f}"
                                             + ("" if sod else f" (SOD assumed {DEFAULT_SOD_FRACTION} x SDD)"))
        else:
            self.magnification_label.setText("Geometry incomplete: choose a device preset or enter SDD and "
                                              "pixel spacing")

    def _source_text(self, name: str) -> str:
        ov = self._overrides
        sources = dict(getattr(self._xray, "sources", {}) or {})
        intr = getattr(self._xray, "intrinsics", None)
        if intr is not None:
            sources = {**(intr.sources or {}), **sources}
        preset = self._preset(ov.get("preset"))
        if name in ov:
            text = f"preset: {preset.name}" if preset and name in ov.get("preset_fields", ()) else "entered by hand"
        elif name in sources:
            text = str(sources[name])
        elif name == "principal_point_px":
            text = "default: detector centre"
        elif name == "sod_mm" and getattr(self._xray, "sod_mm", None):
            text = "from the X-ray"
        elif name == "sod_mm":
            text = "default: 0.6 x SDD"
        else:
            text = NOT_SET
        warning = self._range_warning(name, preset)
        return text + (f"  <span style='color:#ffa94d'>{warning}</span>" if warning else "")

    def _range_warning(self, name: str, preset: DevicePreset | None) -> str:
        if preset is None or name not in ("sdd_mm", "sod_mm"):
            return ""
        lo, hi = preset.range(name)
        value = self.sdd.value() if name == "sdd_mm" else self.sod.value()
        if value and lo is not None and hi is not None and not lo <= value <= hi:
            return f"outside {preset.name} range {lo:g}-{hi:g} mm"
        return ""

    def _preset(self, key) -> DevicePreset | None:
        return next((p for p in self._presets if p.key == key), None)

    # ------------------------------------------------------------------------------------- edits
    def apply_preset(self, key: str) -> None:
        """Take SDD, pixel spacing (scaled to the image size) and SOD from a device preset."""
        preset = self._preset(key)
        if preset is None:
            return
        size = self._xray.size_px if self._xray is not None else None
        values = preset.geometry_for(size)
        ov = {k: v for k, v in self._overrides.items() if k in ("principal_point_px", "distortion_mm")}
        ov.update(values)
        ov["pixel_spacing_mm"] = list(values["pixel_spacing_mm"])
        ov["preset"] = key
        ov["preset_fields"] = ["sdd_mm", "pixel_spacing_mm", "sod_mm"]
        self._emit(ov)

    def set_value(self, name: str, value) -> None:
        """Programmatic edit of one field (same effect as typing it): sdd_mm, pixel_spacing_mm, ..."""
        ov = dict(self._overrides)
        if value is None:
            ov.pop(name, None)
        else:
            ov[name] = list(value) if isinstance(value, (list, tuple)) else float(value)
        fields = [n for n in ov.pop("preset_fields", []) if n != name]
        if fields:
            ov["preset_fields"] = fields
        else:
            ov.pop("preset", None)
        self._emit(ov)

    def reset_overrides(self) -> None:
        self._emit({})

    def _preset_chosen(self, index: int) -> None:
        key = self.preset_combo.itemData(index)
        if key:
            self.apply_preset(key)

    def _edited(self, name: str) -> None:
        if self._updating:
            return
        value = {"sdd_mm": self.sdd.value() or None,
                 "pixel_spacing_mm": [self.du.value(), self.dv.value()] if self.du.value() and self.dv.value()
                 else None,
                 "principal_point_px": None if self.pp_centre.isChecked() else [self.u0.value(), self.v0.value()],
                 "sod_mm": self.sod.value() or None,
                 "distortion_mm": self.distortion.value() or None}[name]
        current = self._overrides.get(name)
        if value == current or (value is not None and current is not None and
                                _close(value, current)):
            return
        shown = self._shown_from_file(name)
        if value is not None and shown is not None and _close(value, shown) and name not in self._overrides:
            return
        self.set_value(name, value)

    def _shown_from_file(self, name: str):
        intr = getattr(self._xray, "intrinsics", None)
        if name == "sod_mm":
            return getattr(self._xray, "sod_mm", None)
        if intr is None:
            return None
        return {"sdd_mm": intr.sdd_mm, "pixel_spacing_mm": list(intr.pixel_spacing_mm),
                "principal_point_px": list(intr.principal_point_px), "distortion_mm": intr.distortion_mm}[name]

    def _centre_toggled(self, checked: bool) -> None:
        self.u0.setEnabled(not checked)
        self.v0.setEnabled(not checked)
        if not self._updating:
            self.set_value("principal_point_px", None if checked else [self.u0.value(), self.v0.value()])

    def _emit(self, overrides: dict) -> None:
        self._overrides = dict(overrides)
        self.overrides_changed.emit(dict(overrides))


def _close(a, b) -> bool:
    import numpy as np
    try:
        return bool(np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=0, atol=1e-6))
    except (TypeError, ValueError):
        return False
