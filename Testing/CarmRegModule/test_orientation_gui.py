"""The window's X-ray orientation (``window_data.set_xray_orientation``): a display stored turned is shown, clicked
and registered turned back, its points turning with it in one undo step, while exported points and sessions stay
on the image as stored (as ``carmreg register --orient-xray`` takes them)."""

import json

import numpy as np
import pytest
from gui_case import TRUE_POSE
from qtpy import QtCore

from carmreg.logic.image.turn import ORIENTATIONS, orient_uv
from carmreg.logic.io.landmarks import Landmarks2D, read_landmarks_2d, write_landmarks_2d
from carmreg.logic.io.xray import load_xray
from carmreg.logic.io.xray_write import write_xray_dicom

pytestmark = pytest.mark.gui

STORED_AS, TURN_BACK = "turned-90", "turned-270"


def _stored_turned(case, folder):
    """The synthetic case's X-ray written as a display stored turned a quarter (the same header), and its clicks as
    that image shows them; returns (X-ray path, clicks path, the clicks' (u, v) as stored)."""
    acquired = load_xray(case.xray_path)
    pixels = np.ascontiguousarray(ORIENTATIONS[STORED_AS](acquired.pixels.astype(np.uint16)))
    xray_path = write_xray_dicom(folder / "turned.dcm", pixels, acquired.intrinsics, sod_mm=600.0)
    uv_stored = orient_uv(case.uv_px[1:4], STORED_AS, case.size_px)
    clicks_path = write_landmarks_2d(folder / "turned.mrk.json", Landmarks2D(list(case.labels[1:4]), uv_stored),
                                     (case.pixel_spacing_mm,) * 2)
    return xray_path, clicks_path, uv_stored


def _points(window) -> np.ndarray:
    return np.array([p.position for p in window.xray_store.points()])


