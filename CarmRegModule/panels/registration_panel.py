"""Registration controls: run all stages or one at a time, progress and cancel, mPDE per stage, convergence.

Stages (method paper; the order comes from ``carmreg.logic.registration.pipeline.STAGES``): ``database``
(coarse DRRs over Ty, Tz),
``spatial`` (similarity search -> Ty, Tz), ``levels`` (beyond the paper: identify or check the level names of
the X-ray clicks - every plausible assignment along the spine registered and scored by image similarity and
landmark fit), ``depth`` (source-detector search on intervertebral distances -> Tx), ``fine`` (CMA-ES on the
mPDE of the labelled centroids, 6 DOF), ``refine`` (image similarity + landmarks, 6 DOF), ``final_drr``
(full-resolution DRR at the found pose). mPDE = mean projection distance error on the detector, mm.
The ready line says which level-identification mode the clicks ask for (named, partly named, unnamed, image
only).
"""

from __future__ import annotations

import time

import numpy as np
from qtpy import QtCore, QtWidgets

from carmreg.logic.report.style import names_shown, status_ink
from carmreg.xray_settings import FIELD_CHOICES, POLARITY_CHOICES, STORAGE_CHOICES

STAGE_TITLES = {"database": "Preparing the DRR database", "spatial": "Finding the spine in the image",
                "levels": "Identifying the levels", "depth": "Estimating the magnification",
                "fine": "Fitting the clicked centres", "refine": "Refining on the image",
                "final_drr": "Rendering the final DRR"}
STAGES_ORDER = tuple(STAGE_TITLES)
METRIC_NAMES = {"gc": "Gradient correlation (GC)", "go": "Gradient orientation (GO)",
                "ncc": "Normalised cross-correlation (NCC)", "gi": "Gradient information (GI)",
                "mi": "Mutual information (MI)", "psnr": "Peak signal-to-noise ratio (PSNR)",
                "ssim": "Structural similarity (SSIM)"}
STAGE_NUMBERS = {"database": "1a", "spatial": "1b", "levels": "1c", "depth": "2", "fine": "3", "refine": "4",
                 "final_drr": ""}  # the method paper's stage numbers, kept in the table for the engineer
# Typical seconds per stage on this project's 2-core CPU (sample case, unnamed clicks, database cached; the
# database takes ~6 s when it has to be built): the time-left estimate scales them by how fast the finished
# stages ran on this machine.
STAGE_SECONDS = {"database": 1.0, "spatial": 0.7, "levels": 6.0, "depth": 0.05, "fine": 0.1, "refine": 1.5,
                 "final_drr": 0.4}


def time_left_s(stages: tuple[str, ...], done: dict[str, float], current: str | None, fraction: float,
                elapsed_in_current_s: float) -> float:
    """Seconds left, estimated: the typical seconds (``STAGE_SECONDS``) of the stages not done, the current one
    by its unfinished part, all scaled by actual/typical of the stages finished here (not the database, whose
    time depends on the cache; 1 before any finished). ``done`` = {stage: seconds it took}."""
    timed = {k: v for k, v in done.items() if k != "database"}
    typical = sum(STAGE_SECONDS.get(k, 1.0) for k in timed)
    scale = float(np.clip(sum(timed.values()) / typical, 0.25, 8.0)) if typical > 0 else 1.0
    left = sum(STAGE_SECONDS.get(k, 1.0) for k in stages if k not in done and k != current) * scale
    if current is not None:
        expected = STAGE_SECONDS.get(current, 1.0) * scale
        if 0.05 < fraction < 1.0 and elapsed_in_current_s > 0.5:
            expected = elapsed_in_current_s / fraction  # the stage's own pace once it has one
        left += max(expected - elapsed_in_current_s, 0.0)
    return left


def format_seconds(seconds: float) -> str:
    return f"about {seconds:.0f} s left" if seconds < 90 else f"about {seconds / 60:.0f} min left"


