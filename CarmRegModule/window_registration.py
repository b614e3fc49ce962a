"""Registration in the window: inputs from the current data, the worker thread, results shown in the views.

Stage by stage: the first ``run_next_stage`` prepares a state with ``CarmRegLogic.prepare``; each call runs one
stage on a worker thread; after the last stage ``CarmRegLogic.result`` builds the RegistrationResult. Any
change of data, geometry or landmarks drops the prepared state (the stages must be run again).

Level identification: the X-ray clicks go to the logic named, partly named, unnamed (label None) or not at all
(``xray_click_mode``). The result's ``level_check.assigned_labels`` names each click in the order the logic got
them; the window keeps the point ids of that order, so the views show ``?1 → T11`` and "Accept assigned names"
renames exactly those points (one undo step).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from carmreg.logic.errors import CancelledError, CarmRegError, GeometryError, InputFileError, RegistrationError
from carmreg.logic.io import session as session_io
from carmreg.logic.registration.preflight import MIN_CLICKS, click_mode
from carmreg.logic.report.style import names_shown
from carmreg.logic.similarity.metrics import METRICS

from .qt_common import process_events, report_errors
from .worker import RegistrationWorker

LOG = logging.getLogger("carmreg.gui")


def _registration_api():
    """The pipeline, imported on first use: it pulls in numba and scipy, which the window does not need to start."""
    from carmreg.logic.registration import pipeline
    return pipeline


class WindowRegistration:
    """Mixin of CarmRegWidget: run, cancel, show and export the registration."""

    # =========================================================================================== registration
    def _stages(self) -> tuple[str, ...]:
        return tuple(_registration_api().STAGES)

    def _metrics(self) -> tuple[str, ...]:
        return tuple(METRICS)

    def registration_inputs(self):
        """(ct, ct_landmarks, xray, xray_landmarks) or a CarmRegError saying what is missing."""
        if self.ct_volume is None:
            raise InputFileError("load a CT first (step 1)")
        if self.xray is None:
            raise InputFileError("load an X-ray first (step 1)")
        if self.xray.intrinsics is None:
            raise GeometryError("the X-ray geometry is incomplete: choose a device preset or enter the SDD and "
                                "pixel spacing (step 1)")
        self._input_click_ids = [p.id for p in self.xray_store.points()]  # the order of to_landmarks()
        return self.ct_volume, self.ct_store.to_landmarks(), self.xray, self.xray_store.to_landmarks()

    def min_xray_clicks(self) -> int:
        """Fewest X-ray clicks the logic registers with (``registration.preflight.MIN_CLICKS``); zero clicks is
        allowed too (image only)."""
        return MIN_CLICKS

    def xray_click_mode(self) -> str:
        """Level identification the X-ray clicks ask for (``registration.preflight.click_mode``): ``named``,
        ``partly_named``, ``unnamed`` or ``image_only``."""
        return click_mode(self.xray_store.to_landmarks())

    def registration_parameters(self):
        from carmreg.logic.resources import cache_dir

        api = _registration_api()
        chosen = self.registration_panel.parameters()
        values = {"metric": chosen["metric"], "polarity": chosen.get("polarity", "auto"),
                  "storage": chosen.get("storage", "auto"), "xray_field": chosen.get("field", "auto"),
                  "estimate_pincushion": chosen.get("estimate_pincushion", True),
                  "cache_dir": str(cache_dir()) if chosen["use_cache"] else None}
        values.update(self.parameter_overrides)
        return api.RegistrationParameters(**values)

    def run_registration(self, wait: bool = False) -> None:
        """Run every stage on a worker thread; ``wait`` blocks until done (scripts, tests). After a cancel the
        stages already finished are kept (same inputs): it continues with the next one."""
        api = _registration_api()
        partial = self._reg_state if self._reg_state is not None and self.registration_panel.next_stage() else None
        inputs = None if partial is not None else self.registration_inputs()
        params = None if partial is not None else self.registration_parameters()
        todo = [s for s in api.STAGES if partial is None or s not in self.registration_panel.mpde_by_stage()]

        def job(logic, stage_done):
            state = partial if partial is not None else logic.prepare(*inputs, params)
            self._running_state = state  # kept by a cancel (the finished stages are in it)
            for name in todo:
                stage_done(logic.run_stage(state, name))
            return state, logic.result(state)
        if partial is None:
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
            self._running_state = st
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
        self._running_state = None
        worker = RegistrationWorker(logic, job, self)
        worker.inputs_version = self.inputs_version
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
        current = self._worker is None or getattr(self._worker, "inputs_version", None) == self.inputs_version
        self._reg_state = state if current else None
        if result is not None:
            self.set_result(result)
            if not current:  # the user edited while it ran: show it, but say it is out of date
                self.mark_result_stale("inputs changed during the run")
        else:
            self.registration_panel.set_running(False)

    @report_errors
    def _worker_failed(self, exc, details: str) -> None:
        self.registration_panel.set_running(False)
        if isinstance(exc, CancelledError):
            current = getattr(self._worker, "inputs_version", None) == self.inputs_version
            state = getattr(self, "_running_state", None)
            if current and state is not None and state.stages:  # keep what was finished
                self._reg_state = state
                self._drop_unfinished_rows(state)
                self.registration_panel.set_cancelled("Cancelled")
            else:
                self._reg_state = None
                self.registration_panel.reset()
                self.registration_panel.set_cancelled("Cancelled")
            self.statusBar().showMessage("Registration cancelled; finished stages kept", 6000)
            return
        self.registration_panel.set_cancelled("failed")
        if isinstance(exc, CarmRegError):
            self.dialogs.error("CarmReg - registration", str(exc))
        else:
            LOG.error("registration failed\n%s", details)
            self.dialogs.error("CarmReg - unexpected error",
                               f"The registration failed unexpectedly: {exc.__class__.__name__}: {exc}", details)

    def _drop_unfinished_rows(self, state) -> None:
        """The panel lists exactly the stages the kept state holds (a stage_done signal may still be queued)."""
        panel = self.registration_panel
        kept = {s.name: s for s in state.stages}
        panel.reset()
        for name in panel.stages:
            if name in kept:
                panel.stage_done(kept[name])
        panel.set_running(False)

    def _worker_finished(self) -> None:
        worker, self._worker = self._worker, None
        self.act_cancel.setEnabled(False)
        self.act_register.setEnabled(True)
        self._update_readiness()
        if worker is not None:
            worker.deleteLater()
        self.registration_finished.emit(self.result is not None and not self.result_stale)

    def set_result(self, result) -> None:
        """Show a RegistrationResult: overlay, per-level PDE, level identification, stage figures, C-arm in 3D."""
        from carmreg.logic.report.page import drawn_mpde_mm
        from carmreg.logic.report.style import answer_banner

        self.result, self.result_stale = result, False
        clicks = self.shown_clicks()
        drawn = drawn_mpde_mm(result.levels)  # the accuracy of the pose drawn (the final one), not of a stage
        summary = (f"mPDE {drawn:.2f} mm   " if drawn is not None else "") + \
            f"magnification {result.magnification:.2f}"
        check = getattr(result, "level_check", None)
        banner = answer_banner(check, bool(result.ok), list(getattr(result, "failed_checks", [])))
        appearance = getattr(result, "appearance", None)
        bone_dark = appearance.bone_dark if appearance is not None else self.xray.bone_dark
        self.overlay_view.set_result(self.xray.pixels, bone_dark, result.drr_line_integral,
                                     result.levels, clicks, summary, banner,
                                     status=check.status if check else None,
                                     names_withheld=not names_shown(check), mask=getattr(result, "field_mask", None))
        ids = self._result_click_ids(result)
        self._show_assigned(result, ids)
        self.result_panel.set_result(result, [self.xray_store.display_name(pid) for pid in ids])
        self._update_accept_names()
        self.registration_panel.set_result(result)
        g = result.geometry
        sizes = self.result_page.sizes()
        if sum(sizes) > 0:  # overlay 60 %, 3D 40 %: neither is squeezed after registering
            self.result_page.setSizes([int(0.6 * sum(sizes)), sum(sizes) - int(0.6 * sum(sizes))])
        self.view3d_result.set_points([(p.label, p.position) for p in self.ct_store.points() if p.label])
        self.view3d_result.set_carm(g.source_lps_mm(result.pose), g.detector_corners_lps_mm(result.pose))
        self.last_result_summary = session_io.summarize_result(result)
        self._mark_dirty()
        self.set_step(4)
        self.result_ready.emit(result)

    # =========================================================================================== level names
    def shown_clicks(self) -> dict:
        """{name as shown ('T11', '?1'): (u, v) px} of every X-ray click, for the overlay."""
        return {self.xray_store.display_name(p.id): p.position.copy() for p in self.xray_store.points()}

    def _result_click_ids(self, result) -> list[int]:
        """Point ids of the clicks ``level_check.assigned_labels`` names, in its order: the clicks as given
        to the logic, picked by ``level_check.click_indices`` (the logic leaves named clicks without a CT
        centroid out of the identification)."""
        ids = [pid for pid in self._input_click_ids if self.xray_store.get(pid) is not None]
        if len(ids) != len(self.xray_store):  # not from this window's inputs (scripts): the current order
            ids = [p.id for p in self.xray_store.points()]
        check = getattr(result, "level_check", None)
        indices = check.click_indices if check else None
        if indices is not None and all(0 <= i < len(ids) for i in indices):
            return [ids[i] for i in indices]
        return ids

    def _show_assigned(self, result, click_ids: list[int]) -> None:
        """Map ``level_check.assigned_labels`` onto the clicks and show it in the X-ray view and panel.
        When the image contradicts the given names, the names it supports (``supported_labels``) are shown and
        offered instead: ``T10 → T11`` in red."""
        check = getattr(result, "level_check", None) if result is not None else None
        labels = list(check.assigned_labels) if check else []
        matched = len(labels) == len(click_ids)
        if check and check.contradicted:
            labels = supported_labels(check)
        self.assigned_names = {pid: lb for pid, lb in zip(click_ids, labels, strict=True) if lb} if matched else {}
        if labels and not matched:
            LOG.warning("level check assigned %d names to %d clicks: not shown", len(labels), len(click_ids))
        self.xray_view.set_assigned(self.assigned_names, check.status if check else None)
        self.xray_panel.set_assigned(self.assigned_names)

    def clear_assigned_names(self) -> None:
        self._show_assigned(None, [])
        self._update_accept_names()

    def names_to_accept(self) -> dict[int, str]:
        """{point id: assigned level} of the clicks whose name would change on accepting."""
        out = {}
        for pid, label in self.assigned_names.items():
            point = self.xray_store.get(pid)
            if point is not None and point.label != label:
                out[pid] = label
        return out

    def _update_accept_names(self) -> None:
        if not hasattr(self, "act_accept_names"):
            return
        reason = ""
        if self.result is not None and self.result_stale:
            reason = "The clicks changed since this result: register again"
        elif self.result is not None and not names_shown(getattr(self.result, "level_check", None)):
            reason = "No level was named: the X-ray was refused (see the result)"
        elif self.result is None or not self.assigned_names:
            reason = "No level names were assigned: register first"
        elif not self.names_to_accept():
            reason = "The clicks already carry the assigned names"
        self.act_accept_names.setEnabled(not reason)
        check = self.result.level_check if self.result is not None else None
        contradicted = bool(check and check.contradicted)
        text = None
        if contradicted and not reason:
            text = "Use the names the image supports: " + ", ".join(
                sorted(set(self.names_to_accept().values()), key=_level_key))
            reason = "Rename the X-ray clicks to the names the image supports and register again (Ctrl+Z undoes)"
        self.result_panel.set_accept_enabled(self.act_accept_names.isEnabled(), reason, text)
        self.result_panel.set_turn_offer(self.refused_display_turn())

    def refused_display_turn(self) -> str | None:
        """The X-ray orientation the current result advises, having refused the display as mirrored or rotated
        (``outcome.advised_turn``); None without such a result, when the result is out of date or the X-ray gone,
        or when no orientation is that turn."""
        from carmreg.logic.registration.outcome import advised_turn

        if self.result is None or self.result_stale or self.xray_as_stored is None:
            return None
        return advised_turn(getattr(self.result, "appearance", None), getattr(self.result, "xray_turned", "as-stored"))

    def turn_and_register(self, orientation: str, wait: bool = False) -> None:
        """Show the X-ray in ``orientation`` (one undo step, its points with it) and register again
        (``run_registration``)."""
        self.set_xray_orientation(orientation)
        self.statusBar().showMessage(f"X-ray shown {orientation.replace('-', ' ')}; registering again. Ctrl+Z "
                                     "undoes the turn", 10000)
        self.run_registration(wait=wait)

    def accept_assigned_names(self, ask: bool = True, register: bool = True) -> dict[int, str]:
        """Name the X-ray clicks as the level identification assigned them (one undo step); returns the
        renamed {point id: level}. Unless confident, asks first when ``ask``. When the image contradicted the
        given names: ``use_supported_names`` (no question: the button says what it does)."""
        if self.result is not None and self.result_stale:
            raise RegistrationError("the X-ray clicks changed since this result: register again before accepting "
                                    "its level names")
        if self.result is None or not self.assigned_names:
            raise RegistrationError("there are no assigned level names to accept: register first (step 4)")
        changes = self.names_to_accept()
        if not changes:
            return {}
        check = self.result.level_check
        status = check.status if check else None
        if status == "contradicted":
            return self.use_supported_names(register)
        if ask and status != "confident":
            names = ", ".join(self.assigned_names.values())
            choice = self.dialogs.question(
                "CarmReg - level names",
                f"The level identification is {str(status).upper()}: {check.message if check else ''}\n\n"
                f"Name the clicks {names} anyway?", ("Accept anyway", "Cancel"))
            if choice != "Accept anyway":
                return {}
        self._accepting_names = True
        try:
            self.xray_store.rename_many(changes, "Accept assigned level names")
        finally:
            self._accepting_names = False
        self._update_accept_names()
        LOG.info("accepted assigned level names %s (%s)", changes, status)
        self.statusBar().showMessage(f"X-ray clicks named {', '.join(changes.values())} ({status}); Ctrl+Z undoes",
                                     8000)
        return changes

    def use_supported_names(self, register: bool = True) -> dict[int, str]:
        """One step for contradicted names: rename the clicks to the labelling the image supports (one undo
        step), which makes this result stale, then register again (``register``) so the overlay, the pose and
        the report follow the new names. Returns the renamed {point id: level}."""
        changes = self.names_to_accept()
        if not changes:
            return {}
        self.xray_store.rename_many(changes, "Use the names the image supports")
        LOG.info("renamed the clicks to the names the image supports: %s", changes)
        self.statusBar().showMessage(f"X-ray clicks renamed {', '.join(changes.values())} (the names the image "
                                     "supports); registering again. Ctrl+Z undoes", 10000)
        if register:
            self.run_registration()
        return changes

    def export_result(self, out_dir: str | Path) -> dict:
        """Write result.json, overlay.png, DRR, .tfm, figures and the 3D Slicer scene (slicer/CarmReg.mrml)
        through the logic, then the report page and the overlay as the view shows it (``overlay_view.png``);
        returns {name: path}."""
        if self.result is None:
            raise RegistrationError("there is no result to export yet: run the registration (step 4)")
        if getattr(self.result, "restored", False):
            raise RegistrationError("this result was reopened from a session without its DRR: register again "
                                    "(step 4) to export it")
        clicks = self.shown_clicks()
        paths = dict(_registration_api().CarmRegLogic().save_result(
            self.result, out_dir, xray_pixels=self.xray.pixels, clicked=clicks,
            ct=self.ct_volume, ct_landmarks=self.ct_store.to_landmarks()) or {})
        paths["report"] = self.export_report(Path(out_dir) / "report.pdf")  # the page as on screen
        paths["overlay_view"] = self.save_screenshot(Path(out_dir) / "overlay_view.png", "overlay")
        if self.last_result_summary is not None:
            self.last_result_summary["out_dir"] = str(out_dir)
        self.statusBar().showMessage(f"Result written to {out_dir}", 8000)
        return paths

    def export_report(self, path: str | Path) -> Path:
        """The one-page PDF report (``report.page``) with the overlay exactly as the view composites it now
        (mode, blend) and the clicks as shown."""
        from carmreg.logic.report.page import write_report_pdf

        if self.result is None:
            raise RegistrationError("there is no result to report yet: run the registration (step 4)")
        if getattr(self.result, "restored", False):
            raise RegistrationError("this result was reopened from a session without its DRR: register again "
                                    "(step 4) to write its report")
        path = write_report_pdf(path, self.result, self.xray.pixels, self.shown_clicks(),
                                composite_rgb=self.overlay_view.composite_rgb())
        self.statusBar().showMessage(f"Report written to {path}", 8000)
        return path



def _level_key(label: str) -> int:
    from carmreg.logic.io.landmarks import level_index

    return level_index(label)


def supported_labels(check) -> list[str]:
    """Per identified click (``assigned_labels`` order), the name the image supports: the winner labelling
    mapped onto the given one position by position along the spine (every labelling names the clicks in
    spine order; the given one is the hypothesis with the assigned names). The assigned names when there is
    no winner."""
    assigned = list(check.assigned_labels)
    winner = list(check.winner_labels)
    given = next((list(h["labels"]) for h in check.hypotheses
                  if sorted(h.get("labels") or []) == sorted(a for a in assigned if a)), None)
    if given is None:
        given = sorted((a for a in assigned if a), key=_level_key)
    if len(winner) != len(given):
        return assigned
    mapping = dict(zip(given, winner, strict=True))
    return [mapping.get(a, a) for a in assigned]
