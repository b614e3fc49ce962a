"""Issue 13, the surgeon's window: the accuracy shown is that of the pose drawn; contradicted names look wrong
and one step renames them; zoom stays about the cursor; the Level column fits its names; a reopened session
shows its result and a recovered one keeps its name; progress moves inside the levels stage and cancel keeps
the finished stages; the report page; the window at 1280 x 720 and 1920 x 1080.

Display tests use stand-in results (no pipeline); the progress/cancel test runs the real pipeline on the small
synthetic case with a short level search."""

import json
import os
import shutil

import numpy as np
import pytest
from gui_helpers import ready, scene_tolerance, view_pos, wheel
from qtpy import QtCore

from carmreg.logic.registration.level_check import LevelCheck

pytestmark = pytest.mark.gui
ARROW = "\u2192"


def _load_case(win, case):
    win.load_ct(case.ct_path)
    win.load_xray(case.xray_path)
    win.import_ct_landmarks(case.ct_landmarks_path)
    win.import_xray_landmarks(case.xray_landmarks_path)


def _named_result(win, names, pdes, status="confident", winner=None, fine_mpde=0.48):
    """A RegistrationResult stand-in for named clicks ``names`` (in the store's order) with a level check."""
    from types import SimpleNamespace

    from carmreg.logic.geometry.camera import CarmGeometry, CarmPose

    geometry = CarmGeometry(win.xray.intrinsics, (0.0, 0.0, 0.0), 600.0)
    pose = CarmPose(0, 0, 0, 0, 0, 0)
    clicks = {p.label: p.position for p in win.xray_store.points()}
    levels = [{"label": lb, "uv_px": [float(clicks[lb][0]) + 2, float(clicks[lb][1])], "fitted": True,
               "pde_mm": pde, "in_image": True, "clicked_uv_px": list(clicks[lb])}
              for lb, pde in zip(names, pdes, strict=True)]
    other = "L3" if "L3" not in names else "T9"  # a level not clicked
    levels.append({"label": other, "uv_px": [160.0, 250.0], "fitted": False, "pde_mm": None, "in_image": True})
    winner = list(winner or names)
    hypotheses = [{"labels": list(names), "score": 0.6 if winner != list(names) else 0.5, "refined": True,
                   "similarity": 0.4, "mpde_mm": 1.0},
                  {"labels": winner, "score": 0.5, "refined": True, "similarity": 0.5, "mpde_mm": 1.2}]
    message = {"confident": "level names agree with the image",
               "contradicted": f"level names CONTRADICTED: the image fits {', '.join(winner)} better than the "
                               f"names given ({', '.join(names)})"}[status]
    check = {"mode": "named", "status": status, "margin": -0.1 if status == "contradicted" else 0.1,
             "assigned_labels": list(names), "winner_labels": winner,
             "runner_up_labels": winner if status == "contradicted" else None, "message": message,
             "hypotheses": hypotheses, "visible_labels": [], "click_indices": list(range(len(names)))}
    stages = [SimpleNamespace(name="fine", mpde_mm=fine_mpde, seconds=0.1, extra={}),
              SimpleNamespace(name="refine", mpde_mm=float(np.mean(pdes)), seconds=1.0, extra={})]
    return SimpleNamespace(pose=pose, projection_matrix=geometry.projection_matrix(pose), geometry=geometry,
                           stages=stages, levels=levels, drr_line_integral=None, convergence=[],
                           ok=status != "contradicted", warnings=[] if status != "contradicted" else [message],
                           failed_checks=[] if status != "contradicted" else [message], magnification=1.6,
                           level_check=LevelCheck.from_dict(check))


def _three_named_clicks(win):
    for label, uv in (("T10", [140.0, 60.0]), ("T11", [150.0, 150.0]), ("T12", [160.0, 240.0])):
        win.xray_store.add(label, uv)


# ------------------------------------------------------------------------------------------- 1. accuracy

def test_the_accuracy_shown_is_that_of_the_pose_drawn_not_the_fine_stage(xray_window):
    win = xray_window
    _three_named_clicks(win)
    win.set_result(_named_result(win, ["T10", "T11", "T12"], [1.0, 2.0, 1.83], fine_mpde=0.48))
    header = win.overlay_view.corner_text()["tl"]
    assert "mPDE 1.61 mm" in header and "0.48" not in header  # mean PDE at the drawn pose: (1 + 2 + 1.83) / 3
    status = win.registration_panel.status_label.text()
    assert "mPDE 1.61 mm at the pose drawn" in status and "0.48" not in status
    assert win.overlay_view.corner_text()["tr"] == ""  # one stacked header: nothing to overprint


