"""Sessions in the window: save/reopen round trip, autosave + recovery after a real crash, unsaved-work prompts,
landmark import/export."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d

pytestmark = pytest.mark.gui
HERE = Path(__file__).resolve().parent


def _load_case(win, case):
    win.load_ct(case.ct_path)
    win.load_xray(case.xray_path)
    win.import_ct_landmarks(case.ct_landmarks_path)
    win.import_xray_landmarks(case.xray_landmarks_path)


def test_session_round_trip_restores_data_geometry_and_points(window, synthetic_case, tmp_path, qapp):
    from carmreg.main_window import CarmRegWidget
    from carmreg.qt_common import ScriptedDialogs

    _load_case(window, synthetic_case)
    window.apply_geometry({"sdd_mm": 1010.0})
    window.xray_store.add("L3", [118.0, 222.5])
    window.registration_panel.set_storage("linear-intensity")  # the X-ray settings travel with the session
    window.registration_panel.set_field("whole")
    path = window.save_session(tmp_path / "case")
    assert path.name == "case.carmreg.json"
    assert not window.is_dirty() and window.windowTitle() == "CarmReg - case.carmreg.json[*]"
    doc = json.loads(path.read_text())
    assert [p["label"] for p in doc["landmarks"]["xray"]] == ["T12", "L1", "L2", "L3"]
    assert doc["geometry_overrides"] == {"sdd_mm": 1010.0}

    other = CarmRegWidget(dialogs=ScriptedDialogs(), autosave=False, view3d_mode="message")
    try:
        other.open_session(path)
        assert other.ct_volume.shape == window.ct_volume.shape
        assert other.xray.intrinsics.sdd_mm == 1010.0
        assert "manual" in str(other.xray.sources.get("sdd_mm", "")).lower() or \
            other.geometry_panel.sources["sdd_mm"].text().startswith("entered by hand")
        assert other.ct_store.labels() == list(synthetic_case.labels)
        for a, b in zip(other.ct_store.points(), window.ct_store.points(), strict=True):
            np.testing.assert_allclose(a.position, b.position, atol=1e-9)
        assert other.xray_store.labels() == ["T12", "L1", "L2", "L3"]
        np.testing.assert_allclose(other.xray_store.find("L3").position, [118.0, 222.5])
        chosen = other.registration_parameters()
        assert (chosen.polarity, chosen.storage, chosen.xray_field) == ("auto", "linear-intensity", "whole")
        assert not other.is_dirty()
        assert other.undo_stack.count() == 0  # opening is not an undoable edit
    finally:
        other.discard_and_close()


CRASHING_RUN = textwrap.dedent("""
    import os, sys
    os.environ["QT_QPA_PLATFORM"] = "offscreen"
    from carmreg.qt_common import ensure_app, ScriptedDialogs, process_events
    from carmreg.main_window import CarmRegWidget
    app = ensure_app()
    win = CarmRegWidget(dialogs=ScriptedDialogs(), state_folder=sys.argv[1], view3d_mode="message")
    win.load_ct(sys.argv[2])
    win.import_ct_landmarks(sys.argv[3])
    win.ct_store.add("S1", [1.0, 2.0, 3.0])
    process_events(1500)   # the autosave timer fires after 0.7 s of quiet
    os._exit(3)            # crash: no clean exit, no prompt
