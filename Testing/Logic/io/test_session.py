"""Session file model: readable JSON round trip, relative data paths, errors, autosave and recovery."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from carmreg.logic.errors import InputFileError, LandmarkError
from carmreg.logic.io import session as s


def _session(tmp_path):
    (tmp_path / "data").mkdir(exist_ok=True)
    ct = tmp_path / "data" / "ct.nrrd"
    xray = tmp_path / "data" / "xray.dcm"
    ct.write_bytes(b"x")
    xray.write_bytes(b"x")
    return s.Session(ct_path=str(ct), xray_path=str(xray),
                     geometry_overrides={"sdd_mm": 1020.0, "pixel_spacing_mm": [0.194, 0.194], "preset": "fp",
                                         "distortion_mm": -1.25},
                     ct_points=[{"label": "L1", "position_lps_mm": [1.5, -2.25, 30.0]},
                                {"label": "T12", "position_lps_mm": [1.0, -2.0, 61.125]}],
                     xray_points=[{"label": "T12", "uv_px": [100.25, 50.5]}, {"label": None, "uv_px": [3, 4]}],
                     parameters={"metric": "gc"})


def test_round_trip_keeps_every_field_and_orders_levels_head_to_sacrum(tmp_path):
    original = _session(tmp_path)
    path = s.save_session(tmp_path / "case.carmreg.json", original)
    loaded = s.load_session(path)
    assert loaded.ct_path == original.ct_path and loaded.xray_path == original.xray_path
    assert loaded.geometry_overrides == original.geometry_overrides
    assert [p["label"] for p in loaded.ct_points] == ["T12", "L1"]  # sorted T12 before L1
    assert loaded.ct_points[0]["position_lps_mm"] == [1.0, -2.0, 61.125]
    assert loaded.xray_points[1] == {"label": None, "uv_px": [3.0, 4.0]}
    assert loaded.parameters == {"metric": "gc"}
    lm = loaded.ct_landmarks()
    np.testing.assert_allclose(lm.as_dict()["L1"], [1.5, -2.25, 30.0])


def test_file_is_readable_json_with_relative_paths_and_survives_moving_the_folder(tmp_path):
    path = s.save_session(tmp_path / "case.carmreg.json", _session(tmp_path))
    doc = json.loads(path.read_text())
    assert doc["format"] == "carmreg-session" and doc["version"] == 1
    assert doc["data"]["ct"]["path"] == "data/ct.nrrd"
    assert path.read_text().count("\n") > 20  # indented, one value per line: diff-able
    moved = tmp_path.parent / (tmp_path.name + "_moved")
    tmp_path.rename(moved)
    loaded = s.load_session(moved / "case.carmreg.json")
    assert loaded.ct_path == str(moved / "data" / "ct.nrrd")


def test_an_xray_orientation_round_trips_and_makes_the_file_version_2(tmp_path):
    """A turned X-ray (``image.turn``) is saved with its orientation as version 2, which an older CarmReg refuses
    (its result lies on the turned image); without a turn the file stays version 1, read as "as-stored"."""
    session = _session(tmp_path)
    session.xray_orientation = "turned-90"
    doc = json.loads(s.save_session(tmp_path / "turned.carmreg.json", session).read_text())
    assert doc["version"] == 2 and doc["xray_orientation"] == "turned-90"
    assert s.load_session(tmp_path / "turned.carmreg.json").xray_orientation == "turned-90"
    assert s.load_session(s.save_session(tmp_path / "plain.carmreg.json", _session(tmp_path))).xray_orientation \
        == "as-stored"
    doc["xray_orientation"] = "sideways"
    (tmp_path / "bad.carmreg.json").write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match="\"xray_orientation\" 'sideways' is not one of: as-stored"):
        s.load_session(tmp_path / "bad.carmreg.json")


def test_unnamed_ct_point_cannot_become_landmarks():
    session = s.Session(ct_points=[{"label": None, "position_lps_mm": [0, 0, 0]}])
    with pytest.raises(LandmarkError, match="no level name"):
        session.ct_landmarks()


@pytest.mark.parametrize("text, match", [
    ("not json", "not a readable session"),
    ('{"format": "something-else"}', "not a CarmReg session"),
    ('{"format": "carmreg-session", "version": 99}', "newer than this CarmReg"),
    ('{"format": "carmreg-session", "landmarks": {"ct": [{"label": "T1"}]}}', "position_lps_mm"),
    ('{"format": "carmreg-session", "landmarks": {"xray": [{"uv_px": [1, "a"]}]}}', "uv_px"),
    ('{"format": "carmreg-session", "geometry_overrides": {"sid": 3}}', "unknown geometry field"),
    ('{"format": "carmreg-session", "geometry_overrides": {"distortion_mm": "4 mm"}}',
     "geometry override distortion_mm = '4 mm' is not a number of mm"),
])
def test_bad_session_files_raise_input_file_error_naming_the_file(tmp_path, text, match):
    path = tmp_path / "bad.carmreg.json"
    path.write_text(text)
    with pytest.raises(InputFileError, match=match) as info:
        s.load_session(path)
    assert "bad.carmreg.json" in str(info.value)


def test_missing_session_file(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        s.load_session(tmp_path / "nope.carmreg.json")


def test_failed_write_leaves_the_previous_session_intact(tmp_path, monkeypatch):
    path = s.save_session(tmp_path / "case.carmreg.json", _session(tmp_path))
    before = path.read_text()
    bad = _session(tmp_path)
    bad.parameters = {"x": object()}  # not JSON-serialisable: the write fails mid-way
    with pytest.raises(TypeError):
        s.save_session(path, bad)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_autosave_of_a_dead_process_is_recoverable_and_own_or_live_ones_are_not(tmp_path):
    session = _session(tmp_path)
    state = tmp_path / "state"
    mine = s.write_autosave(session, folder=state)
    assert mine.name == f"autosave-{os.getpid()}.carmreg.json"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    dead_pid = int(dead.stdout)
    s.write_autosave(session, pid=dead_pid, folder=state)
    s.write_autosave(session, pid=1, folder=state)  # pid 1 is alive: another running instance
    found = s.find_recoverable(state)
    assert found == [state / f"autosave-{dead_pid}.carmreg.json"]
    recovered = s.load_session(found[0])
    assert [p["label"] for p in recovered.ct_points] == ["T12", "L1"]
    s.clear_autosave(folder=state)
    assert not mine.exists()


def test_state_dir_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("CARMREG_STATE_DIR", str(tmp_path / "st"))
    assert s.state_dir() == tmp_path / "st"
    assert s.autosave_path(pid=42) == tmp_path / "st" / "autosave-42.carmreg.json"
    assert s.find_recoverable() == []