# ------------------------------------------------------------------------------------------- 2. wrong names

def test_contradicted_names_look_wrong_and_one_step_uses_the_names_the_image_supports(xray_window):
    win = xray_window
    _three_named_clicks(win)
    win.set_result(_named_result(win, ["T10", "T11", "T12"], [1.1, 0.9, 1.2], "contradicted",
                                 winner=["T11", "T12", "L1"]))
    # the overlay: fitted levels red with "?", never the green "fitted" look; a red banner across the top
    fitted = {s.key[1]: s for s in win.overlay_view.markers().values() if s.key[0] == "level" and s.style == "fitted"}
    assert set(fitted) == {"T10", "T11", "T12"}
    assert all(s.color == "#ff8787" and s.text.startswith(f"{k}?") for k, s in fitted.items())
    headline, reason, colour = win.overlay_view.banner
    assert headline.startswith("LEVEL NAMES CONTRADICTED") and colour == "#c92a2a" and "T11, T12, L1" in reason
    assert not win.overlay_view.banner_rect(QtCore.QRectF(0, 0, 800, 600)).isEmpty()
    rp = win.result_panel
    assert rp.banner.isVisibleTo(rp) and "CONTRADICTED" in rp.banner.text() and rp.banner_colour == "#c92a2a"
    # the X-ray shows what the image supports, and the button offers exactly that
    texts = sorted(spec.text for spec in win.xray_view.markers().values())
    assert texts == [f"T10 {ARROW} T11", f"T11 {ARROW} T12", f"T12 {ARROW} L1"]
    assert rp.accept_button.isEnabled()
    assert rp.accept_button.text().startswith("Use the names the image supports: T11, T12, L1")
    changed = win.accept_assigned_names(ask=True, register=False)  # no question: the button says what it does
    assert sorted(changed.values()) == ["L1", "T11", "T12"] and win.dialogs.messages == []
    assert sorted(win.xray_store.labels()) == ["L1", "T11", "T12"]
    assert win.result_stale  # registered with the old names: stale until registered again
    assert win.undo_stack.undoText().startswith("Use the names the image supports")
    win.undo_stack.undo()
    assert sorted(win.xray_store.labels()) == ["T10", "T11", "T12"]


def test_confident_names_stay_green_with_a_green_banner(xray_window):
    win = xray_window
    _three_named_clicks(win)
    win.set_result(_named_result(win, ["T10", "T11", "T12"], [1.0, 1.0, 1.0]))
    fitted = [s for s in win.overlay_view.markers().values() if s.key[0] == "level" and s.style == "fitted"]
    assert fitted and all(s.color == "#40c057" and "?" not in s.text for s in fitted)
    assert win.overlay_view.banner[2] == "#2b8a3e" and "CONFIRMED" in win.overlay_view.banner[0]
    assert win.result_panel.accept_button.text() == "Accept assigned names"


def test_a_refused_image_shows_no_level_name_and_offers_none(xray_window):
    """The X-ray refused (a mirrored display): the overlay draws its markers without names (whatever "Names"
    says), the banner says why in red, the level box names nothing and no names are offered."""
    win = xray_window
    _three_named_clicks(win)
    result = _named_result(win, ["T10", "T11", "T12"], [1.0, 1.0, 1.0])
    result.level_check.runner_up_labels = ["T11", "T12", "L1"]
    result.level_check = result.level_check.withheld_for("the display is mirrored or rotated")
    result.ok, result.warnings = False, ["the display is mirrored or rotated"]
    win.set_result(result)
    levels = [s for s in win.overlay_view.markers().values() if s.key[0] == "level"]
    assert len(levels) == 4 and all(s.text == "" for s in levels)
    headline, reason, colour = win.overlay_view.banner
    assert headline == "IMAGE REFUSED - NO LEVEL NAMED" and colour == "#c92a2a" and "mirrored" in reason
    rp = win.result_panel
    assert rp.level_assigned_label.text() == "none: the X-ray was refused"
    assert rp.level_runner_up_label.text() == "-" and not rp.hypotheses_caption.isHidden()
    assert "not an answer" in rp.hypotheses_caption.text() and rp.hypotheses_table.rowCount() >= 1
    cells = [rp.hypotheses_table.item(r, c) for r in range(rp.hypotheses_table.rowCount()) for c in range(4)]
    assert not any(cell.font().bold() for cell in cells)  # the record's winner is no answer: nothing in bold
    summary = win.registration_panel.status_label.text()  # the Register step's summary line names nothing either
    assert "none named" in summary and not any(name in summary for name in ("T10", "T11", "T12", "L1"))
    assert not rp.accept_button.isEnabled() and not win.act_accept_names.isEnabled()
    assert "refused" in rp.accept_button.toolTip() and not win.assigned_names
    assert sorted(spec.text for spec in win.xray_view.markers().values()) == ["T10", "T11", "T12"]  # the user's
    projected = [rp.table.item(r, 0).text() for r in range(rp.table.rowCount())]  # the CT's levels, as Slicer's
    assert projected and all(name.endswith("?") for name in projected)