def test_a_display_stored_turned_is_turned_back_undoably_kept_on_disk_as_stored_and_registers(
        window, synthetic_case, tmp_path):
    xray_path, clicks_path, uv_stored = _stored_turned(synthetic_case, tmp_path)
    window.load_ct(synthetic_case.ct_path)
    window.load_xray(xray_path)
    window.import_ct_landmarks(synthetic_case.ct_landmarks_path)
    window.import_xray_landmarks(clicks_path)
    combo = window.orientation_combo
    assert combo.isEnabled() and combo.currentData() == "as-stored"
    np.testing.assert_allclose(_points(window), uv_stored, atol=1e-9)
    # the user picks the turn a refusal names, by the words it names it with
    index = combo.findData(TURN_BACK)
    assert combo.itemText(index) == f"shown {TURN_BACK.replace('-', ' ')}"
    combo.activated.emit(index)
    acquired = load_xray(synthetic_case.xray_path)
    assert window.xray_orientation == TURN_BACK and combo.currentData() == TURN_BACK
    np.testing.assert_array_equal(window.xray.pixels, acquired.pixels)
    shown = [window.xray_view.value_at(QtCore.QPointF(u, v)) for u, v in ((40, 200), (200, 40), (10, 10))]
    assert shown == [float(acquired.pixels[v, u]) for u, v in ((40, 200), (200, 40), (10, 10))]
    np.testing.assert_allclose(_points(window), synthetic_case.uv_px[1:4], atol=1e-9)
    assert "shown turned 270" in window.xray_info.text()
    # one undo step turns image and points back; redo again
    assert window.undo_stack.undoText() == "Show the X-ray turned 270"
    window.undo_stack.undo()
    assert window.xray_orientation == "as-stored" and combo.currentData() == "as-stored"
    np.testing.assert_array_equal(window.xray.pixels, load_xray(xray_path).pixels)
    np.testing.assert_allclose(_points(window), uv_stored, atol=1e-9)
    window.undo_stack.redo()
    np.testing.assert_allclose(_points(window), synthetic_case.uv_px[1:4], atol=1e-9)
    # exported points stay on the image as stored
    exported = read_landmarks_2d(window.export_xray_landmarks(tmp_path / "exported.mrk.json"))
    np.testing.assert_allclose(exported.uv_px, uv_stored, atol=1e-9)
    # registered turned back: the acquisition's pose, every level where the acquisition shows it, the turn recorded
    window.run_registration(wait=True)
    assert window.dialogs.messages == []
    result = window.result
    assert result.ok, result.warnings
    np.testing.assert_allclose(result.pose.as_array(), TRUE_POSE, atol=0.3)
    markers = {spec.key[1]: spec for spec in window.overlay_view.markers().values() if spec.key[0] == "level"}
    for label, uv in zip(synthetic_case.labels, synthetic_case.uv_px, strict=True):
        assert np.hypot(markers[label].x - uv[0], markers[label].y - uv[1]) < 0.5  # px
    window.export_result(tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert "turned 270 as the user asked" in doc["inputs"]["geometry_sources"]["orientation"]
    # the session keeps the points as stored and the turn; reopened, all is shown as before
    session = window.save_session(tmp_path / "work")
    saved = json.loads(session.read_text())
    assert saved["version"] == 2 and saved["xray_orientation"] == TURN_BACK
    np.testing.assert_allclose([p["uv_px"] for p in saved["landmarks"]["xray"]], uv_stored, atol=1e-9)
    window.open_session(session)
    assert window.xray_orientation == TURN_BACK and combo.currentData() == TURN_BACK
    np.testing.assert_allclose(_points(window), synthetic_case.uv_px[1:4], atol=1e-9)
    assert window.result is not None and window.dialogs.messages == []  # the saved result, on the turned X-ray
    # another X-ray file is shown as stored
    window.load_xray(synthetic_case.xray_path)
    assert window.xray_orientation == "as-stored" and combo.currentData() == "as-stored"


def test_a_session_whose_turned_xray_is_missing_keeps_its_path_turn_and_points_until_it_is_found(
        window, synthetic_case, tmp_path):
    """Reopened without its X-ray (moved, a drive not mounted), a session with a turn is reported, and saved again
    it still names the file and the turn; the file found again is shown turned, its points with it."""
    xray_path, clicks_path, uv_stored = _stored_turned(synthetic_case, tmp_path)
    window.load_ct(synthetic_case.ct_path)
    window.load_xray(xray_path)
    window.import_xray_landmarks(clicks_path)
    window.set_xray_orientation(TURN_BACK)
    session = window.save_session(tmp_path / "work")
    away = xray_path.with_name("moved.dcm")
    xray_path.rename(away)
    window.open_session(session)
    assert "X-ray file not found" in window.dialogs.messages[-1][1] and window.xray is None
    assert not window.orientation_combo.isEnabled()
    np.testing.assert_allclose(_points(window), uv_stored, atol=1e-9)  # kept as stored: no image to turn them on
    saved = json.loads(window.save_session(tmp_path / "again").read_text())
    assert saved["version"] == 2 and saved["xray_orientation"] == TURN_BACK
    assert saved["data"]["xray"]["absolute"] == str(xray_path)
    np.testing.assert_allclose([p["uv_px"] for p in saved["landmarks"]["xray"]], uv_stored, atol=1e-9)
    away.rename(xray_path)
    window.load_xray(xray_path)
    assert window.xray_orientation == TURN_BACK and window.orientation_combo.currentData() == TURN_BACK
    np.testing.assert_allclose(_points(window), synthetic_case.uv_px[1:4], atol=1e-9)
    window.load_xray(synthetic_case.xray_path)  # another file: as stored, as always
    assert window.xray_orientation == "as-stored"


def test_without_an_xray_there_is_nothing_to_turn_and_a_session_without_a_turn_stays_version_1(window, tmp_path):
    from carmreg.logic.errors import InputFileError

    assert not window.orientation_combo.isEnabled()
    with pytest.raises(InputFileError, match="load an X-ray"):
        window.set_xray_orientation("mirrored-left-right")
    saved = json.loads(window.save_session(tmp_path / "empty").read_text())
    assert saved["version"] == 1 and "xray_orientation" not in saved


def test_the_sample_stored_mirrored_is_refused_offered_its_turn_and_then_names_its_levels(window, drr_cache_dir,
                                                                                           tmp_path):
    """The embedded sample (real CT, simulated C-arm image with distortion, K-wires and per-level motion) loaded,
    then its X-ray replaced by the same image stored mirrored (the same header) and its named clicks as that image
    shows them: the window refuses it, names no level and offers "Show the X-ray mirrored left right and register
    again". That one step turns image and clicks and registers the acquisition: the overlay names every CT level
    that projects into the image, each visible level within 5 mm (detector) of its true position, also those not
    clicked. Undoing the turn leaves the result out of date, nothing offered."""
    from carmreg.logic.errors import InputFileError
    from carmreg.logic.resources import sample_case

    try:
        paths = sample_case()
    except InputFileError as exc:
        pytest.skip(str(exc))
    window.parameter_overrides = {"cache_dir": drr_cache_dir}  # the level check judges the display at the clicks
    window.load_sample_case()
    ct_levels = window.ct_store.labels()
    acquired = load_xray(paths["xray"])
    cols = acquired.size_px[0]
    mirrored_path = write_xray_dicom(tmp_path / "mirrored.dcm",
                                     np.ascontiguousarray(acquired.pixels.astype(np.uint16)[:, ::-1]),
                                     acquired.intrinsics, sod_mm=acquired.sod_mm)
    clicks = read_landmarks_2d(paths["xray_landmarks"])
    write_landmarks_2d(tmp_path / "mirrored.mrk.json",
                       Landmarks2D(clicks.labels, clicks.uv_px * [-1, 1] + [cols - 1, 0]), None)
    window.load_xray(mirrored_path)
    window.import_xray_landmarks(tmp_path / "mirrored.mrk.json")
    window.run_registration(wait=True)
    refused = window.result
    assert refused.appearance.orientation == "mirrored-left-right" and not refused.ok
    assert refused.level_check.withheld and "--orient-xray mirrored-left-right" in refused.level_check.message
    button = window.result_panel.turn_button
    assert button.isVisible() and button.text() == "Show the X-ray mirrored left right and register again"
    window.result_panel.turn_requested.disconnect()  # the same step, waiting for the registration to finish
    window.result_panel.turn_requested.connect(lambda name: window.turn_and_register(name, wait=True))
    button.click()
    assert window.dialogs.messages == [], window.dialogs.messages
    result = window.result
    assert window.xray_orientation == "mirrored-left-right" and result.appearance.orientation == "as-stored"
    assert result.ok and result.level_check.status == "confident", result.warnings
    np.testing.assert_allclose(_points(window), clicks.uv_px, atol=1e-9)
    assert not button.isVisible()
    in_image = [lv["label"] for lv in result.levels if lv["in_image"]]
    assert [lv["label"] for lv in result.levels] == ct_levels
    assert window.overlay_view.level_names() == in_image and len(in_image) >= 4
    fitted = [lv for lv in result.levels if lv["fitted"]]
    # the image refinement weighs the clicks lightly (they carry click noise, per-level motion and distortion):
    # the clicked levels may sit a little off the clicks; the true positions are checked below
    assert len(fitted) >= 3 and max(lv["pde_mm"] for lv in fitted) < 3.0
    truth = json.loads(paths["ground_truth"].read_text())["levels"]
    spacing = result.geometry.intrinsics.pixel_spacing_mm[0]
    visible = [lv for lv in result.levels if truth.get(lv["label"], {}).get("visible")]
    assert len(visible) >= 4
    for lv in visible:
        err_mm = float(np.hypot(*(np.asarray(lv["uv_px"]) - truth[lv["label"]]["uv_true_px"]))) * spacing
        assert err_mm < 5.0, (lv["label"], err_mm)
    window.undo_stack.undo()  # the turn: the result is out of date, nothing offered
    assert window.xray_orientation == "as-stored" and window.result_stale and not button.isVisible()