""")


@pytest.mark.slow
def test_autosave_survives_a_crash_and_is_offered_for_recovery(window, synthetic_case, tmp_path):
    state = tmp_path / "state"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE.parents[1])] + sys.path))
    done = subprocess.run([sys.executable, "-c", CRASHING_RUN, str(state), str(synthetic_case.ct_path),
                           str(synthetic_case.ct_landmarks_path)], capture_output=True, text=True, timeout=120,
                          env=env)
    assert done.returncode == 3, done.stderr[-2000:]
    leftovers = list(state.glob("autosave-*.carmreg.json"))
    assert len(leftovers) == 1
    window.dialogs.answers["question"] = ["Recover"]
    assert window.offer_recovery() is True
    assert window.ct_store.labels() == list(synthetic_case.labels) + ["S1"]
    np.testing.assert_allclose(window.ct_store.find("S1").position, [1.0, 2.0, 3.0])
    assert window.ct_volume is not None and window.ct_path == str(synthetic_case.ct_path)
    assert window.is_dirty()  # recovered work is not saved anywhere yet
    assert "did not close normally" in window.dialogs.messages[-1][1]
    assert not leftovers[0].exists()  # taken over by this run's own autosave
    assert (state / f"autosave-{os.getpid()}.carmreg.json").exists()
    window.dialogs.answers["question"] = ["Recover"]
    assert window.offer_recovery() is False  # nothing left to recover


def test_discarding_a_crash_autosave_deletes_it(window, tmp_path):
    from carmreg.logic.io.session import Session, write_autosave

    state = tmp_path / "state"
    path = write_autosave(Session(ct_points=[{"label": "T1", "position_lps_mm": [0, 0, 0]}]), pid=999_999_9,
                          folder=state)
    window.dialogs.answers["question"] = ["Discard"]
    assert window.offer_recovery() is False
    assert not path.exists() and len(window.ct_store) == 0


def test_edits_are_autosaved_and_a_clean_close_removes_the_autosave(qapp, tmp_path):
    from carmreg.logic.io.session import load_session
    from carmreg.main_window import CarmRegWidget
    from carmreg.qt_common import ScriptedDialogs, process_events

    state = tmp_path / "state"
    win = CarmRegWidget(dialogs=ScriptedDialogs({"question": ["Discard"]}), state_folder=state,
                        view3d_mode="message")
    win.ct_store.add("T12", [0.0, 1.0, 2.0])
    process_events(1200)
    autosave = state / f"autosave-{os.getpid()}.carmreg.json"
    assert [p["label"] for p in load_session(autosave).ct_points] == ["T12"]
    assert win.autosave_label.text().startswith("Autosaved")
    assert win.close()  # asks: Discard
    assert "unsaved changes" in win.dialogs.messages[-1][1]
    assert not autosave.exists()


def test_unsaved_work_is_never_dropped_without_asking(window):
    window.xray_store.add("T12", [10.0, 20.0])
    window.dialogs.answers["question"] = ["Cancel"]
    assert window.new_session(ask=True) is False
    assert window.xray_store.labels() == ["T12"]
    assert window.close() is False  # Cancel (the default answer) keeps the window open
    window.dialogs.answers["question"] = ["Discard"]
    assert window.new_session(ask=True) is True
    assert len(window.xray_store) == 0 and not window.is_dirty()


def test_save_answer_saves_before_going_on(window, tmp_path):
    window.ct_store.add("L1", [0.0, 0.0, 0.0])
    window.dialogs.answers = {"question": ["Save"], "save_file": [str(tmp_path / "kept.carmreg.json")]}
    assert window.new_session(ask=True) is True
    assert [p["label"] for p in json.loads((tmp_path / "kept.carmreg.json").read_text())["landmarks"]["ct"]] == ["L1"]


def test_landmark_export_import_round_trip_as_slicer_markups(window, synthetic_case, tmp_path):
    _load_case(window, synthetic_case)
    ct_out = window.export_ct_landmarks(tmp_path / "ct_out.mrk.json")
    xr_out = window.export_xray_landmarks(tmp_path / "xr_out.mrk.json")
    ct = read_landmarks_3d(ct_out)
    xr = read_landmarks_2d(xr_out)
    assert ct.labels == list(synthetic_case.labels)
    np.testing.assert_allclose(ct.points_lps_mm, synthetic_case.centroids_lps_mm, atol=1e-9)
    np.testing.assert_allclose(xr.uv_px, synthetic_case.uv_px[1:4], atol=1e-9)
    assert json.loads(xr_out.read_text())["markups"][0]["carmreg"]["pixel_spacing_mm"] == [0.9, 0.9]
    window.dialogs.answers["open_file"] = [str(ct_out)]
    window._action_import_ct()
    assert window.ct_store.labels() == list(synthetic_case.labels)


def test_errors_from_the_logic_become_dialogs_not_crashes(window, tmp_path):
    bad = tmp_path / "broken.nrrd"
    bad.write_text("NRRD0004\ngarbage\n")
    window.dialogs.answers["open_file"] = [str(bad), str(tmp_path / "missing.mrk.json")]
    window._action_load_ct()
    window._action_import_ct()
    titles = [m[0] for m in window.dialogs.messages]
    assert titles == ["CarmReg", "CarmReg"]  # plain warnings: CarmRegErrors with a one-line message
    assert "broken.nrrd" in window.dialogs.messages[0][1]
    assert "missing.mrk.json" in window.dialogs.messages[1][1]
    assert all(m[2] is None for m in window.dialogs.messages)  # no traceback for user errors


def test_propose_centroids_from_a_vertebra_label_map(window, synthetic_case, tmp_path):
    from carmreg.logic.geometry.vertebrae import carmreg_label_value
    from carmreg.logic.geometry.volume import Volume
    from carmreg.logic.io.volumes import write_volume_nrrd

    window.load_ct(synthetic_case.ct_path)
    hu = window.ct_volume.hu
    labels = np.zeros(hu.shape, np.int16)
    body = hu == 450  # the synthetic vertebral bodies
    ijk = np.argwhere(body)
    lps = ijk @ window.ct_volume.ijk_to_lps[:3, :3].T + window.ct_volume.ijk_to_lps[:3, 3]
    for name, centre in zip(synthetic_case.labels, synthetic_case.centroids_lps_mm, strict=True):
        mine = np.abs(lps[:, 2] - centre[2]) < 12
        labels[tuple(ijk[mine].T)] = carmreg_label_value(name)
    path = write_volume_nrrd(tmp_path / "vertebrae.nrrd", Volume(labels, window.ct_volume.ijk_to_lps))
    window.ct_store.add("T11", [0.0, 0.0, 0.0])
    window.dialogs.answers = {"open_file": [str(path)], "question": ["Add missing"]}
    window._action_propose_centroids()
    assert window.ct_store.labels() == list(synthetic_case.labels)
    np.testing.assert_allclose(window.ct_store.find("T11").position, [0.0, 0.0, 0.0])  # kept
    for name, centre in zip(synthetic_case.labels[1:], synthetic_case.centroids_lps_mm[1:], strict=True):
        assert np.linalg.norm(window.ct_store.find(name).position - centre) < 1.5  # mm, voxel-grid centroid
    window.undo_stack.undo()
    assert window.ct_store.labels() == ["T11"]


BAD_AUTOSAVES = {
    "sdd_text": {"geometry_overrides": {"sdd_mm": "abc"}},
    "version_text": {"version": "abc"},
    "data_list": {"data": [1, 2]},
    "deep": None,  # 100 000 nested brackets
    "missing_ct": {"data": {"ct": {"path": "/nonexistent/ct.nrrd"}}},
}


@pytest.mark.parametrize("case", list(BAD_AUTOSAVES))
def test_a_bad_autosave_never_stops_the_window_and_is_set_aside(window, tmp_path, case):
    """Recovery of a damaged autosave: at most one dialog without a traceback, the window keeps working, the
    autosave is renamed ``*.unreadable-*`` so the next start does not offer (and fail on) it again."""
    state = tmp_path / "state"
    state.mkdir(exist_ok=True)
    path = state / "autosave-9999999.carmreg.json"
    change = BAD_AUTOSAVES[case]
    if change is None:
        path.write_text('{"format": "carmreg-session", "data": ' + "[" * 100_000 + "]" * 100_000 + "}")
    else:
        path.write_text(json.dumps({"format": "carmreg-session", "version": 1, **change}))
    window.dialogs.answers["question"] = ["Recover"]
    assert window.offer_recovery() is False or case == "missing_ct"
    assert not path.exists()
    errors = [m for m in window.dialogs.messages if "Traceback" in " ".join(filter(None, m))]
    assert errors == []
    if case != "missing_ct":
        assert len(list(state.glob("autosave-9999999.carmreg.json.unreadable-*"))) == 1
        assert "could not be restored" in window.dialogs.messages[-1][1]
    assert window.offer_recovery() is False  # nothing offered at the next start