# ------------------------------------------------------------------------------------------- 3. zoom

def test_wheel_zoom_keeps_the_point_under_the_cursor(xray_window):
    view = xray_window.xray_view
    for scene_xy, notches in (((40.0, 30.0), 1), ((350.0, 260.0), 2), ((200.0, 20.0), -1)):
        before = view.zoom_level()
        pos = view_pos(view, scene_xy)
        wheel(view, scene_xy, notches)
        assert view.zoom_level() == pytest.approx(before * 1.15 ** notches, rel=1e-6)
        after = view.mapToScene(pos)
        assert np.hypot(after.x() - scene_xy[0], after.y() - scene_xy[1]) <= scene_tolerance(view)


def test_ctrl_wheel_in_the_ct_zooms_about_the_cursor_and_plain_wheel_scrolls(window, synthetic_case):
    window.load_ct(synthetic_case.ct_path)
    view = window.axial
    ready(view)
    rect = view.image_rect()
    target = (rect.left() + 0.2 * rect.width(), rect.top() + 0.25 * rect.height())  # off centre, like a vertebra
    pos = view_pos(view, target)
    depth, zoom = view.depth_mm, view.zoom_level()
    for _ in range(3):
        wheel(view, target, 1, QtCore.Qt.KeyboardModifier.ControlModifier)
    assert view.zoom_level() == pytest.approx(zoom * 1.15 ** 3, rel=1e-6)
    after = view.mapToScene(pos)
    assert np.hypot(after.x() - target[0], after.y() - target[1]) <= scene_tolerance(view)
    assert view.depth_mm == depth  # Ctrl+wheel zooms, it does not change the slice
    wheel(view, target, 1)
    assert view.depth_mm != depth


# ------------------------------------------------------------------------------------------- 4. Level column

def test_the_level_column_fits_its_names_when_the_table_fills_from_empty(window):
    panel = window.ct_panel
    assert panel.table.rowCount() == 0
    for label, z in (("T10", 40.0), ("T11", 10.0), ("T12", -20.0)):
        window.ct_store.add(label, [0.0, 0.0, z])
    table = panel.table
    width = table.columnWidth(0)
    for row in range(3):
        combo = table.cellWidget(row, 0)
        assert combo.currentText() in ("T10", "T11", "T12")
        assert width >= combo.sizeHint().width()  # the whole name shows, not "T1"


def test_undo_puts_the_level_picker_back_on_the_undone_level(window):
    store = window.ct_store
    store.set_pending_level("T11")
    store.place([0.0, 0.0, 10.0])
    assert store.pending_level == "T12" and window.ct_panel.level_combo.currentText() == "T12"
    window.undo_stack.undo()
    assert store.labels() == [] and store.pending_level == "T11"
    assert window.ct_panel.level_combo.currentText() == "T11"
    window.undo_stack.redo()
    assert store.labels() == ["T11"] and store.pending_level == "T12"


# ------------------------------------------------------------------------------------------- 5. sessions

