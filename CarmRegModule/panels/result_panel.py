"""Checking the result: overlay mode and blend, per-level projection distance errors, pose and P, export.

PDE (projection distance error) of a level = distance on the detector, mm, between its CT centroid projected
with the found P and the user's click on the X-ray. Fitted levels were used by the optimiser; the others are
an independent check of the level names and the pose.

Level identification (``RegistrationResult.level_check``): which levels the X-ray clicks are, and how sure the
image makes that. ``mode`` says what was given (named, partly named, unnamed clicks, or none: image only);
``status`` is confident (green), ambiguous (amber) or contradicted (red); ``margin`` = how much better the
assigned labelling scores than the runner-up (larger = surer). Without clicks, the levels the found pose
puts in the image (``visible_labels``) are listed instead. "Accept assigned names" writes the assigned names
into the clicks (one undo step; the window does it).
"""

from __future__ import annotations

import html

import numpy as np
from qtpy import QtCore, QtGui, QtWidgets

from carmreg.logic.geometry.camera import POSE_NAMES
from carmreg.logic.registration.level_check import LevelCheck
from carmreg.logic.report.composite import MODES
from carmreg.logic.report.style import MODE_DESCRIPTION, status_ink, unsure_name

MAX_HYPOTHESES = 6
HYPOTHESES_TIP = ("The labellings tried, best first (bold: the image's choice). Score: image dissimilarity + "
                  "landmark misfit, lower is better. Similarity: GC at the labelling's pose; 'eq' where the equalised "
                  "X-ray agrees more, the image agreement the confidence rule judges")
RECORD_CAPTION = ("The labellings tried on the image as stored: a record of the contest, not an answer (the X-ray "
                  "was refused, no level is named)")


def _number(value, decimals: int) -> str:
    """A finite number with ``decimals`` places, else "-" (missing, inf or nan)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "-"
    return f"{v:.{decimals}f}" if np.isfinite(v) else "-"


def format_margin(margin) -> str:
    """The level check's margin as text ('inf' = no other labelling to compare with)."""
    if margin is None:
        return "-"
    margin = float(margin)
    if not np.isfinite(margin):
        return "no alternative labelling" if margin > 0 else "-"
    return f"{margin:+.3f}"


def ranked_hypotheses(check: LevelCheck) -> list[dict]:
    """The labellings considered, best first: the winner, the runner-up, then the registered ones by score (the
    refinement objective: lower is better), then those not registered (an implausible magnification). Each
    labelling once (its best fit): without clicks several starts can end on the same level."""
    winner = list(check.winner_labels or check.assigned_labels)
    runner_up = list(check.runner_up_labels or [])

    def key(h: dict):
        labels = list(h.get("labels") or [])
        score = h.get("score")
        rank = 0 if labels == winner else 1 if labels == runner_up else 2
        return rank, not h.get("refined", True), float("inf") if score is None else float(score)
    out, seen = [], set()
    for h in sorted(check.hypotheses, key=key):  # no clicks: several fits may land on one level
        labels = tuple(h.get("labels") or [])
        if labels not in seen:
            seen.add(labels)
            out.append(h)
    return out


def arrow_list(names: list[str], labels: list[str]) -> str:
    """'?1 → T10, ?2 → T11, T12' (a click keeps its shown name alone when the assigned one is the same)."""
    return ", ".join(lb if shown == lb else f"{shown} \u2192 {lb}" for shown, lb in zip(names, labels, strict=False))


