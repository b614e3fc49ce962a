"""Session handling of the window: save/open (readable JSON via ``carmreg.logic.io.session``), new, unsaved-work
prompts, autosave after every change and recovery of the autosave a crashed run left behind."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from qtpy import QtGui

from carmreg.logic.errors import CarmRegError
from carmreg.logic.io import session as session_io
from carmreg.logic.registration.level_check import LevelCheck

LOG = logging.getLogger("carmreg.gui")


class WindowSession:
    """Mixin of CarmRegWidget: session file, dirty state, autosave and recovery, closing."""

    # =========================================================================================== session
    def current_session(self) -> session_io.Session:
        """The user's work as a Session; the X-ray points on the image as stored, with the orientation it is shown
        in."""
        xray_points = self.xray_store.to_records()
        if self.xray_as_stored is not None and xray_points:
            stored = self.xray_uv_as_stored([p["uv_px"] for p in xray_points])
            xray_points = [{**p, "uv_px": [float(x) for x in uv]} for p, uv in zip(xray_points, stored, strict=True)]
        return session_io.Session(
            ct_path=self.ct_path, xray_path=self.xray_path,
            geometry_overrides={k: v for k, v in self.geometry_overrides.items()},
            ct_points=self.ct_store.to_records(), xray_points=xray_points,
            xray_orientation=self.xray_orientation,
            parameters=self.registration_panel.parameters(),
            last_result=None if self.last_result_summary is None else {**self.last_result_summary,
                                                                       "stale": bool(self.result_stale)},
            session_file=self.session_path)

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
        """Load data and points from a Session; missing data files are reported, points are kept, and so are the
        missing files' paths and the X-ray's orientation: saved again, the session still names them, and the same X-ray
        file loaded later is shown turned as the session had it (``set_xray_image``)."""
        self.new_session(ask=False)
        problems = []
        if session.ct_path:
            try:
                self.load_ct(session.ct_path)
            except CarmRegError as exc:
                problems.append(str(exc))
                self.ct_path = session.ct_path
        if session.xray_path:
            try:
                self.load_xray(session.xray_path, session.geometry_overrides)
            except CarmRegError as exc:
                problems.append(str(exc))
                self.xray_path, self.xray_orientation = session.xray_path, session.xray_orientation
        self.geometry_overrides = dict(session.geometry_overrides)
        self.ct_store.replace_all([p["label"] for p in session.ct_points],
                                  [p["position_lps_mm"] for p in session.ct_points], undoable=False)
        uv_px = [p["uv_px"] for p in session.xray_points]
        if self.xray_as_stored is not None:
            self._apply_orientation(session.xray_orientation)
            uv_px = self.xray_uv_as_shown(np.reshape(uv_px, (-1, 2)))
        self.xray_store.replace_all([p["label"] for p in session.xray_points], uv_px, undoable=False)
        metric = session.parameters.get("metric")
        if metric:
            self.registration_panel.set_metric(metric)
        self.registration_panel.set_polarity(session.parameters.get("polarity"))
        self.registration_panel.set_storage(session.parameters.get("storage"))
        self.registration_panel.set_field(session.parameters.get("field"))
        self.registration_panel.set_estimate_pincushion(session.parameters.get("estimate_pincushion"))
        self.last_result_summary = session.last_result
        if session.last_result:
            try:
                self.show_saved_result(session.last_result)
            except (CarmRegError, KeyError, TypeError, ValueError) as exc:
                LOG.warning("the session's saved result cannot be shown: %s", exc)
        self.undo_stack.clear()
        self.session_path = path
        self._dirty = dirty
        self._update_title()
        if problems:
            self.dialogs.error("CarmReg - session", "The session opened, but:\n" + "\n".join(problems))

    def show_saved_result(self, summary: dict) -> bool:
        """Show a session's saved result (``session.summarize_result``) on the data just loaded: the overlay
        with every level projected by the saved P (no DRR: registering again recomputes it), the level answer,
        the pose and the numbers. Refused (False) when the X-ray or its geometry no longer give the saved P."""
        from carmreg.logic.geometry.camera import POSE_NAMES, CarmGeometry, CarmPose

        if self.xray is None or self.xray.intrinsics is None or summary.get("sod_mm") is None:
            return False
        pose = CarmPose.from_array([float(summary["pose"][n]) for n in POSE_NAMES])
        geometry = CarmGeometry(self.xray.intrinsics, tuple(float(x) for x in summary["isocenter_lps_mm"]),
                                float(summary["sod_mm"]))
        P, saved = geometry.projection_matrix(pose), np.asarray(summary["projection_matrix"], float)
        if P.shape != saved.shape or not np.allclose(P / np.abs(P).max(), saved / np.abs(saved).max(), atol=1e-9):
            LOG.warning("the saved result's projection matrix does not match the X-ray geometry: not shown")
            return False
        stages = [SavedStage(st["name"], st.get("mpde_mm"), float(st.get("seconds") or 0.0))
                  for st in summary.get("stages") or []]
        levels = [{"in_image": True, "clicked_uv_px": None, "name_margin": None, **lv}
                  for lv in summary.get("levels") or []]
        warnings = list(summary.get("warnings") or [])
        failed = summary.get("failed_checks")
        if failed is None:  # a session saved before the failed checks were recorded apart: its warnings, as then
            failed = [] if summary.get("ok") else warnings
        result = SavedResult(pose, P, geometry, stages, levels, bool(summary.get("ok")), warnings,
                             LevelCheck.from_dict(summary.get("level_check")), list(failed))
        self.set_result(result)
        if summary.get("stale"):
            self.mark_result_stale("inputs changed since this result")
        self.statusBar().showMessage("The session's last result is shown (without the DRR): register again to "
                                     "recompute it", 8000)
        return True

    def new_session(self, ask: bool = True) -> bool:
        if ask and not self.maybe_save("Start a new session"):
            return False
        self._stop_registration()
        self.set_ct_volume(None)
        self.set_xray_image(None)
        self.geometry_overrides = {}
        for store in (self.ct_store, self.xray_store):
            store.replace_all([], [], undoable=False)
        self.undo_stack.clear()
        self.result, self.last_result_summary, self.session_path = None, None, None
        self.overlay_view.clear()
        self.result_panel.set_result(None)
        self.clear_assigned_names()
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
        """If a previous run crashed, offer its autosave. Returns True when work was recovered.

        Never raises: an autosave that cannot be read or restored is set aside (renamed ``*.unreadable``,
        so it is not offered again at every start, yet kept for the user) and named in one dialog."""
        try:
            found = session_io.find_recoverable(self.state_folder)
        except OSError as exc:
            LOG.warning("cannot look for autosaves in %s: %s", self.state_folder, exc)
            return False
        if not found:
            return False
        newest = found[0]
        try:
            return self._recover(newest, found)
        except Exception as exc:  # noqa: BLE001 - a bad autosave must never stop the window from starting
            kept = session_io.set_aside(newest)
            LOG.warning("autosave %s could not be restored: %s", newest, exc)
            self.new_session(ask=False)
            message = str(exc) if isinstance(exc, CarmRegError) else f"{exc.__class__.__name__}: {exc}"
            self.dialogs.error("CarmReg - recover work", f"The work autosaved by a previous run could not be "
                               f"restored ({' '.join(message.split())[:300]}). It was set aside as {kept}.")
            return False

    def _recover(self, newest: Path, found: list[Path]) -> bool:
        session = session_io.load_session(newest)
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(newest.stat().st_mtime))
        text = (f"CarmReg did not close normally ({when}). Recover the unsaved work?\n\n"
                f"CT: {session.ct_path or '-'}\nX-ray: {session.xray_path or '-'}\n"
                f"{len(session.ct_points)} CT point(s), {len(session.xray_points)} X-ray point(s)")
        choice = self.dialogs.question("CarmReg - recover work", text, ("Recover", "Discard", "Later"))
        if choice == "Later":
            return False
        if choice == "Recover":  # keeps the session file name it belonged to (saved as autosave's session_file)
            self.restore_session(session, session.session_file, dirty=True)
            self.autosave_now()
        for path in found:
            path.unlink(missing_ok=True)
        return choice == "Recover"

    def _mark_dirty(self) -> None:
        self._dirty = True
        self._update_title()
        if self.autosave_enabled:
            self._autosave_timer.start()

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        if self.is_running():
            choice = self.dialogs.question("CarmReg", "A registration is running. Cancel it and quit?",
                                           ("Cancel and quit", "Keep running"))
            if choice != "Cancel and quit":
                event.ignore()
                return
            self._stop_registration()
        if not self.maybe_save("Quit"):
            event.ignore()
            return
        self._release_for_quit(keep_autosave=False)
        event.accept()

    def close_for_signal(self, signum: int) -> None:
        """Quit at once on a termination signal (``qt_signals``), asking nothing: a running registration is
        cancelled, unsaved work is written to the autosave (kept: the next start offers to recover it), and the
        application's event loops end with exit code 128 + ``signum`` (``quit_code``, for a signal that lands
        before the main loop runs)."""
        self.quit_code = 128 + int(signum)
        self._stop_registration()
        self._release_for_quit(keep_autosave=self._dirty)
        self.hide()
        self._end_application(self.quit_code)

    def _stop_registration(self) -> None:
        """Cancel a running registration and wait (up to 30 s) for its worker to end."""
        if self.is_running():
            self.cancel_registration()
            self.wait_for_registration(30)

    def _release_for_quit(self, keep_autosave: bool) -> None:
        """The last steps of quitting: no more autosave timer; the autosave written now and kept for recovery
        (``keep_autosave``) or removed (nothing unsaved: no recovery to offer); the 3D plotters closed."""
        self._autosave_timer.stop()
        if keep_autosave:
            self.autosave_now()
        elif self.autosave_enabled:
            session_io.clear_autosave(folder=self.state_folder)
        for v3 in (self.view3d, self.view3d_result):
            v3.close_plotter()

    @staticmethod
    def _end_application(code: int) -> None:
        """Every running event loop of the application ends, ``app.exec()`` returning ``code`` (and any later
        event loop in this process returns at once: Qt's ``QCoreApplication.exit``)."""
        from qtpy import QtWidgets

        QtWidgets.QApplication.instance().exit(code)

    def discard_and_close(self) -> None:
        """Close without asking and without keeping an autosave (scripts, screenshots, tests)."""
        self._stop_registration()
        self._dirty = False
        self.undo_stack.clear()
        self.close()



@dataclass
class SavedStage:
    name: str
    mpde_mm: float | None
    seconds: float
    extra: dict = field(default_factory=dict)


@dataclass
class SavedResult:
    """A registration result read back from a session (``session.summarize_result``): what the window shows,
    without the DRR and the figures; ``restored`` tells the export to ask for a new registration."""

    pose: object
    projection_matrix: np.ndarray
    geometry: object
    stages: list
    levels: list
    ok: bool
    warnings: list
    level_check: LevelCheck | None
    failed_checks: list = field(default_factory=list)
    drr_line_integral: None = None
    convergence: list = field(default_factory=list)
    restored: bool = True

    @property
    def magnification(self) -> float:
        return float(self.geometry.magnification(self.pose))