def test_a_reopened_session_shows_its_result(window, synthetic_case, tmp_path):
    _load_case(window, synthetic_case)
    names = window.xray_store.labels()
    window.set_result(_named_result(window, names, [0.5, 0.7, 0.6]))
    shown = window.overlay_view.level_names()
    path = window.save_session(tmp_path / "case.carmreg.json")
    window.new_session(ask=False)
    assert window.result is None and window.overlay_view.level_names() == []
    window.open_session(path)
    assert window.result is not None and getattr(window.result, "restored", False)
    assert window.overlay_view.level_names() == shown
    assert "mPDE 0.60 mm" in window.overlay_view.corner_text()["tl"]
    assert window.result_panel.table.rowCount() == len(shown)
    assert "CONFIRMED" in window.overlay_view.banner[0]
    assert not window.result_panel.report_button.isEnabled()  # no DRR: register again to export
    assert not window.is_dirty() and window.windowTitle().startswith("CarmReg - case.carmreg.json")


def test_a_recovered_session_keeps_its_file_name(window, synthetic_case, tmp_path):
    state = tmp_path / "state"
    _load_case(window, synthetic_case)
    saved = window.save_session(tmp_path / "mine.carmreg.json")
    window.ct_store.move(window.ct_store.find("T12").id, [1.0, 20.0, 31.0])  # unsaved edit
    own = window.autosave_now()
    crashed = state / "autosave-999999.carmreg.json"  # as left by a process that died
    shutil.copy(own, crashed)
    os.utime(crashed, None)
    window.new_session(ask=False)
    window.dialogs.answers["question"] = ["Recover"]
    assert window.offer_recovery() is True
    assert window.session_path == str(saved) and window.is_dirty()
    assert "mine.carmreg.json" in window.windowTitle()
    np.testing.assert_allclose(window.ct_store.find("T12").position, [1.0, 20.0, 31.0])


# ------------------------------------------------------------------------------------------- 8. progress

def test_progress_moves_inside_the_levels_stage_and_cancel_keeps_finished_stages(window, synthetic_case,
                                                                                monkeypatch):
    from gui_case import FAST_PARAMETERS

    from carmreg.logic.registration.image_refine import RefineParameters
    from carmreg.logic.registration.labelling_fit import coarse_refine_parameters
    from carmreg.worker import RegistrationWorker

    _load_case(window, synthetic_case)
    window.xray_store.rename_many({p.id: None for p in window.xray_store.points()})  # unnamed: the image names
    coarse = coarse_refine_parameters()
    coarse.max_evaluations, coarse.popsize = 48, 8
    window.parameter_overrides = {**FAST_PARAMETERS, "refine_coarse": coarse, "level_check": True,
                                  "refine": RefineParameters(enabled=False)}
    seen, original = [], RegistrationWorker._progress

    def progress(worker, stage, fraction, message):  # the worker thread: cancel inside the 2nd labelling
        seen.append((stage, fraction, message))
        if message.startswith("labelling 2 of") and len(seen) < 1000:
            worker.cancel()
        original(worker, stage, fraction, message)
    monkeypatch.setattr(RegistrationWorker, "_progress", progress)
    panel = window.registration_panel
    assert panel.next_button.text() == "Next: preparing the DRR database"
    window.run_registration(wait=True)
    labelling = [m for s, f, m in seen if s == "levels" and m.startswith("labelling")]
    # 3 runs of 3 clicks along 5 levels, and the leading two refitted from each other's pose: 5 fits
    assert len(labelling) == 2 and labelling[0].startswith("labelling 1 of 5: ")
    assert labelling[1].startswith("labelling 2 of 5: ")
    fractions = [f for s, f, m in seen if s == "levels"]
    assert 0.0 < max(fractions) < 1.0  # moved inside the stage, did not finish
    # cancelled inside the levels stage: database and spatial kept, Register continues from the levels
    assert window.result is None and window.dialogs.messages == []
    assert list(panel.mpde_by_stage()) == ["database", "spatial"] and panel.next_stage() == "levels"
    assert "kept 2 finished stage(s)" in panel.stage_label.text()
    assert panel.run_button.text() == "Register (continue)"
    database = window._reg_state.database
    seen.clear()
    monkeypatch.setattr(RegistrationWorker, "_progress", original)
    window.run_registration(wait=True)
    assert window.result is not None and window.result.ok, window.dialogs.messages
    assert window._reg_state.database is database  # not rebuilt
    assert [s.name for s in window.result.stages] == ["database", "spatial", "levels", "depth", "fine", "refine",
                                                      "final_drr"]
    assert len(window.result.level_check.assigned_labels) == 3


