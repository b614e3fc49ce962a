"""Landmark list and level picker for one PointStore (CT or X-ray centroids).

The picker shows the level the next click will place (it advances T11 -> T12 -> L1 after each click and
skips levels already placed). The table lists the points head to sacrum; its level column renames a point,
its row selects it (the views jump to it). Import/export buttons call the window's handlers.

With ``allow_unnamed`` (the X-ray panel) a "Name the levels" check box switches the store between named
clicks and unnamed ones (shown as ``?1``, ``?2``, ... top of the image first); an "Identified" column then
shows the level the registration assigned to each click (``set_assigned``).
"""

from __future__ import annotations

from qtpy import QtCore, QtWidgets

from carmreg.logic.errors import CarmRegError
from carmreg.logic.io.landmarks import LEVEL_NAMES

from ..qt_common import report_errors

UNNAMED = "(unnamed)"


class LandmarkPanel(QtWidgets.QWidget):
    """Picker + table + actions for one store."""

    import_requested = QtCore.Signal()
    export_requested = QtCore.Signal()
    propose_requested = QtCore.Signal()

    def __init__(self, store, title: str, hint: str, coordinates: str, parent=None, propose: bool = False,
                 allow_unnamed: bool = False):
        super().__init__(parent)
        self.store = store
        self.dialogs = None
        self.coordinates = coordinates
        self.allow_unnamed = allow_unnamed
        self.assigned: dict[int, str] = {}  # point id -> level the registration assigned
        self.setObjectName(f"landmarks_{store.name.replace(' ', '_').replace('-', '').lower()}")
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        heading = QtWidgets.QLabel(title)
        heading.setObjectName("heading")
        layout.addWidget(heading)
        tip = QtWidgets.QLabel(hint)
        tip.setObjectName("hint")
        tip.setWordWrap(True)
        layout.addWidget(tip)

        self.name_check = QtWidgets.QCheckBox("Name the levels")
        self.name_check.setChecked(store.naming)
        self.name_check.setToolTip("On: each click gets the level shown in the picker. Off: clicks stay unnamed "
                                   "(?1, ?2, ... from the top of the image) and CarmReg identifies their levels "
                                   "from the image. Naming only the levels you are sure of also works.")
        self.name_check.toggled.connect(store.set_naming)
        self.name_check.setVisible(allow_unnamed)
        layout.addWidget(self.name_check)
        picker = QtWidgets.QHBoxLayout()
        self.picker_label = QtWidgets.QLabel("Next click places")
        picker.addWidget(self.picker_label)
        self.level_combo = QtWidgets.QComboBox()
        self.level_combo.addItems(LEVEL_NAMES)
        self.level_combo.setMaxVisibleItems(16)
        self.level_combo.setCurrentText(store.pending_level)
        self.level_combo.currentTextChanged.connect(self._pick)
        picker.addWidget(self.level_combo)
        self.place_check = QtWidgets.QCheckBox("Place mode")
        self.place_check.setChecked(True)
        self.place_check.setToolTip("When on, a left click on the image places the level shown. "
                                    "Shift+click or turning this off lets the left button pan.")
        picker.addWidget(self.place_check)
        picker.addStretch(1)
        layout.addLayout(picker)

        self.mode_label = QtWidgets.QLabel()
        self.mode_label.setObjectName("hint")
        self.mode_label.setWordWrap(True)
        self.mode_label.setVisible(allow_unnamed)
        layout.addWidget(self.mode_label)

        headers = ["Level", coordinates] + (["Identified"] if allow_unnamed else []) + [""]
        self.delete_column = len(headers) - 1
        self.table = QtWidgets.QTableWidget(0, len(headers))
        self.table.setHorizontalHeaderLabels(headers)
        self.table.verticalHeader().setVisible(False)
        self.table.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        header = self.table.horizontalHeader()
        # the Level cells are combo boxes (cell widgets), which ResizeToContents ignores: a fixed width that
        # fits the longest entry, so T10, T11, T12 never read "T1" after the table fills from empty
        header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.Fixed)
        self.table.setColumnWidth(0, level_column_width())
        header.setSectionResizeMode(1, QtWidgets.QHeaderView.ResizeMode.Stretch)
        for column in range(2, len(headers)):
            header.setSectionResizeMode(column, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.table.itemSelectionChanged.connect(self._row_selected)
        self.table.setMinimumHeight(150)
        layout.addWidget(self.table, 1)
        self.count_label = QtWidgets.QLabel()
        self.count_label.setObjectName("hint")
        layout.addWidget(self.count_label)
        self.warning_label = QtWidgets.QLabel()
        self.warning_label.setObjectName("warning")
        self.warning_label.setWordWrap(True)
        self.warning_label.setStyleSheet("color: #ffa94d; font-weight: bold;")
        self.warning_label.setVisible(False)
        layout.addWidget(self.warning_label)

        buttons = QtWidgets.QGridLayout()
        self.delete_button = QtWidgets.QPushButton("Delete selected")
        self.delete_button.clicked.connect(self._delete_selected)
        self.clear_button = QtWidgets.QPushButton("Clear all")
        self.clear_button.clicked.connect(self._clear)
        self.import_button = QtWidgets.QPushButton("Import .mrk.json...")
        self.import_button.clicked.connect(self.import_requested)
        self.export_button = QtWidgets.QPushButton("Export .mrk.json...")
        self.export_button.clicked.connect(self.export_requested)
        buttons.addWidget(self.delete_button, 0, 0)
        buttons.addWidget(self.clear_button, 0, 1)
        buttons.addWidget(self.import_button, 1, 0)
        buttons.addWidget(self.export_button, 1, 1)
        if propose:
            self.propose_button = QtWidgets.QPushButton("Propose from vertebra label map...")
            self.propose_button.setToolTip("Compute the centroid of every complete vertebra in a label map "
                                           "(TotalSegmentator or CarmReg values) on this CT")
            self.propose_button.clicked.connect(self.propose_requested)
            buttons.addWidget(self.propose_button, 2, 0, 1, 2)
        layout.addLayout(buttons)

        store.changed.connect(self.refresh)
        store.selection_changed.connect(self._select_row)
        store.pending_level_changed.connect(self._pending_changed)
        store.naming_changed.connect(self._naming_changed)
        self._naming_changed(store.naming)
        self.refresh()

    # ------------------------------------------------------------------------------------- sync
    def refresh(self) -> None:
        points = self.store.points()
        numbers = self.store.unnamed_numbers()
        self.table.blockSignals(True)
        self.table.setRowCount(len(points))
        for row, point in enumerate(points):
            combo = QtWidgets.QComboBox()
            first = f"?{numbers[point.id]}" if point.id in numbers else UNNAMED
            combo.addItems([first] + LEVEL_NAMES)
            combo.setCurrentText(point.label or first)
            combo.setToolTip(f"{first}: unnamed click; choose a level to name it" if not point.label
                             else f"Rename {point.label}, or choose {UNNAMED} to leave its level to CarmReg")
            combo.currentTextChanged.connect(lambda text, pid=point.id: self._rename(pid, text))
            self.table.setCellWidget(row, 0, combo)
            coords = ", ".join(f"{x:.1f}" for x in point.position)
            item = QtWidgets.QTableWidgetItem(coords)
            item.setData(QtCore.Qt.ItemDataRole.UserRole, point.id)
            self.table.setItem(row, 1, item)
            if self.allow_unnamed:
                self.table.setItem(row, 2, QtWidgets.QTableWidgetItem(self._assigned_text(point)))
            remove = QtWidgets.QToolButton()
            remove.setText("x")
            remove.setToolTip(f"Delete {point.label or first}")
            remove.clicked.connect(lambda _=False, pid=point.id: self.store.remove(pid))
            self.table.setCellWidget(row, self.delete_column, remove)
        self.table.blockSignals(False)
        self._select_row(self.store.selected)
        names = self.store.labels()
        unnamed = len(numbers)
        text = f"{len(points)} point(s)" + (f": {', '.join(names)}" if names else "")
        if unnamed:
            text += (" + " if names else ": ") + f"{unnamed} unnamed"
        self.count_label.setText(text)

    def set_warnings(self, warnings: list[str]) -> None:
        """Plausibility warnings on the points (spine order, spacing); [] hides the line."""
        self.warning_label.setText("\n".join(f"\u26a0 {w}" for w in warnings))
        self.warning_label.setVisible(bool(warnings))

    def set_assigned(self, assigned: dict[int, str]) -> None:
        """Show the level the registration assigned to each click ({point id: level}); {} clears."""
        self.assigned = dict(assigned)
        self.refresh()

    def _assigned_text(self, point) -> str:
        name = self.assigned.get(point.id)
        if not name:
            return ""
        return name if point.label in (None, name) else f"{name} (named {point.label})"

    def _select_row(self, point_id) -> None:
        self.table.blockSignals(True)
        self.table.clearSelection()
        for row in range(self.table.rowCount()):
            item = self.table.item(row, 1)
            if item is not None and item.data(QtCore.Qt.ItemDataRole.UserRole) == point_id:
                self.table.selectRow(row)
        self.table.blockSignals(False)

    def _row_selected(self) -> None:
        rows = self.table.selectionModel().selectedRows()
        if rows:
            item = self.table.item(rows[0].row(), 1)
            self.store.select(item.data(QtCore.Qt.ItemDataRole.UserRole))

    def _pending_changed(self, label: str) -> None:
        self.level_combo.blockSignals(True)
        self.level_combo.setCurrentText(label)
        self.level_combo.blockSignals(False)

    def _pick(self, label: str) -> None:
        self.store.set_pending_level(label)

    def _naming_changed(self, on: bool) -> None:
        self.name_check.blockSignals(True)
        self.name_check.setChecked(on)
        self.name_check.blockSignals(False)
        self.level_combo.setEnabled(on)
        self.level_combo.setVisible(on)
        self.picker_label.setText("Next click places" if on else "Next click places an unnamed point")
        self.mode_label.setText(
            "Clicks get the level shown in the picker." if on else
            "Clicks stay unnamed (?1, ?2, ... from the top of the image); CarmReg identifies their levels from "
            "the image. Click at least 3 vertebral centres, or none to identify the levels from the image alone.")

    @report_errors
    def _rename(self, point_id, text: str) -> None:
        try:
            self.store.rename(point_id, None if text == UNNAMED or text.startswith("?") else text)
        except CarmRegError:
            QtCore.QTimer.singleShot(0, self.refresh)
            raise

    def _delete_selected(self) -> None:
        self.store.remove_selected()

    def _clear(self) -> None:
        if len(self.store):
            self.store.replace_all([], [], text="Clear landmarks")


def level_column_width() -> int:
    """Width (px) of the Level column: a combo box holding every entry it can show (``?12``, the unnamed
    entry, every level name), plus a margin."""
    probe = QtWidgets.QComboBox()
    probe.addItems(["?12", UNNAMED] + LEVEL_NAMES)
    probe.setSizeAdjustPolicy(QtWidgets.QComboBox.SizeAdjustPolicy.AdjustToContents)
    width = probe.sizeHint().width() + 6
    probe.deleteLater()
    return width