class ConvergencePlot(QtWidgets.QWidget):
    """mPDE (mm) of the best pose so far against cost evaluations of the fine stage (matplotlib).

    The optimiser minimises mPDE plus a small rotation prior, so this curve may rise slightly.

    ``convergence`` entries are (evaluations, best mPDE mm, ...) as the fine stage records them."""

    def __init__(self, parent=None):
        super().__init__(parent)
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
        from matplotlib.figure import Figure

        self.figure = Figure(figsize=(3.4, 2.1), dpi=100, facecolor="#2d3034")
        self.canvas = FigureCanvasQTAgg(self.figure)
        self.canvas.setMinimumHeight(170)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.canvas)
        self.axes = self.figure.add_subplot(111)
        self.points: list[tuple[float, float]] = []
        self.set_convergence([])

    def set_convergence(self, convergence) -> None:
        self.points = [(float(entry[0]), float(entry[1])) for entry in convergence]
        ax = self.axes
        ax.clear()
        ax.set_facecolor("#1e2023")
        for side in ax.spines.values():
            side.set_color("#8a8f96")
        ax.tick_params(colors="#c8ccd0", labelsize=7)
        ax.set_xlabel("cost evaluations", color="#c8ccd0", fontsize=8)
        ax.set_ylabel("mPDE of best pose (mm)", color="#c8ccd0", fontsize=8)
        ax.set_title("Fine stage convergence", color="#e9ecef", fontsize=9)
        if self.points:
            e, m = zip(*self.points, strict=True)
            ax.plot(e, m, color="#3fa7ff", lw=1.6)
            ax.scatter([e[-1]], [m[-1]], color="#ffd43b", s=14, zorder=3)
            if min(m) > 0 and max(m) / min(m) > 20:
                ax.set_yscale("log")
            ax.annotate(f"{m[-1]:.2f} mm", (e[-1], m[-1]), textcoords="offset points", xytext=(-40, 8),
                        color="#ffd43b", fontsize=8)
        else:
            ax.text(0.5, 0.5, "no fine stage yet", ha="center", va="center", color="#8a8f96",
                    transform=ax.transAxes, fontsize=8)
        ax.grid(True, color="#44484e", lw=0.5)
        self.figure.tight_layout(pad=0.6)
        self.canvas.draw_idle()