def test_time_left_estimate_uses_the_pace_of_this_machine():
    from carmreg.panels.registration_panel import STAGE_SECONDS, STAGES_ORDER, time_left_s

    # nothing done, at the start: the typical seconds of every stage
    assert time_left_s(STAGES_ORDER, {}, None, 0.0, 0.0) == pytest.approx(sum(STAGE_SECONDS.values()))
    # spatial took twice its typical time: the rest is expected twice as slow
    left = time_left_s(STAGES_ORDER, {"database": 9.0, "spatial": 2 * STAGE_SECONDS["spatial"]}, None, 0.0, 0.0)
    rest = sum(v for k, v in STAGE_SECONDS.items() if k not in ("database", "spatial"))
    assert left == pytest.approx(2 * rest)
    # inside a stage with a pace of its own: 2 s for a quarter -> 6 s more for it
    left = time_left_s(STAGES_ORDER, {"database": 1.0}, "spatial", 0.25, 2.0)
    assert left == pytest.approx(6.0 + sum(v for k, v in STAGE_SECONDS.items() if k not in ("database",
                                                                                             "spatial")))


# ------------------------------------------------------------------------------------------- report

def test_the_report_pdf_of_a_registration_reads_back(window, synthetic_case, tmp_path):
    pypdf = pytest.importorskip("pypdf")
    _load_case(window, synthetic_case)
    window.run_registration(wait=True)
    assert window.result is not None and window.result.ok
    paths = window.export_result(tmp_path / "out")
    reader = pypdf.PdfReader(str(paths["report"]))
    assert len(reader.pages) == 1
    text = reader.pages[0].extract_text()
    for expected in ("NOT FOR DIAGNOSIS", "T12", "L1", "L2", "magnification at the isocentre",
                     "mPDE of the pose drawn", "SDD 1000.0 mm", "CarmReg 0.1.0"):
        assert expected in text, expected
    drawn = np.mean([lv["pde_mm"] for lv in window.result.levels if lv["fitted"]])
    assert f"mPDE of the pose drawn {drawn:.2f} mm" in text
    assert json.loads((tmp_path / "out" / "result.json").read_text())["ok"] is True


# ------------------------------------------------------------------------------------------- 7. layout

@pytest.mark.parametrize("size", [(1280, 720), (1920, 1080)])
def test_nothing_overprints_at_common_screen_sizes(xray_window, size):
    from carmreg.qt_common import process_events

    win = xray_window
    _three_named_clicks(win)
    win.resize(*size)
    win.set_result(_named_result(win, ["T10", "T11", "T12"], [1.1, 0.9, 1.2], "contradicted",
                                 winner=["T11", "T12", "L1"]))
    process_events(50)
    rp = win.result_panel
    scroll = rp.parentWidget()  # the viewport of the step's scroll area
    for panel in (rp, win.registration_panel):  # no page needs a horizontal scroll bar (clipped text)
        assert panel.minimumSizeHint().width() <= panel.parentWidget().width(), panel.objectName()
    for button in (rp.accept_button, rp.report_button, rp.export_button, rp.png_button):
        top_left = button.mapTo(scroll, QtCore.QPoint(0, 0))
        assert 0 <= top_left.y() and top_left.y() + button.height() <= scroll.height(), button.text()
    assert win.overlay_view.width() >= 0.35 * size[0]
    assert win.view3d_result.width() >= 0.15 * size[0]


# ------------------------------------------------------------------------------------------- 10. front doors