class ResultPanel(QtWidgets.QWidget):
    """Controls for the OverlayView plus the numbers of the last result."""

    export_requested = QtCore.Signal()
    overlay_png_requested = QtCore.Signal()
    report_requested = QtCore.Signal()
    accept_names_requested = QtCore.Signal()
    turn_requested = QtCore.Signal(str)  # an ``image.turn.ORIENTATIONS`` name: show the X-ray so, register again

    def __init__(self, overlay_view, parent=None):
        super().__init__(parent)
        self.setObjectName("result_panel")
        self.overlay = overlay_view
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        heading = QtWidgets.QLabel("Check the overlay")
        heading.setObjectName("heading")
        layout.addWidget(heading)
        self.banner = QtWidgets.QLabel()
        self.banner.setObjectName("level_banner")
        self.banner.setWordWrap(True)
        self.banner.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.banner.setVisible(False)
        layout.addWidget(self.banner)

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
        layout.addWidget(self._level_box())

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
        self.export_button = QtWidgets.QPushButton("Result folder...")
        self.export_button.setToolTip("result.json, overlay.png, DRR (PNG + NRRD), carm.tfm, convergence plot")
        self.export_button.clicked.connect(self.export_requested)
        self.png_button = QtWidgets.QPushButton("Overlay PNG...")
        self.png_button.setToolTip("The overlay view as a PNG image")
        self.png_button.clicked.connect(self.overlay_png_requested)
        self.report_button = QtWidgets.QPushButton("Report PDF...")
        self.report_button.setToolTip("One page to keep: the overlay as shown, the level answer, named levels, "
                                      "pose, magnification, inputs and versions")
        self.report_button.clicked.connect(self.report_requested)
        row.addWidget(self.report_button)
        row.addWidget(self.export_button)
        row.addWidget(self.png_button)
        layout.insertLayout(2, row)  # under the heading and the level banner: never below the fold
        layout.insertWidget(2, self.accept_button)  # the one step on the level names, right under the banner
        self.turn_button = QtWidgets.QPushButton()
        self.turn_button.setObjectName("turn_xray")
        self.turn_button.setVisible(False)
        self.turn_button.clicked.connect(lambda: self.turn_requested.emit(self._turn_offered))
        self._turn_offered = ""
        layout.insertWidget(3, self.turn_button)  # the one step on a refused display
        self.set_result(None)

    def _level_box(self) -> QtWidgets.QGroupBox:
        box = QtWidgets.QGroupBox("Level identification")
        box.setObjectName("level_identification")
        form = QtWidgets.QFormLayout(box)
        self.level_mode_label = QtWidgets.QLabel("-")
        self.level_status_label = QtWidgets.QLabel("-")
        self.level_status_label.setObjectName("level_status")
        self.level_message_label = QtWidgets.QLabel("")
        self.level_margin_label = QtWidgets.QLabel("-")
        self.level_margin_label.setWordWrap(True)
        self.level_runner_up_label = QtWidgets.QLabel("-")
        self.level_assigned_label = QtWidgets.QLabel("-")
        for label in (self.level_mode_label, self.level_message_label, self.level_assigned_label,
                      self.level_runner_up_label):
            label.setWordWrap(True)
        for label in (self.level_message_label, self.level_assigned_label):
            label.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.level_margin_label.setToolTip("Score of the assigned labelling minus the runner-up's: larger = surer")
        form.addRow("Mode", self.level_mode_label)
        form.addRow("Status", self.level_status_label)
        form.addRow(self.level_message_label)
        form.addRow("Assigned", self.level_assigned_label)
        form.addRow("Margin", self.level_margin_label)
        form.addRow("Runner-up", self.level_runner_up_label)
        self.appearance_label = QtWidgets.QLabel("-")
        self.appearance_label.setWordWrap(True)
        self.appearance_label.setToolTip("How the X-ray shows bone and how clearly the image said so "
                                         "(result.json 'appearance'); override it in the Register step")
        form.addRow("X-ray", self.appearance_label)
        self.hypotheses_table = QtWidgets.QTableWidget(0, 4)
        self.hypotheses_table.setHorizontalHeaderLabels(["Labelling", "Score\n(lower better)", "Similarity",
                                                         "mPDE\n(mm)"])
        self.hypotheses_table.verticalHeader().setVisible(False)
        self.hypotheses_table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.hypotheses_table.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.NoSelection)
        header = self.hypotheses_table.horizontalHeader()
        header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.Stretch)
        for c in (1, 2, 3):
            header.setSectionResizeMode(c, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.hypotheses_table.setFixedHeight(
            self.hypotheses_table.verticalHeader().defaultSectionSize() * MAX_HYPOTHESES
            + header.sizeHint().height() + 6)
        self.hypotheses_table.setToolTip(HYPOTHESES_TIP)
        self.hypotheses_caption = QtWidgets.QLabel(RECORD_CAPTION)
        self.hypotheses_caption.setObjectName("hypotheses_caption")
        self.hypotheses_caption.setWordWrap(True)
        self.hypotheses_caption.setVisible(False)
        form.addRow(self.hypotheses_caption)
        form.addRow(self.hypotheses_table)
        self.accept_button = QtWidgets.QPushButton("Accept assigned names")
        self.accept_button.setToolTip("Name the X-ray clicks as assigned by the level identification (Ctrl+Z "
                                      "undoes)")
        self.accept_button.clicked.connect(self.accept_names_requested)
        return box  # the accept button sits at the top of the step (see __init__), shown when it can act

    def set_level_check(self, check: LevelCheck | None, click_names: list[str] | None = None) -> None:
        """Show ``result.level_check`` (None: no identification ran); ``click_names`` = the clicks as shown
        ('T10', '?1', ...) in the order the logic got them."""
        check = check or LevelCheck("", "")
        status = check.status or None
        colour = status_ink(status)
        self.level_status_color = colour if status else None
        mode = check.mode or None
        self.level_mode_label.setText(MODE_DESCRIPTION.get(mode, mode or "-"))
        self.level_status_label.setText(status.upper() if status else "-")
        self.level_status_label.setStyleSheet(f"color: {colour}; font-weight: bold;")
        message = check.message
        self.level_message_label.setText(message)
        self.level_message_label.setStyleSheet(f"color: {colour};" if status != "confident" else "")
        self.level_message_label.setVisible(bool(message))
        labels = list(check.assigned_labels)
        names = list(click_names or [])
        visible = list(check.visible_labels)
        if check.withheld:
            self.level_assigned_label.setText("none: the X-ray was refused")
        elif labels and len(names) == len(labels):
            self.level_assigned_label.setText(arrow_list(names, labels))
        elif labels:
            self.level_assigned_label.setText(", ".join(labels))
        else:  # no clicks: the levels the found pose puts in the image
            self.level_assigned_label.setText(f"in the image: {', '.join(visible)}" if visible else "-")
        margin = format_margin(check.margin) if status else "-"
        if status and margin.startswith(("+", "-")) and len(margin) > 1:
            from carmreg.logic.registration.level_confidence import ConfidenceRule

            t = ConfidenceRule().margin
            margin += (f"  (runner-up score minus this one: proposed from +{t:.3f}; never confident without clicks)"
                       if mode == "image_only" else
                       f"  (runner-up score minus this one: confident from +{t:.3f}, contradicted below -{t:.3f})")
        self.level_margin_label.setText(margin)
        runner_up = [] if check.withheld else check.runner_up_labels
        prefers = status == "contradicted" and mode in ("named", "partly_named")
        at_centre = " at the centre" if mode == "image_only" else ""  # no clicks: a pose, by its centre level
        self.level_runner_up_label.setText(("the image prefers " if prefers else "") + ", ".join(runner_up)
                                           + at_centre if runner_up else "-")
        self._set_hypotheses(check, labels)

    def _set_hypotheses(self, check: LevelCheck, labels: list[str]) -> None:
        """The labellings tried, best first, the image's choice in bold; on a refused X-ray (``withheld``) a record
        of the contest under a caption saying so, no row in bold (nothing there is an answer)."""
        record = bool(check.withheld)
        self.hypotheses_caption.setVisible(record)
        self.hypotheses_table.setToolTip(RECORD_CAPTION if record else HYPOTHESES_TIP)
        hypotheses = ranked_hypotheses(check)[:MAX_HYPOTHESES]
        self.hypotheses_table.setRowCount(len(hypotheses))
        winner = None if record else list(check.winner_labels or labels)
        for row, h in enumerate(hypotheses):
            registered = h.get("refined", True)
            names = ", ".join(h.get("labels") or []) or "-"
            cells = [f"{names} at the centre" if check.mode == "image_only" and names != "-" else names] + [
                _number(h.get(k), d) if registered else "-"
                for k, d in (("score", 3), ("similarity", 3), ("mpde_mm", 2))]
            agreement = h.get("agreement")
            if registered and agreement is not None and agreement > (h.get("similarity") or 0.0) + 5e-4:
                cells[2] += f" (eq {agreement:.3f})"  # the equalised image's GC (registration.agreement)
            if not registered:
                cells[1] = "not registered"
            elif h.get("stopped_at_evaluations"):  # early_stop: far behind, its search cut short
                cells[1] += f" (stopped at {h['stopped_at_evaluations']})"
            for col, text in enumerate(cells):
                item = QtWidgets.QTableWidgetItem(text)
                if list(h.get("labels") or []) == winner:
                    font = item.font()
                    font.setBold(True)
                    item.setFont(font)
                self.hypotheses_table.setItem(row, col, item)

    def set_turn_offer(self, orientation: str | None) -> None:
        """Offer "Show the X-ray <orientation> and register again" (a display refused as stored mirrored or
        rotated, ``orientation`` the window's X-ray orientation that shows it as the CT matches it); None hides it."""
        self._turn_offered = orientation or ""
        self.turn_button.setVisible(bool(orientation))
        if orientation:
            self.turn_button.setText(f"Show the X-ray {orientation.replace('-', ' ')} and register again")
            self.turn_button.setToolTip("The X-ray matches the CT best so turned: its display was stored mirrored or "
                                        "rotated. Turns the image and its points (step 1's X-ray orientation; "
                                        "Ctrl+Z undoes) and registers again")

    def set_accept_enabled(self, enabled: bool, reason: str = "", text: str | None = None) -> None:
        """Enable "Accept assigned names"; ``text`` relabels it (contradicted names: "Use the names the image
        supports: ...")."""
        self.accept_button.setEnabled(bool(enabled))
        self.accept_button.setVisible(bool(enabled))
        self.accept_button.setText(text or "Accept assigned names")
        self.accept_button.setObjectName("danger" if text else "")
        self.accept_button.setStyleSheet("QPushButton { background: #c92a2a; color: white; font-weight: bold; }"
                                         if text and enabled else "")
        self.accept_button.setToolTip(reason or "Name the X-ray clicks as assigned by the level identification "
                                                "(Ctrl+Z undoes)")

    def _names_toggled(self, on: bool) -> None:
        self.overlay.show_names = on
        self.overlay.refresh_markers()

    def set_banner(self, banner: tuple[str, str, str] | None) -> None:
        """The level answer (headline, reason, colour) as a coloured block at the top; None hides it."""
        self.banner_colour = banner[2] if banner else None
        if banner is None:
            self.banner.setVisible(False)
            return
        headline, reason, colour = banner
        ink = "black" if QtGui.QColor(colour).lightnessF() > 0.6 else "white"
        self.banner.setStyleSheet(f"QLabel#level_banner {{ background: {colour}; color: {ink}; padding: 6px; "
                                  "border-radius: 3px; }")
        # the headline only: the reason is the message in "Level identification" below, in the same colour
        self.banner.setText(f"<b style='font-size:12pt'>{html.escape(headline)}</b>")
        self.banner.setToolTip(reason)
        self.banner.setVisible(True)

    def set_stale(self, banner: tuple[str, str, str]) -> None:
        """The result shown no longer describes the inputs: the grey ``banner`` (``stale_banner``) and the level
        status greyed, "out of date" beside it."""
        from carmreg.logic.report.style import status_ink

        self.set_banner(banner)
        status = self.level_status_label.text()
        if status not in ("", "-") and not status.endswith("(OUT OF DATE)"):
            self.level_status_label.setText(f"{status} (OUT OF DATE)")
        self.level_status_label.setStyleSheet(f"color: {status_ink(None)}; font-weight: bold;")

    def set_appearance(self, appearance, turned: str = "as-stored") -> None:
        """Show ``result.appearance`` (polarity, how clearly, storage, orientation; ``turned``: the turn the X-ray
        was registered in, ``RegistrationResult.xray_turned``) or '-'."""
        if appearance is None:
            self.appearance_label.setText("-")
            self.appearance_label.setStyleSheet("")
            return
        self.appearance_label.setText(appearance.summary(turned))
        self.appearance_label.setStyleSheet("" if appearance.trusted else "color: #ffa94d;")

    def set_result(self, result, click_names: list[str] | None = None) -> None:
        has = result is not None
        self.set_banner(None)
        if has:
            from carmreg.logic.report.style import answer_banner

            self.set_banner(answer_banner(getattr(result, "level_check", None), bool(result.ok),
                                          list(getattr(result, "failed_checks", []))))
        restored = has and getattr(result, "restored", False)
        for button in (self.export_button, self.report_button):
            button.setEnabled(has and not restored)
            button.setToolTip(button.toolTip().split(" (reopened")[0] + (
                " (reopened from a session: register again to export)" if restored else ""))
        self.png_button.setEnabled(has)
        self.table.setRowCount(0 if not has else len(result.levels))
        self.set_level_check(getattr(result, "level_check", None) if has else None, click_names)
        self.set_appearance(getattr(result, "appearance", None) if has else None,
                            getattr(result, "xray_turned", "as-stored"))
        if not has:
            self.set_accept_enabled(False, "No result yet")
            self.pose_label.setText("No result yet: run the registration (step 4).")
            return
        check = getattr(result, "level_check", None)
        for row, level in enumerate(result.levels):
            pde = level.get("pde_mm")
            u, v = level["uv_px"]
            cells = [unsure_name(level["label"], check), "yes" if level.get("fitted") else "no",
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
