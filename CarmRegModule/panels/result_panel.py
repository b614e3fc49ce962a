"""Checking the result: overlay mode and blend, per-level projection distance errors, pose and P, export.

PDE (projection distance error) of a level = distance on the detector, mm, between its CT centroid projected
with the found P and the user's click on the X-ray. Fitted levels were used by the optimiser; the others are
an independent check of the level names and the pose.
"""

from __future__ import annotations

import numpy as np
from qtpy import QtCore, QtWidgets

from Logic.camera import POSE_NAMES

from ..overlay_images import MODES


class ResultPanel(QtWidgets.QWidget):
    """Controls for the OverlayView plus the numbers of the last result."""

    export_requested = QtCore.Signal()
    overlay_png_requested = QtCore.Signal()

    def __init__(self, overlay_view, parent=None):
        super().__init__(parent)
        self.setObjectName("result_panel")
        self.overlay = overlay_view
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        heading = QtWidgets.QLabel("Check the overlay")
        heading.setObjectName("heading")
        layout.addWidget(heading)

        box = QtWidgets.QGroupBox("Display")
        form = QtWidgets.QFormLayout(box)
        modes = QtWidgets.QHBoxLayout()
        self.mode_buttons = {}
        group = QtWidgets.QButtonGroup(self)
        for mode in MODES:
            button = QtWidgets.QRadioButton(mode.capitalize())
            button.toggled.connect(lambda on, m=mode: on and self.overlay.set_mode(m))
            group.addButton(button)
            modes.addWidget(button)
            self.mode_buttons[mode] = button
        self.mode_buttons["blend"].setChecked(True)
        form.addRow("Mode", modes)
        self.alpha_slider = QtWidgets.QSlider(QtCore.Qt.Orientation.Horizontal)
        self.alpha_slider.setRange(0, 100)
        self.alpha_slider.setValue(50)
        self.alpha_slider.valueChanged.connect(lambda v: self.overlay.set_alpha(v / 100.0))
        self.alpha_slider.setToolTip("0 = X-ray only, 100 = DRR only (also the edge strength)")
        form.addRow("X-ray  <->  DRR", self.alpha_slider)
        self.tiles_spin = QtWidgets.QSpinBox()
        self.tiles_spin.setRange(2, 32)
        self.tiles_spin.setValue(8)
        self.tiles_spin.valueChanged.connect(self.overlay.set_tiles)
        form.addRow("Checkerboard tiles", self.tiles_spin)
        self.names_check = QtWidgets.QCheckBox("Show level names and PDE")
        self.names_check.setChecked(True)
        self.names_check.toggled.connect(self._names_toggled)
        form.addRow("", self.names_check)
        layout.addWidget(box)

        self.table = QtWidgets.QTableWidget(0, 4)
        self.table.setHorizontalHeaderLabels(["Level", "Fitted", "PDE (mm)", "(u, v) px"])
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        header = self.table.horizontalHeader()
        for c in range(3):
            header.setSectionResizeMode(c, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(3, QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.table.setMinimumHeight(140)
        layout.addWidget(QtWidgets.QLabel("Every CT-labelled level, projected with the found pose:"))
        layout.addWidget(self.table, 1)
        self.pose_label = QtWidgets.QLabel("No result yet.")
        self.pose_label.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.pose_label.setStyleSheet("font-family: monospace; font-size: 9pt;")
        self.pose_label.setWordWrap(True)
        layout.addWidget(self.pose_label)
        row = QtWidgets.QHBoxLayout()
        self.export_button = QtWidgets.QPushButton("Export result folder...")
        self.export_button.setToolTip("result.json, overlay.png, DRR (PNG + NRRD), carm.tfm, convergence plot")
        self.export_button.clicked.connect(self.export_requested)
        self.png_button = QtWidgets.QPushButton("Save overlay view PNG...")
        self.png_button.clicked.connect(self.overlay_png_requested)
        row.addWidget(self.export_button)
        row.addWidget(self.png_button)
        layout.addLayout(row)
        self.set_result(None)

    def _names_toggled(self, on: bool) -> None:
        self.overlay.show_names = on
        self.overlay.refresh_markers()

    def set_result(self, result) -> None:
        has = result is not None
        self.export_button.setEnabled(has)
        self.png_button.setEnabled(has)
        self.table.setRowCount(0 if not has else len(result.levels))
        if not has:
            self.pose_label.setText("No result yet: run the registration (step 4).")
            return
        for row, level in enumerate(result.levels):
            pde = level.get("pde_mm")
            u, v = level["uv_px"]
            cells = [level["label"], "yes" if level.get("fitted") else "no",
                     "-" if pde is None else f"{pde:.2f}",
                     f"({u:.1f}, {v:.1f})" + ("" if level.get("in_image", True) else "  outside image")]
            for col, text in enumerate(cells):
                self.table.setItem(row, col, QtWidgets.QTableWidgetItem(text))
        pose = result.pose.as_dict()
        units = ["mm", "mm", "mm", "deg", "deg", "deg"]
        lines = ["  ".join(f"{n.split('_')[0]} {pose[n]:+7.2f} {u}" for n, u in zip(POSE_NAMES[i:i + 3],
                                                                                   units[i:i + 3], strict=True))
                 for i in (0, 3)]
        P = np.asarray(result.projection_matrix)
        scaled = P / np.abs(P[2, :3]).max()
        lines.append("P (LPS mm -> px), scaled:")
        lines += ["  [" + " ".join(f"{x:10.3f}" for x in r) + " ]" for r in scaled]
        self.pose_label.setText("\n".join(lines))