def test_gui_help_documents_every_option_including_session(capsys):
    from carmreg.cli import main

    with pytest.raises(SystemExit) as done:
        main(["gui", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    for option in ("--session FILE", "--sample", "--ct CT", "--xray XRAY", "--ct-landmarks FILE",
                   "--xray-landmarks FILE", "install-system-deps.sh"):
        assert option in text, option


def test_gui_without_a_display_exits_2_with_one_line_and_leaves_no_autosave(tmp_path):
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    env["CARMREG_STATE_DIR"] = str(tmp_path / "state")
    done = subprocess.run([sys.executable, "-m", "carmreg.cli", "gui", "--sample"], capture_output=True, text=True,
                          timeout=120, env=env)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("carmreg: error: no display"), done.stderr
    assert not (tmp_path / "state").exists() or not any((tmp_path / "state").iterdir())


def test_gui_with_a_missing_session_file_exits_2(tmp_path, capsys):
    from carmreg.cli import main

    assert main(["gui", "--session", str(tmp_path / "nope.carmreg.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.carmreg.json" in err[0] and "not found" in err[0]


def test_screenshots_of_your_own_files_not_only_the_sample(qapp, synthetic_case, tmp_path, monkeypatch):
    from PIL import Image

    monkeypatch.setenv("CARMREG_NO_VTK", "1")  # keep it fast: no 3D

    from carmreg.app import export_screenshots

    inputs = {"ct": synthetic_case.ct_path, "xray": synthetic_case.xray_path,
              "ct_landmarks": synthetic_case.ct_landmarks_path, "xray_landmarks": synthetic_case.xray_landmarks_path}
    paths = export_screenshots(tmp_path, sample=False, views=("xray", "window_ct"), register=False,
                               size=(1280, 720), inputs=inputs)
    assert [p.name for p in paths] == ["carmreg_xray.png", "carmreg_window_ct.png"]
    assert Image.open(paths[1]).size == (1280, 720)
    xray = np.asarray(Image.open(paths[0]).convert("L"), float)
    assert xray.std() > 10  # the synthetic X-ray, not an empty view


# ------------------------------------------------------------------------------------------- 9. smaller ones

def test_a_ct_point_that_breaks_the_spine_order_is_warned_about(window):
    store, panel = window.ct_store, window.ct_panel
    store.add("T12", [0.0, 0.0, 40.0])
    store.add("L1", [0.0, 0.0, 10.0])
    assert not panel.warning_label.isVisibleTo(panel)
    l2 = store.add("L2", [80.0, -60.0, 60.0])  # in the liver, above L1
    assert panel.warning_label.isVisibleTo(panel)
    assert "not in spine order" in panel.warning_label.text() and "L2" in panel.warning_label.text()
    store.move(l2, [0.0, 0.0, -20.0])
    assert not panel.warning_label.isVisibleTo(panel)


def test_no_clicks_lists_each_level_once_and_metrics_have_their_names(xray_window):
    from carmreg.panels.result_panel import ranked_hypotheses

    check = {"winner_labels": ["T11"], "runner_up_labels": ["T10"],
             "hypotheses": [{"labels": ["T11"], "score": 0.52, "refined": True},
                            {"labels": ["T11"], "score": 0.50, "refined": True},
                            {"labels": ["T10"], "score": 0.57, "refined": True},
                            {"labels": ["T10"], "score": 0.55, "refined": True}]}
    ranked = ranked_hypotheses(LevelCheck.from_dict({"mode": "image_only", "status": "proposed", **check}))
    assert [(h["labels"], h["score"]) for h in ranked] == [(["T11"], 0.50), (["T10"], 0.55)]
    combo = xray_window.registration_panel.metric_combo
    assert combo.itemText(0) == "Gradient correlation (GC)"
    assert xray_window.registration_panel.parameters()["metric"] == "gc"
    xray_window.registration_panel.set_metric("ncc")
    assert xray_window.registration_panel.parameters()["metric"] == "ncc"


def test_xray_window_and_level_can_be_typed_and_follow_right_drag(xray_window):
    from gui_helpers import RIGHT, drag

    win, view = xray_window, xray_window.xray_view
    win.xray_window_spin.setValue(200.0)
    win.xray_level_spin.setValue(300.0)
    assert (view.window, view.level) == (200.0, 300.0)
    drag(view, (100.0, 100.0), (160.0, 100.0), RIGHT)  # right-drag widens the window
    assert view.window > 200.0 and win.xray_window_spin.value() == pytest.approx(view.window, abs=0.5)
    win.invert_check.setChecked(True)
    assert view.invert


def test_run_gui_with_a_session_opens_it_with_its_result(window, synthetic_case, tmp_path, monkeypatch):
    from qtpy import QtWidgets

    from carmreg import app
    from carmreg.main_window import CarmRegWidget

    _load_case(window, synthetic_case)
    window.set_result(_named_result(window, window.xray_store.labels(), [0.5, 0.7, 0.6]))
    path = window.save_session(tmp_path / "case.carmreg.json")
    monkeypatch.setenv("CARMREG_STATE_DIR", str(tmp_path / "state2"))
    monkeypatch.setenv("CARMREG_NO_VTK", "1")
    seen = {}

    def close_when_loaded(tries=[0]):  # noqa: B006 - a counter shared by the re-armed timer
        tries[0] += 1
        opened = [w for w in QtWidgets.QApplication.topLevelWidgets()
                  if isinstance(w, CarmRegWidget) and w.isVisible() and w is not window]
        win = opened[-1] if opened else None
        if win is not None and (win.result is not None or tries[0] > 100):
            seen.update(title=win.windowTitle(), restored=getattr(win.result, "restored", False),
                        names=win.overlay_view.level_names())
            win.discard_and_close()
            QtWidgets.QApplication.instance().exit(0)
        else:
            QtCore.QTimer.singleShot(100, close_when_loaded)

    QtCore.QTimer.singleShot(100, close_when_loaded)
    assert app.run_gui(session=str(path)) == 0
    assert seen["title"].startswith("CarmReg - case.carmreg.json") and seen["restored"]
    assert seen["names"] == window.overlay_view.level_names()


def test_the_pincushion_setting_reaches_the_logic(window):
    """Register step: 'Estimate an intensifier's pincushion from the image' (on by default) becomes
    RegistrationParameters.estimate_pincushion; a session's False switches it off, anything else leaves it on."""
    win = window
    assert win.registration_parameters().estimate_pincushion is True
    win.registration_panel.set_estimate_pincushion(False)
    assert win.registration_parameters().estimate_pincushion is False
    assert win.registration_panel.parameters()["estimate_pincushion"] is False
    win.registration_panel.set_estimate_pincushion(None)  # a session from before stop 37
    assert win.registration_parameters().estimate_pincushion is True


def test_the_polarity_setting_reaches_the_logic_and_a_session_and_the_found_one_is_shown(window):
    """Register step: 'X-ray polarity', 'X-ray storage' and 'X-ray field' (auto by default) become
    RegistrationParameters.polarity, .storage and .field and are kept in a session; the Check step shows what the
    registration found (result.appearance), amber when not trusted."""
    from carmreg.logic.image.appearance import POLARITY_SETTINGS, decide_polarity
    from carmreg.logic.image.field import FIELDS
    from carmreg.logic.image.prepare import STORAGES
    from carmreg.xray_settings import FIELD_CHOICES, POLARITY_CHOICES, STORAGE_CHOICES

    win = window
    assert win.registration_parameters().polarity == "auto"
    win.registration_panel.set_polarity("bone-bright")
    assert win.registration_parameters().polarity == "bone-bright"
    assert win.registration_panel.parameters()["polarity"] == "bone-bright"
    win.registration_panel.set_polarity("nonsense")
    assert win.registration_parameters().polarity == "auto"
    assert tuple(key for key, _ in POLARITY_CHOICES) == POLARITY_SETTINGS
    assert {key for key, _ in STORAGE_CHOICES} == {"auto", *STORAGES}  # every storage offered, and only those
    assert tuple(key for key, _ in FIELD_CHOICES) == FIELDS
    assert win.registration_parameters().storage == "auto"  # 'X-ray storage': the same way
    win.registration_panel.set_storage("linear-intensity")
    assert win.registration_parameters().storage == "linear-intensity"
    assert win.registration_panel.parameters()["storage"] == "linear-intensity"  # what a session keeps
    win.registration_panel.set_storage(None)  # a session from before stop 57
    assert win.registration_parameters().storage == "auto"
    assert win.registration_parameters().xray_field == "auto"  # 'X-ray field': found unless the whole image is said
    win.registration_panel.set_field("whole")
    assert win.registration_parameters().xray_field == "whole"
    assert win.registration_panel.parameters()["field"] == "whole"  # what a session keeps
    win.registration_panel.set_field(None)
    assert win.registration_parameters().xray_field == "auto"
    found = decide_polarity({"bone-dark": 0.2, "bone-bright": 0.5}, None, "auto", True, "PNG", None)
    win.result_panel.set_appearance(found)
    assert "bone-bright, found from the image" in win.result_panel.appearance_label.text()
    assert win.result_panel.appearance_label.styleSheet() == ""
    unclear = decide_polarity({"bone-dark": 0.30, "bone-bright": 0.29}, None, "auto", True, "PNG", None)
    win.result_panel.set_appearance(unclear)
    assert "barely tells" in win.result_panel.appearance_label.text()
    assert "#ffa94d" in win.result_panel.appearance_label.styleSheet()