class RegistrationPanel(QtWidgets.QWidget):
    """Buttons, progress and per-stage figures (see module docstring)."""

    run_all_requested = QtCore.Signal()
    run_next_requested = QtCore.Signal()
    cancel_requested = QtCore.Signal()
    reset_requested = QtCore.Signal()

    def __init__(self, stages: tuple[str, ...], metrics: tuple[str, ...] = (), parent=None):
        super().__init__(parent)
        self.setObjectName("registration_panel")
        self.stages = tuple(stages)
        self.mode: str | None = None
        self._done: dict[str, object] = {}
        self._started = 0.0
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        heading = QtWidgets.QLabel("Register CT to X-ray")
        heading.setObjectName("heading")
        layout.addWidget(heading)
        self.ready_label = QtWidgets.QLabel()
        self.ready_label.setWordWrap(True)
        layout.addWidget(self.ready_label)

        form = QtWidgets.QFormLayout()
        self.metric_combo = QtWidgets.QComboBox()
        for key in list(metrics) or ["gc"]:
            self.metric_combo.addItem(METRIC_NAMES.get(key, key), key)
        self.metric_combo.setToolTip("Image similarity for finding the spine in the image (stage 1b); gradient "
                                     "correlation is the most reliable on C-arm images (README)")
        form.addRow("Similarity", self.metric_combo)
        self.metric_combo.currentIndexChanged.connect(lambda _i: self._done and self.reset_requested.emit())
        self.polarity_combo = self._setting(form, "X-ray polarity", "xray_polarity", POLARITY_CHOICES,
                                            "How the X-ray shows bone. CarmReg finds it from the image against the CT "
                                            "and says how clearly (Check step); set it only to override")
        self.storage_combo = self._setting(form, "X-ray storage", "xray_storage", STORAGE_CHOICES,
                                           "How a bone-dark X-ray stores its values. CarmReg takes what the DICOM "
                                           "states, else finds it from the image against the CT (Check step); set it "
                                           "only to override")
        self.field_combo = self._setting(form, "X-ray field", "xray_field", FIELD_CHOICES,
                                         "Where the beam reached the detector. CarmReg finds the exposed field (the "
                                         "collimator's or intensifier's shadow left out); choose the whole image when "
                                         "the field found leaves out anatomy")
        self.pincushion_check = QtWidgets.QCheckBox("Estimate an intensifier's pincushion from the image")
        self.pincushion_check.setChecked(True)
        self.pincushion_check.setToolTip("On a round field (an image intensifier's) with no Pincushion given (C-arm "
                                         "geometry), the image refinement estimates it and says how much; unchecked: "
                                         "a pinhole camera, as for a flat panel or an image already corrected")
        form.addRow("", self.pincushion_check)
        self.pincushion_check.toggled.connect(lambda _on: self._done and self.reset_requested.emit())
        self.cache_check = QtWidgets.QCheckBox("Reuse the DRR database cache")
        self.cache_check.setChecked(True)
        form.addRow("", self.cache_check)
        layout.addLayout(form)

        row = QtWidgets.QHBoxLayout()
        self.run_button = QtWidgets.QPushButton("Register (all stages)")
        self.run_button.setObjectName("primary")
        self.run_button.clicked.connect(self.run_all_requested)
        self.next_button = QtWidgets.QPushButton("Run next stage")
        self.next_button.clicked.connect(self.run_next_requested)
        self.cancel_button = QtWidgets.QPushButton("Cancel")
        self.cancel_button.clicked.connect(self.cancel_requested)
        self.cancel_button.setEnabled(False)
        row.addWidget(self.run_button, 2)
        row.addWidget(self.next_button, 1)
        row.addWidget(self.cancel_button, 1)
        layout.addLayout(row)

        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(True)
        self.progress.setFormat("idle")
        layout.addWidget(self.progress)
        self.stage_label = QtWidgets.QLabel(" ")
        self.stage_label.setObjectName("hint")
        layout.addWidget(self.stage_label)

        self.table = QtWidgets.QTableWidget(len(self.stages), 3)
        self.table.setHorizontalHeaderLabels(["Stage", "mPDE (mm)", "Time (s)"])
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.NoSelection)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.Stretch)
        for c in (1, 2):
            header.setSectionResizeMode(c, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.table.setFixedHeight(self.table.verticalHeader().defaultSectionSize() * (len(self.stages) + 1) + 6)
        layout.addWidget(self.table)
        self.plot = ConvergencePlot()
        layout.addWidget(self.plot)
        self.status_label = QtWidgets.QLabel()
        self.status_label.setWordWrap(True)
        self.status_label.setTextFormat(QtCore.Qt.TextFormat.RichText)
        layout.addWidget(self.status_label)
        self.reset_button = QtWidgets.QPushButton("Start over (forget stage results)")
        self.reset_button.clicked.connect(self.reset_requested)
        layout.addWidget(self.reset_button)
        layout.addStretch(1)
        self.reset()

    def _setting(self, form, label: str, name: str, choices: tuple, tip: str) -> QtWidgets.QComboBox:
        """A combo box of an X-ray setting ((key, words) ``choices``, the first the default) in ``form``; changing
        it after a registration asks for a fresh start, as every input does."""
        combo = QtWidgets.QComboBox()
        combo.setObjectName(name)
        for key, text in choices:
            combo.addItem(text, key)
        combo.setToolTip(tip)
        form.addRow(label, combo)
        combo.currentIndexChanged.connect(lambda _i: self._done and self.reset_requested.emit())
        return combo

    # ------------------------------------------------------------------------------------- state
    def parameters(self) -> dict:
        return {"metric": self.metric_combo.currentData() or self.metric_combo.currentText(),
                "polarity": self.polarity_combo.currentData() or "auto",
                "storage": self.storage_combo.currentData() or "auto",
                "field": self.field_combo.currentData() or "auto", "use_cache": self.cache_check.isChecked(),
                "estimate_pincushion": self.pincushion_check.isChecked()}

    def set_estimate_pincushion(self, on) -> None:
        """Whether an uncalibrated intensifier's pincushion is estimated (a session's choice; anything but False:
        yes)."""
        self.pincushion_check.setChecked(on is not False)

    def set_metric(self, key: str) -> None:
        """Choose the metric by its key (``gc``, ``ncc``, ...)."""
        index = self.metric_combo.findData(key)
        if index >= 0:
            self.metric_combo.setCurrentIndex(index)

    @staticmethod
    def _choose(combo: QtWidgets.QComboBox, key) -> None:
        """Choose ``key`` in an X-ray setting's combo (``_setting``); anything not offered (a session from an older
        CarmReg, a hand-edited one): its first choice, auto."""
        combo.setCurrentIndex(max(combo.findData(key if isinstance(key, str) else ""), 0))

    def set_polarity(self, key) -> None:
        """Choose the X-ray polarity setting (``POLARITY_CHOICES``)."""
        self._choose(self.polarity_combo, key)

    def set_storage(self, key) -> None:
        """Choose the X-ray storage setting (``STORAGE_CHOICES``)."""
        self._choose(self.storage_combo, key)

    def set_field(self, key) -> None:
        """Choose the X-ray field setting (``FIELD_CHOICES``)."""
        self._choose(self.field_combo, key)

    def set_ready(self, ready: bool, reason: str, mode: str | None = None) -> None:
        """Enable the run buttons; ``mode`` = the level-identification mode the clicks ask for."""
        self.mode = mode
        self.ready_label.setText(reason)
        self.ready_label.setObjectName("ok" if ready else "warning")
        self.ready_label.setStyleSheet(f"color: {'#69db7c' if ready else '#ffa94d'};")
        self._ready = ready
        self._update_buttons(running=False)

    def reset(self) -> None:
        self._done = {}
        self._stage_started: dict[str, float] = {}
        for row, name in enumerate(self.stages):
            title = f"{STAGE_NUMBERS.get(name, ''):<3} {STAGE_TITLES.get(name, name)}"
            self.table.setItem(row, 0, QtWidgets.QTableWidgetItem(title))
            self.table.setItem(row, 1, QtWidgets.QTableWidgetItem("-"))
            self.table.setItem(row, 2, QtWidgets.QTableWidgetItem("-"))
        self.progress.setValue(0)
        self.progress.setFormat("idle")
        self.stage_label.setText(" ")
        self.plot.set_convergence([])
        self.status_label.setText("")
        self._ready = getattr(self, "_ready", False)
        self._update_buttons(running=False)

    def next_stage(self) -> str | None:
        return next((s for s in self.stages if s not in self._done), None)

    def set_running(self, running: bool) -> None:
        if running:
            self._started = time.perf_counter()
            self._stage_started = {}
            self.status_label.setText("")
        self._update_buttons(running)

    def _update_buttons(self, running: bool) -> None:
        ready = getattr(self, "_ready", False)
        nxt = self.next_stage()
        self.run_button.setEnabled(ready and not running)
        self.next_button.setEnabled(ready and not running and nxt is not None)
        title = STAGE_TITLES.get(nxt, nxt) or ""
        self.next_button.setText(f"Next: {title[:1].lower()}{title[1:]}" if nxt else "All stages done")
        self.next_button.setToolTip(f"Run only the next stage ({nxt})" if nxt else "")
        partial = bool(self._done) and nxt is not None
        self.run_button.setText("Register (continue)" if partial else "Register (all stages)")
        self.run_button.setToolTip("Run the stages not done yet; 'Start over' forgets the finished ones"
                                   if partial else "Run every stage")
        self.cancel_button.setEnabled(running)
        self.metric_combo.setEnabled(not running)
        self.polarity_combo.setEnabled(not running)
        self.storage_combo.setEnabled(not running)
        self.field_combo.setEnabled(not running)
        self.pincushion_check.setEnabled(not running)
        self.reset_button.setEnabled(not running and bool(self._done))

    def set_progress(self, stage: str, fraction: float, message: str) -> None:
        """The logic's progress(stage, fraction, message): the bar = time spent / (time spent + time left),
        its text the stage in plain words and its own progress ("labelling 3 of 7"), the time left below."""
        now = time.perf_counter()
        started = self._stage_started.setdefault(stage, now)
        elapsed = now - self._started if self._started else 0.0
        fraction = max(0.0, min(1.0, fraction))
        done = {k: v.seconds for k, v in self._done.items() if k != stage}
        left = time_left_s(self.stages, done, stage if fraction < 1.0 else None, fraction, now - started)
        spent = sum(done.values()) + (now - started)
        self.progress.setValue(int(1000 * min(spent / max(spent + left, 1e-6), 1.0)))
        detail = message if message and not message.startswith(stage) else f"{100 * fraction:.0f} %"
        self.progress.setFormat(f"{STAGE_TITLES.get(stage, stage)}: {detail}")
        self.stage_label.setText(f"{format_seconds(left)}   ({elapsed:.1f} s so far)")
        self.time_left_s = left

    def stage_done(self, stage) -> None:
        """Show one StageResult (name, mpde_mm, seconds, extra)."""
        self._done[stage.name] = stage
        row = self.stages.index(stage.name) if stage.name in self.stages else None
        if row is not None:
            self.table.setItem(row, 1, QtWidgets.QTableWidgetItem(
                "-" if stage.mpde_mm is None else f"{stage.mpde_mm:.2f}"))
            self.table.setItem(row, 2, QtWidgets.QTableWidgetItem(f"{stage.seconds:.1f}"))
            note = ", ".join(f"{k}: {v}" for k, v in (stage.extra or {}).items()
                             if isinstance(v, (int, float, str, bool)))
            self.table.item(row, 0).setToolTip(note)
        self._update_buttons(running=True)

    def set_cancelled(self, message: str) -> None:
        """Stopped (cancel or failure): the finished stages stay in the table and are kept for the next run."""
        kept = [STAGE_TITLES.get(k, k).lower() for k in self.stages if k in self._done]
        self.progress.setFormat("cancelled" if message != "failed" else "failed")
        nxt = self.next_stage()
        if kept and nxt is not None:
            message += (f"; kept {len(kept)} finished stage(s) - Register continues with "
                        f"{STAGE_TITLES.get(nxt, nxt).lower()}")
        self.stage_label.setText(message)
        self.set_running(False)

    def set_result(self, result) -> None:
        self.plot.set_convergence(result.convergence or [])
        self.progress.setValue(1000)
        self.progress.setFormat("done")
        self.stage_label.setText(f"finished in {sum(s.seconds for s in result.stages):.1f} s (stage time)")
        from carmreg.logic.report.page import drawn_mpde_mm

        total = sum(s.seconds for s in result.stages)
        drawn = drawn_mpde_mm(result.levels)
        head = ("<b style='color:#69db7c'>Registered</b>" if result.ok
                else "<b style='color:#ff8787'>Registration check failed</b>")
        text = head + (f" - mPDE {drawn:.2f} mm at the pose drawn" if drawn is not None else "")
        text += f", magnification {result.magnification:.2f}, {total:.1f} s in total."
        text += level_check_html(getattr(result, "level_check", None))
        if result.warnings:
            text += "<ul style='margin-left:-20px'>" + "".join(f"<li style='color:#ffa94d'>{w}</li>"
                                                            for w in result.warnings) + "</ul>"
        self.status_label.setText(text)
        self.set_running(False)

    def mpde_by_stage(self) -> dict[str, float | None]:
        return {name: stage.mpde_mm for name, stage in self._done.items()}


def level_check_html(check) -> str:
    """One line on the level names (``LevelCheck`` or None): status (coloured), assigned names, margin over the
    runner-up; on a refused X-ray (``style.names_shown``) that no level is named, and no labelling."""
    if not check:
        return ""
    if not names_shown(check):
        return f"<br>Level names: <b style='color:{status_ink('contradicted')}'>none named</b> (the X-ray was refused)."
    from .result_panel import format_margin

    colour = status_ink(check.status)
    text = f"<br>Level names: <b style='color:{colour}'>{check.status}</b>"
    if check.assigned_labels:
        text += f" ({', '.join(check.assigned_labels)})"
    text += f", margin {format_margin(check.margin)}"
    runner_up = check.runner_up_labels
    if runner_up:
        text += f" over {', '.join(runner_up)}"
    return text + "."
