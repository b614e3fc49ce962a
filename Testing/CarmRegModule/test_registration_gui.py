"""Registration from the window: whole pipeline and stage by stage on a worker thread, cancel, errors as
dialogs, the overlay's projected level names, export. (The embedded sample case registered from the window, its
levels named where the X-ray shows them: ``test_orientation_gui.py``, after its display stored mirrored is turned
back.)"""

import json

import numpy as np
import pytest
from gui_case import TRUE_POSE

pytestmark = pytest.mark.gui


def _load_case(win, case):
    win.load_ct(case.ct_path)
    win.load_xray(case.xray_path)
    win.import_ct_landmarks(case.ct_landmarks_path)
    win.import_xray_landmarks(case.xray_landmarks_path)


def test_register_shows_every_ct_level_on_the_overlay_and_recovers_the_pose(window, synthetic_case, tmp_path):
    _load_case(window, synthetic_case)
    assert window.registration_panel.run_button.isEnabled()
    assert "Ready: 3 levels" in window.registration_panel.ready_label.text()
    window.run_registration(wait=True)
    assert window.dialogs.messages == []
    result = window.result
    assert result.ok
    np.testing.assert_allclose(result.pose.as_array(), TRUE_POSE, atol=0.3)
    # what the user reads: every CT-labelled level, fitted ones apart, PDE per fitted level
    assert window.overlay_view.level_names() == list(synthetic_case.labels)
    markers = {spec.key[1]: spec for spec in window.overlay_view.markers().values() if spec.key[0] == "level"}
    assert [k for k, m in markers.items() if m.style == "fitted"] == ["T12", "L1", "L2"]
    assert markers["T11"].style == "check" and markers["T11"].text == "T11"
    assert markers["L1"].text.startswith("L1  0.0") and markers["L1"].text.endswith("mm")
    for label, uv in zip(synthetic_case.labels, synthetic_case.uv_px, strict=True):
        assert np.hypot(markers[label].x - uv[0], markers[label].y - uv[1]) < 0.5  # px
    # per-stage figures and the convergence plot
    mpde = window.registration_panel.mpde_by_stage()
    assert set(mpde) == {"database", "spatial", "depth", "fine", "refine", "levels", "final_drr"}
    assert mpde["fine"] < 0.1 and mpde["spatial"] < 20.0
    assert len(window.registration_panel.plot.points) > 5
    assert window.result_panel.table.rowCount() == 5
    assert window.view3d_result.has_carm()
    assert window.step_tabs.currentIndex() == 4 and window.view_tabs.currentIndex() == 2
    # overlay modes recomposite the same-size image
    for mode in ("checkerboard", "edges", "blend"):
        window.result_panel.mode_buttons[mode].setChecked(True)
        assert window.overlay_view.composite_rgb().shape == (256, 256, 3)
    # export through the logic
    paths = window.export_result(tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert doc["ok"] is True and {"overlay", "tfm", "result", "slicer_scene"} <= set(paths)
    assert paths["slicer_scene"] == tmp_path / "out" / "slicer" / "CarmReg.mrml"
    assert window.current_session().last_result["out_dir"] == str(tmp_path / "out")


def test_stage_by_stage_gives_the_same_result_and_fills_the_table_row_by_row(window, synthetic_case):
    _load_case(window, synthetic_case)
    panel = window.registration_panel
    seen = []
    for expected in ("database", "spatial", "levels", "depth", "fine", "refine", "final_drr"):
        assert panel.next_stage() == expected
        window.run_next_stage(wait=True)
        seen.append(list(panel.mpde_by_stage()))
    assert seen[0] == ["database"] and seen[-1][-1] == "final_drr"
    assert panel.next_stage() is None and not panel.next_button.isEnabled()
    assert window.result is not None and window.result.ok
    np.testing.assert_allclose(window.result.pose.as_array(), TRUE_POSE, atol=0.3)


def test_editing_a_landmark_drops_the_prepared_stages_and_marks_the_result_stale(window, synthetic_case):
    _load_case(window, synthetic_case)
    window.run_next_stage(wait=True)
    assert window.registration_panel.next_stage() == "spatial"
    window.xray_store.move(window.xray_store.find("L1").id, [120.0, 113.0])
    assert window.registration_panel.next_stage() == "database"


def test_cancel_stops_the_worker_without_an_error_dialog(window, synthetic_case):
    _load_case(window, synthetic_case)
    window.run_registration(wait=False)
    assert window.is_running() and window.act_cancel.isEnabled()
    window.cancel_registration()
    window.wait_for_registration(60)
    assert not window.is_running()
    assert window.result is None
    assert window.dialogs.messages == []
    assert window.registration_panel.run_button.isEnabled()


def test_too_few_common_levels_is_explained_before_and_on_running(window, synthetic_case):
    _load_case(window, synthetic_case)
    window.xray_store.remove(window.xray_store.find("L2").id)
    ready = window.registration_panel.ready_label.text()
    assert "only 2 level(s) (T12, L1)" in ready and "at least 3" in ready
    assert not window.registration_panel.run_button.isEnabled()
    window._action_register()  # Ctrl+R still reaches the logic, which refuses with a clear message
    window.wait_for_registration(60)
    title, message, details = window.dialogs.messages[-1]
    assert "at least 3" in message and details is None


@pytest.mark.slow
def test_a_result_computed_while_the_user_edited_is_shown_as_out_of_date(window, synthetic_case):
    _load_case(window, synthetic_case)
    window.run_registration(wait=False)
    window.xray_store.move(window.xray_store.find("L1").id, [119.0, 113.5])  # edit during the run
    window.wait_for_registration(120)
    assert window.result is not None and window.result_stale
    assert "register again" in window.overlay_view.summary
    assert window._reg_state is None  # stages must run again on the edited landmarks


def test_another_xray_takes_the_previous_clicks_away_and_greys_the_answer(window, synthetic_case):
    """Clicks placed on one X-ray are not the vertebrae of another of the same size (they would register
    silently): loading another file removes them in one undoable step; the answer shown turns grey, out of date."""
    from carmreg.logic.report.style import STALE_WORDS, status_fill

    _load_case(window, synthetic_case)
    window.run_registration(wait=True)
    assert window.result.ok and not window.result_stale
    window.load_xray(synthetic_case.png_path, {"sdd_mm": 1000.0, "pixel_spacing_mm": (0.9, 0.9)})  # the same size
    assert len(window.xray_store) == 0
    assert window.result_stale
    assert window.overlay_view.banner[0] == STALE_WORDS
    assert window.result_panel.banner_colour == status_fill(None)
    assert "previous image were removed" in window.statusBar().currentMessage()
    window.undo_stack.undo()
    assert sorted(window.xray_store.labels()) == ["L1", "L2", "T12"]
    window.load_xray(synthetic_case.png_path, {"sdd_mm": 1000.0, "pixel_spacing_mm": (1.0, 1.0)})  # same file: kept
    assert len(window.xray_store) == 3
