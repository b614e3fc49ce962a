"""Unnamed X-ray clicks in the window: placing them ("Name the levels" off), mixing named and unnamed, undo,
session / autosave / .mrk.json round trips with label None, when Register is enabled and which level
identification mode it announces, the assigned names after a registration ("?1 → T11"), the level
identification in the result panel and "Accept assigned names" (undoable).

The labelling tests need no registration; ``test_sample_case_with_unnamed_clicks...`` runs the real pipeline on
the embedded sample case (slow)."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
from gui_helpers import click, drag, key, scene_tolerance
from qtpy import QtCore

pytestmark = pytest.mark.gui
ARROW = "\u2192"


def _texts(view) -> dict[int, str]:
    """{point id: marker text} as drawn in the X-ray view."""
    return {k: spec.text for k, spec in view.markers().items()}


def _unnamed_off(win) -> None:
    win.xray_panel.name_check.setChecked(False)


def test_unticking_name_the_levels_places_unnamed_clicks_numbered_from_the_top(xray_window):
    win = xray_window
    store, view = win.xray_store, win.xray_view
    _unnamed_off(win)
    assert not store.naming and not win.act_name_levels.isChecked()
    assert not win.xray_panel.level_combo.isEnabled()
    pending = store.pending_level
    for uv in ((200.0, 200.0), (180.0, 80.0), (220.0, 260.0)):
        click(view, uv)
    assert [p.label for p in store.points()] == [None, None, None]
    assert store.pending_level == pending  # the level picker is not used
    assert win.undo_stack.count() == 3
    tol = scene_tolerance(view)
    by_text = {text: store.get(pid).position for pid, text in _texts(view).items()}
    assert sorted(by_text) == ["?1", "?2", "?3"]
    np.testing.assert_allclose(by_text["?1"], [180.0, 80.0], atol=tol)   # top of the image first
    np.testing.assert_allclose(by_text["?2"], [200.0, 200.0], atol=tol)
    np.testing.assert_allclose(by_text["?3"], [220.0, 260.0], atol=tol)
    # the table lists them in the same order, and the count says they are unnamed
    assert [win.xray_panel.table.cellWidget(r, 0).currentText() for r in range(3)] == ["?1", "?2", "?3"]
    assert win.xray_panel.count_label.text() == "3 point(s): 3 unnamed"
    # the logic gets label None for each, in that order
    marks = store.to_landmarks()
    assert marks.labels == [None, None, None]
    np.testing.assert_allclose(marks.uv_px[:, 1], [80.0, 200.0, 260.0], atol=tol)
    # dragging ?1 below ?3 renumbers along the spine
    drag(view, (180.0, 80.0), (180.0, 280.0))
    assert sorted(_texts(view).values()) == ["?1", "?2", "?3"]
    assert store.get(store.points()[-1].id).position[1] == pytest.approx(280.0, abs=tol)
    # the N action turns naming back on
    win.act_name_levels.trigger()
    assert store.naming and win.xray_panel.name_check.isChecked()
    store.set_pending_level("T11")
    click(view, (300.0, 150.0))
    assert store.labels() == ["T11"] and store.unnamed_count() == 3


def test_named_and_unnamed_clicks_mix_and_rename_through_the_table(xray_window):
    win = xray_window
    store, view, panel = win.xray_store, win.xray_view, win.xray_panel
    store.set_pending_level("T12")
    click(view, (150.0, 150.0))
    _unnamed_off(win)
    click(view, (160.0, 60.0))
    click(view, (170.0, 240.0))
    assert store.labels() == ["T12"] and store.unnamed_count() == 2
    texts = sorted(_texts(view).values())
    assert texts == ["?1", "?2", "T12"]
    assert panel.count_label.text() == "3 point(s): T12 + 2 unnamed"
    assert store.to_landmarks().labels == ["T12", None, None]
    # name ?2 (the lower one) L1 through its table combo: the other stays ?1
    row = [panel.table.cellWidget(r, 0).currentText() for r in range(3)].index("?2")
    panel.table.cellWidget(row, 0).setCurrentText("L1")
    assert store.labels() == ["T12", "L1"]
    np.testing.assert_allclose(store.find("L1").position, [170.0, 240.0], atol=scene_tolerance(view))
    assert sorted(_texts(view).values()) == ["?1", "L1", "T12"]
    # and take the name off T12 again: it becomes an unnamed click, numbered by its height (row 150 between 60 and 240)
    row = [panel.table.cellWidget(r, 0).currentText() for r in range(3)].index("T12")
    panel.table.cellWidget(row, 0).setCurrentText("(unnamed)")
    assert store.labels() == ["L1"]
    shown = {text: store.get(pid).position[1] for pid, text in _texts(view).items()}
    assert shown["?1"] == pytest.approx(60.0, abs=1) and shown["?2"] == pytest.approx(150.0, abs=1)
    # the mode line of the registration panel follows
    assert win.xray_click_mode() == "partly_named"
    win.undo_stack.undo()
    win.undo_stack.undo()
    assert store.labels() == ["T12"] and store.unnamed_count() == 2


def test_unnamed_click_undo_redo_delete_and_bulk_rename_in_one_step(xray_window):
    win = xray_window
    store, view = win.xray_store, win.xray_view
    _unnamed_off(win)
    click(view, (100.0, 50.0))
    click(view, (110.0, 150.0))
    tol = scene_tolerance(view)
    lower = store.points()[1]
    drag(view, (110.0, 150.0), (130.0, 170.0))
    store.select(lower.id)
    key(view, QtCore.Qt.Key.Key_Delete)
    assert len(store) == 1
    assert win.undo_stack.count() == 4  # two clicks, one move, one delete
    win.undo_stack.undo()
    np.testing.assert_allclose(store.get(lower.id).position, [130.0, 170.0], atol=tol)
    assert store.get(lower.id).label is None
    win.undo_stack.undo()
    np.testing.assert_allclose(store.get(lower.id).position, [110.0, 150.0], atol=tol)
    win.undo_stack.redo()
    np.testing.assert_allclose(store.get(lower.id).position, [130.0, 170.0], atol=tol)
    # naming several clicks at once is one undo step; a name used twice is refused
    upper = store.points()[0]
    store.rename_many({upper.id: "T11", lower.id: "T12"}, "Name them")
    assert store.labels() == ["T11", "T12"] and win.undo_stack.undoText().startswith("Name them")
    store.rename_many({upper.id: "T12", lower.id: "T11"})  # a swap is allowed
    assert store.find("T12").id == upper.id
    from carmreg.logic.errors import LandmarkError
    with pytest.raises(LandmarkError, match="placed twice"):
        store.rename_many({upper.id: "L1", lower.id: "L1"})
    win.undo_stack.undo()
    win.undo_stack.undo()
    assert [p.label for p in store.points()] == [None, None]


def test_unnamed_clicks_survive_session_autosave_and_mrk_json_round_trips(xray_window, tmp_path):
    from carmreg.logic.io import session as session_io
    from carmreg.logic.io.landmarks import read_landmarks_2d
    from carmreg.main_window import CarmRegWidget
    from carmreg.qt_common import ScriptedDialogs

    win = xray_window
    store = win.xray_store
    store.add("T12", [150.0, 150.0])
    store.add(None, [160.0, 60.0])
    store.add(None, [170.0, 240.5])
    expected = [(p.label, list(p.position), store.display_name(p.id)) for p in store.points()]
    assert [e[2] for e in expected] == ["T12", "?1", "?2"]

    # autosave: the record keeps label null
    autosave = win.autosave_now()
    doc = json.loads(autosave.read_text())
    assert [p["label"] for p in doc["landmarks"]["xray"]] == ["T12", None, None]
    assert session_io.load_session(autosave).xray_landmarks().labels == ["T12", None, None]

    # session file: reopened in another window, same labels, positions and ?k numbering
    path = win.save_session(tmp_path / "unnamed")
    other = CarmRegWidget(dialogs=ScriptedDialogs(), autosave=False, view3d_mode="message")
    try:
        other.restore_session(session_io.load_session(path), str(path))
        got = [(p.label, list(p.position), other.xray_store.display_name(p.id)) for p in other.xray_store.points()]
        assert got == expected
        assert other.undo_stack.count() == 0
    finally:
        other.discard_and_close()

    # Slicer markups: unnamed clicks are written with an empty label and read back as None
    mrk = win.export_xray_landmarks(tmp_path / "clicks.mrk.json")
    marks = read_landmarks_2d(mrk, (0.3, 0.3))
    assert sorted(marks.labels, key=str) == sorted(["T12", None, None], key=str)
    store.replace_all([], [], undoable=False)
    win.import_xray_landmarks(mrk)
    assert [(p.label, p.position.round(3).tolist()) for p in store.points()] == \
        [(e[0], np.round(e[1], 3).tolist()) for e in expected]


def test_register_is_enabled_for_unnamed_clicks_and_no_clicks_and_says_which_mode(window, synthetic_case):
    win = window
    win.load_ct(synthetic_case.ct_path)
    win.load_xray(synthetic_case.xray_path)
    win.import_ct_landmarks(synthetic_case.ct_landmarks_path)
    panel, store = win.registration_panel, win.xray_store
    uv = synthetic_case.uv_px

    def state():
        return panel.run_button.isEnabled(), panel.mode, panel.ready_label.text()

    enabled, mode, text = state()  # no X-ray clicks at all: identify from the image alone
    assert enabled and mode == "image_only" and "image alone" in text and win.act_register.isEnabled()
    assert win.min_xray_clicks() == 3  # the logic's minimum: 3 clicks, named or not (or none)
    store.add(None, uv[1])
    store.add(None, uv[2])
    enabled, mode, text = state()
    assert not enabled and mode == "unnamed" and "only 2 X-ray click(s): click the centres of at least 3" in text
    store.add(None, uv[3])
    enabled, mode, text = state()
    assert enabled and mode == "unnamed" and "3 unnamed X-ray clicks" in text
    # two named clicks alone are not enough, as before
    store.replace_all(["T12", "L1"], uv[1:3], undoable=False)
    enabled, mode, text = state()
    assert not enabled and mode == "named" and "only 2 level(s) (T12, L1)" in text
    store.add(None, uv[3])
    enabled, mode, text = state()
    assert enabled and mode == "partly_named" and "2 named (T12, L1) and 1 unnamed" in text
    store.rename(store.points()[-1].id, "L2")
    enabled, mode, text = state()
    assert enabled and mode == "named" and text.startswith("Ready: 3 levels")
    # named head-down (a display turned 180 degrees, or the names reversed): refused with the turn, as everywhere
    store.replace_all(["L2", "L1", "T12"], uv[1:4], undoable=False)
    enabled, mode, text = state()
    assert not enabled and mode == "named" and "run head-down (T12 lies below L2 on the image)" in text
    assert 'X-ray orientation "shown turned 180"' in text
    # unnamed clicks across the image (a display turned a quarter): refused with both quarter turns
    across = np.asarray(uv[1:4], float)[:, ::-1].tolist()  # columns and rows swapped: the spine runs across
    store.replace_all([None, None, None], across, undoable=False)
    enabled, mode, text = state()
    assert not enabled and mode == "unnamed" and "the X-ray clicks run across the image (" in text
    assert "--orient-xray turned-90 or turned-270" in text
    store.replace_all(["T12", "L1", "L2"], uv[1:4], undoable=False)
    # three named clicks of which only two have a CT centroid: leaving them unnamed is offered
    store.rename(store.find("L2").id, "L5")
    enabled, mode, text = state()
    assert not enabled and "only 2 level(s) (T12, L1)" in text and "or leave the X-ray clicks unnamed" in text
    # the CT centroids stay required (named, at least 3) in every mode
    store.replace_all([None, None, None], uv[1:4], undoable=False)
    win.ct_store.replace_all(["T11", "T12"], synthetic_case.centroids_lps_mm[:2], undoable=False)
    enabled, mode, text = state()
    assert not enabled and "only 2 CT centroid(s)" in text
    store.replace_all([], [], undoable=False)
    assert not panel.run_button.isEnabled()


def _fake_result(win, assigned, status, mode="unnamed", margin=0.012, runner_up=None, visible=None,
                 click_indices=None):
    """A RegistrationResult stand-in with a level_check, for the display without running the pipeline."""
    from carmreg.logic.geometry.camera import CarmGeometry, CarmPose
    from carmreg.logic.io.landmarks import level_index
    from carmreg.logic.registration.level_check import LevelCheck

    geometry = CarmGeometry(win.xray.intrinsics, (0.0, 0.0, 0.0), 600.0)
    pose = CarmPose(0, 0, 0, 0, 0, 0)
    levels = [{"label": lb, "uv_px": [150.0, 60.0 + 90 * i], "fitted": True, "pde_mm": 0.5, "in_image": True}
              for i, lb in enumerate(assigned)]
    winner = sorted(assigned, key=level_index)  # spine order, as the logic lists labellings
    hypotheses = [{"labels": ["T1", "T2", "T3"], "score": 0.9, "similarity": 0.05, "mpde_mm": 3.0, "refined": False},
                  {"labels": list(runner_up or []), "score": 0.512, "similarity": 0.40, "mpde_mm": 1.1,
                   "refined": True},
                  {"labels": winner, "score": 0.5, "similarity": 0.41, "agreement": 0.47, "mpde_mm": 0.8,
                   "refined": True}]
    message = {"confident": "the level names agree with the image",
               "ambiguous": "level names AMBIGUOUS: the image fits about as well one level higher",
               "contradicted": "level names CONTRADICTED: check them"}[status]
    check = {"mode": mode, "status": status, "margin": margin, "assigned_labels": list(assigned),
             "winner_labels": winner, "runner_up_labels": runner_up, "message": message, "hypotheses": hypotheses,
             "visible_labels": list(visible or assigned),
             "click_indices": list(range(len(assigned)) if click_indices is None else click_indices)}
    return SimpleNamespace(pose=pose, projection_matrix=geometry.projection_matrix(pose), geometry=geometry,
                           stages=[], levels=levels, drr_line_integral=None, convergence=[],
                           ok=status != "contradicted", warnings=[], failed_checks=[], magnification=1.6,
                           level_check=LevelCheck.from_dict(check), appearance=None, field_mask=None)


def test_assigned_names_show_on_the_clicks_and_can_be_accepted_and_undone(xray_window):
    """The display side of the level identification, with a stand-in result (no pipeline)."""
    win = xray_window
    store, view, rp = win.xray_store, win.xray_view, win.result_panel
    store.add(None, [160.0, 240.0])
    store.add("T11", [150.0, 150.0])
    store.add(None, [140.0, 60.0])
    assert store.to_landmarks().labels == ["T11", None, None]  # the order the logic gets: T11, ?1, ?2
    win.set_result(_fake_result(win, ["T11", "T10", "T12"], "ambiguous", "partly_named", 0.012,
                                ["T11", "T12", "L1"]))
    texts = sorted(_texts(view).values())
    assert texts == [f"?1 {ARROW} T10", f"?2 {ARROW} T12", "T11"]
    coloured = [spec.color for spec in view.markers().values() if ARROW in spec.text]
    assert coloured and all(c == "#ffa94d" for c in coloured)  # ambiguous: amber
    # the overlay: every name the image did not confirm carries a "?", the fitted levels in amber, not green
    drawn = [spec for spec in win.overlay_view.markers().values() if spec.key[0] == "level"]
    assert len(drawn) == 3 and all(spec.text.startswith(f"{spec.key[1]}?") for spec in drawn)
    assert all(spec.color == "#ffa94d" for spec in drawn if spec.style == "fitted")
    # the result panel: mode, status colour, message, margin, runner-up, assigned names, hypotheses
    assert "partly named" in rp.level_mode_label.text()
    assert rp.level_status_label.text() == "AMBIGUOUS" and rp.level_status_color == "#ffa94d"
    assert "AMBIGUOUS" in rp.level_message_label.text() and rp.level_message_label.isVisibleTo(rp)
    assert rp.level_margin_label.text().startswith("+0.012  (runner-up score minus this one: confident from +0.020")
    assert rp.level_runner_up_label.text() == "T11, T12, L1"
    assert rp.level_assigned_label.text() == f"T11, ?1 {ARROW} T10, ?2 {ARROW} T12"
    # labellings best first: the winner (bold), the runner-up, then the others
    table = rp.hypotheses_table
    assert [table.item(r, 0).text() for r in range(3)] == ["T10, T11, T12", "T11, T12, L1", "T1, T2, T3"]
    assert table.item(0, 1).text() == "0.500" and table.item(0, 0).font().bold()
    assert table.item(0, 2).text() == "0.410 (eq 0.470)" and table.item(1, 2).text() == "0.400"  # eq where higher
    assert table.item(1, 1).text() == "0.512" and not table.item(1, 0).font().bold()
    assert "ambiguous" in win.registration_panel.status_label.text()
    assert win.xray_panel.table.item(1, 2).text() == "T10"  # the Identified column (rows: T11, ?1, ?2)
    # accept: not confident, so the window asks; "Cancel" (the default answer) changes nothing
    assert rp.accept_button.isEnabled() and win.act_accept_names.isEnabled()
    assert win.accept_assigned_names(ask=True) == {}
    assert store.labels() == ["T11"]
    win.dialogs.answers["question"] = ["Accept anyway"]
    rp.accept_button.click()
    assert store.labels() == ["T10", "T11", "T12"] and store.unnamed_count() == 0
    assert sorted(_texts(view).values()) == ["T10", "T11", "T12"]
    assert not win.result_stale and not rp.accept_button.isEnabled()
    assert win.undo_stack.undoText().startswith("Accept assigned level names")
    win.undo_stack.undo()  # one step back to the unnamed clicks; the result no longer matches them
    assert store.labels() == ["T11"] and store.unnamed_count() == 2
    assert win.result_stale and not rp.accept_button.isEnabled()


def test_status_colours_and_image_only_mode_in_the_result_panel(xray_window):
    win = xray_window
    rp = win.result_panel
    result = _fake_result(win, [], "confident", "image_only", float("inf"), visible=["T10", "T11", "T12"])
    win.set_result(result)
    assert rp.level_status_label.text() == "CONFIDENT" and rp.level_status_color == "#69db7c"
    assert "image alone" in rp.level_mode_label.text()
    assert rp.level_margin_label.text() == "no alternative labelling"
    assert rp.level_assigned_label.text() == "in the image: T10, T11, T12"
    assert not rp.accept_button.isEnabled() and win.xray_view.assigned == {}
    store = win.xray_store
    store.add(None, [140.0, 60.0])
    store.add(None, [150.0, 150.0])
    store.add(None, [160.0, 240.0])
    win.set_result(_fake_result(win, ["T10", "T11", "T12"], "contradicted", "unnamed", -0.05, ["T9", "T10", "T11"]))
    assert rp.level_status_label.text() == "CONTRADICTED" and rp.level_status_color == "#ff8787"
    assert "CONTRADICTED" in rp.level_message_label.text()
    assert sorted(_texts(win.xray_view).values()) == [f"?{k} {ARROW} T1{k - 1}" for k in (1, 2, 3)]
    assert win.accept_assigned_names(ask=False, register=False) and store.labels() == ["T10", "T11", "T12"]
    assert win.result_stale  # the names changed: this result was registered with the others
    store.move(store.find("T10").id, [141.0, 61.0])
    assert win.result_stale and win.xray_view.assigned == {}
    from carmreg.logic.errors import RegistrationError
    with pytest.raises(RegistrationError, match="register again"):
        win.accept_assigned_names(ask=False)


def test_a_named_click_without_ct_centroid_is_skipped_when_mapping_the_assigned_names(xray_window):
    """The logic identifies only the clicks it can use: unnamed ones and named ones with a CT centroid."""
    win = xray_window
    store = win.xray_store
    win.ct_store.replace_all(["T10", "T11", "T12"], [[0, 0, 40.0], [0, 0, 10.0], [0, 0, -20.0]], undoable=False)
    store.add("L4", [150.0, 280.0])  # not on the CT
    store.add(None, [140.0, 60.0])
    store.add(None, [150.0, 150.0])
    assert store.to_landmarks().labels == ["L4", None, None]
    win.set_result(_fake_result(win, ["T11", "T12"], "confident", "unnamed", 0.2, ["T10", "T11"], click_indices=[1, 2]))
    assert sorted(_texts(win.xray_view).values()) == [f"?1 {ARROW} T11", f"?2 {ARROW} T12", "L4"]
    assert win.accept_assigned_names(ask=True) and store.labels() == ["T11", "T12", "L4"]
    assert win.dialogs.messages == []  # confident: no question asked


@pytest.mark.slow
def test_sample_case_with_unnamed_clicks_is_identified_as_t10_t11_t12(window, drr_cache_dir):
    """The embedded sample (real CT, simulated C-arm X-ray): its three X-ray clicks, names removed, are
    identified by the registration; the X-ray view and the result panel show it."""
    from carmreg.logic.errors import InputFileError
    from carmreg.logic.resources import sample_case

    try:
        sample_case()
    except InputFileError as exc:
        pytest.skip(str(exc))
    window.parameter_overrides = {"cache_dir": drr_cache_dir}
    window.load_sample_case()
    store = window.xray_store
    assert store.labels() == ["T10", "T11", "T12"]
    store.rename_many({p.id: None for p in store.points()}, "Forget the names")
    assert window.registration_panel.mode == "unnamed" and window.registration_panel.run_button.isEnabled()
    window.run_registration(wait=True)
    assert window.dialogs.messages == [], window.dialogs.messages
    check = window.result.level_check
    assert check.mode == "unnamed"
    assert check.assigned_labels == ["T10", "T11", "T12"], check
    assert check.status in ("confident", "ambiguous", "contradicted")
    texts = sorted(_texts(window.xray_view).values())
    assert texts == [f"?1 {ARROW} T10", f"?2 {ARROW} T11", f"?3 {ARROW} T12"]
    rp = window.result_panel
    assert rp.level_status_label.text() == check.status.upper()
    assert rp.level_assigned_label.text() == f"?1 {ARROW} T10, ?2 {ARROW} T11, ?3 {ARROW} T12"
    assert "unnamed" in rp.level_mode_label.text()
    window.accept_assigned_names(ask=False)
    assert store.labels() == ["T10", "T11", "T12"]
