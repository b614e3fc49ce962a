"""Vertebral landmarks: level names, .mrk.json and plain JSON (3D and 2D), pairing CT and X-ray by label."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from carmreg.logic.errors import InputFileError, LandmarkError
from carmreg.logic.io.landmarks import (
    LEVEL_NAMES,
    Landmarks2D,
    Landmarks3D,
    next_level,
    normalize_level_name,
    pair_by_label,
    read_landmarks_2d,
    read_landmarks_3d,
    write_landmarks_2d,
    write_landmarks_3d,
)

CT = Landmarks3D(["T11", "T12", "L1", "L2"],
                 [[1.5, -20.25, 100.0], [2.0, -18.0, 72.125], [2.5, -15.5, 40.0], [3.0, -12.0, 5.5]])


def _mrk(points, system="LPS", extra=None):
    markup = {"type": "Fiducial", "coordinateSystem": system, "controlPoints": points}
    markup.update(extra or {})
    return {"@schema": "x", "markups": [markup]}


def _write(tmp_path, name, doc):
    path = tmp_path / name
    path.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return path


# ----------------------------------------------------------------------------------------------- names

@pytest.mark.parametrize("raw, name", [("t12", "T12"), (" T 12 ", "T12"), ("l-1", "L1"), ("C7", "C7"),
                                       ("S1", "S1"), ("L6", "L6"), ("T13", "T13"), ("t01", "T1")])
def test_normalize_level_name(raw, name):
    assert normalize_level_name(raw) == name


@pytest.mark.parametrize("raw", ["X1", "T14", "S2", "C8", "L0", "", "T12a", "vertebra"])
def test_unknown_level_names_refused(raw):
    with pytest.raises(LandmarkError, match="not a vertebral level"):
        normalize_level_name(raw)


def test_level_order_and_next_level():
    assert LEVEL_NAMES[17:22] == ["T11", "T12", "T13", "L1", "L2"] and len(LEVEL_NAMES) == 27
    assert next_level(None) == "T12" and next_level("T12") == "L1" and next_level("L1", -2) == "T11"
    assert next_level("l5") == "S1" and next_level("T13") == "L1" and next_level("L6", -1) == "L5"
    assert next_level("S1") == "S1" and next_level("C1", -1) == "C1"


# ----------------------------------------------------------------------------------------------- 3D

def test_3d_round_trip_mrk_json(tmp_path):
    path = write_landmarks_3d(tmp_path / "ct.mrk.json", CT)
    doc = json.loads(path.read_text())
    markup = doc["markups"][0]
    assert doc["@schema"].endswith("markups-schema-v1.0.3.json#")
    assert markup["coordinateSystem"] == "LPS" and markup["coordinateUnits"] == "mm"
    assert [p["label"] for p in markup["controlPoints"]] == CT.labels
    back = read_landmarks_3d(path)
    assert back.labels == CT.labels
    np.testing.assert_array_equal(back.points_lps_mm, CT.points_lps_mm)


def test_3d_ras_input_is_converted_to_lps(tmp_path):
    doc = _mrk([{"label": "T12", "position": [10.0, 20.0, 30.0]},
                {"label": "L1", "position": [-1.0, -2.0, 3.0], "positionStatus": "defined"}], system="RAS")
    back = read_landmarks_3d(_write(tmp_path, "ras.mrk.json", doc))
    np.testing.assert_array_equal(back.points_lps_mm, [[-10.0, -20.0, 30.0], [1.0, 2.0, 3.0]])


def test_3d_plain_json_and_undefined_points(tmp_path):
    back = read_landmarks_3d(_write(tmp_path, "p.json", {"t12": [1, 2, 3], "L 1": [4, 5, 6]}))
    assert back.labels == ["T12", "L1"]
    np.testing.assert_array_equal(back.as_dict()["L1"], [4, 5, 6])
    doc = _mrk([{"label": "T12", "position": [1, 2, 3]},
                {"label": "L1", "position": [0, 0, 0], "positionStatus": "undefined"}])
    assert read_landmarks_3d(_write(tmp_path, "u.mrk.json", doc)).labels == ["T12"]


def test_3d_sorted_head_to_sacrum():
    shuffled = Landmarks3D(["L2", "T11", "L1"], [[0, 0, 3], [0, 0, 1], [0, 0, 2]])
    assert shuffled.sorted().labels == ["T11", "L1", "L2"]
    np.testing.assert_array_equal(shuffled.sorted().points_lps_mm[:, 2], [1, 2, 3])


def test_3d_duplicates_nan_and_unknown_names(tmp_path):
    with pytest.raises(LandmarkError, match="T12 is labelled more than once"):
        read_landmarks_3d(_write(tmp_path, "d.mrk.json", _mrk([{"label": "T12", "position": [1, 2, 3]},
                                                               {"label": "t 12", "position": [4, 5, 6]}])))
    with pytest.raises(LandmarkError, match="not a finite number"):
        read_landmarks_3d(_write(tmp_path, "n.json", '{"T12": [1.0, NaN, 3.0]}'))
    with pytest.raises(LandmarkError, match="'X9' is not a vertebral level"):
        read_landmarks_3d(_write(tmp_path, "x.mrk.json", _mrk([{"label": "X9", "position": [1, 2, 3]}])))
    with pytest.raises(LandmarkError, match="not a vertebral level"):  # an unnamed CT point
        read_landmarks_3d(_write(tmp_path, "e.mrk.json", _mrk([{"label": "", "position": [1, 2, 3]}])))


def test_3d_bad_files(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_landmarks_3d(tmp_path / "none.mrk.json")
    with pytest.raises(InputFileError, match="not a valid JSON"):
        read_landmarks_3d(_write(tmp_path, "bad.json", "{not json"))
    with pytest.raises(InputFileError, match="not a Slicer markups file"):
        read_landmarks_3d(_write(tmp_path, "m.json", {"markups": []}))
    with pytest.raises(InputFileError, match="coordinateSystem 'IJK'"):
        read_landmarks_3d(_write(tmp_path, "i.json", _mrk([], system="IJK")))
    with pytest.raises(InputFileError, match="no 3-number position"):
        read_landmarks_3d(_write(tmp_path, "p.json", _mrk([{"label": "T12", "position": [1, 2]}])))
    with pytest.raises(InputFileError, match=r"level names to \[x, y, z\]"):
        read_landmarks_3d(_write(tmp_path, "q.json", {"T12": [1, 2]}))
    with pytest.raises(InputFileError, match="not a Slicer markups file"):
        read_landmarks_3d(_write(tmp_path, "r.json", _mrk([1, 2])))


# ----------------------------------------------------------------------------------------------- 2D

def test_2d_round_trip_with_spacing(tmp_path):
    xray = Landmarks2D(["T12", None, "L1"], [[100.25, 200.5], [50.0, 60.0], [110.0, 260.75]])
    path = write_landmarks_2d(tmp_path / "xr.mrk.json", xray, pixel_spacing_mm=(0.3, 0.25))
    markup = json.loads(path.read_text())["markups"][0]
    assert markup["carmreg"]["pixel_spacing_mm"] == [0.3, 0.25]
    np.testing.assert_allclose(markup["controlPoints"][0]["position"], [100.25 * 0.3, 200.5 * 0.25, 0.0])
    back = read_landmarks_2d(path)
    assert back.labels == ["T12", None, "L1"] and not back.named
    np.testing.assert_array_equal(back.uv_px, xray.uv_px)
    assert back.pixel_spacing_mm == (0.3, 0.25)
    assert set(back.as_dict()) == {"T12", "L1"}


def test_2d_points_placed_in_slicer_use_position_over_spacing(tmp_path):
    doc = _mrk([{"label": "T12", "position": [30.0, 50.0, 0.0]}])
    back = read_landmarks_2d(_write(tmp_path, "s.mrk.json", doc), pixel_spacing_mm=(0.3, 0.25))
    np.testing.assert_allclose(back.uv_px, [[100.0, 200.0]])
    ras = _mrk([{"label": "T12", "position": [-30.0, -50.0, 0.0]}], system="RAS")
    back = read_landmarks_2d(_write(tmp_path, "r.mrk.json", ras), pixel_spacing_mm=(0.3, 0.25))
    np.testing.assert_allclose(back.uv_px, [[100.0, 200.0]])
    back = read_landmarks_2d(_write(tmp_path, "n.mrk.json", doc))  # no spacing known: 1 mm per pixel
    np.testing.assert_allclose(back.uv_px, [[30.0, 50.0]])


def test_2d_plain_json_named_and_unnamed(tmp_path):
    named = read_landmarks_2d(_write(tmp_path, "n.json", {"T12": [10, 20], "l1": [11, 40]}))
    assert named.labels == ["T12", "L1"] and named.named
    unnamed = read_landmarks_2d(_write(tmp_path, "u.json", [[10, 20], [11, 40], [12, 60]]))
    assert unnamed.labels == [None, None, None] and unnamed.uv_px.shape == (3, 2)
    assert unnamed.as_dict() == {}
    with pytest.raises(InputFileError, match=r"\[column, row\]"):
        read_landmarks_2d(_write(tmp_path, "b.json", [[1, 2, 3]]))
    with pytest.raises(InputFileError, match=r"\[column, row\]"):
        read_landmarks_2d(_write(tmp_path, "c.json", {"T12": "here"}))


def test_2d_duplicates_and_nan(tmp_path):
    with pytest.raises(LandmarkError, match="L1 is labelled more than once"):
        read_landmarks_2d(_write(tmp_path, "d.json", {"L1": [1, 2], "l 1": [3, 4]}))
    with pytest.raises(LandmarkError, match="not a finite number"):
        read_landmarks_2d(_write(tmp_path, "n.json", "[[1.0, 2.0], [Infinity, 3.0]]"))
    assert read_landmarks_2d(_write(tmp_path, "ok.json", [[1, 2], [1, 2]])).uv_px.shape == (2, 2)  # unnamed


def test_2d_malformed_control_points_are_input_errors(tmp_path):
    doc = _mrk([{"label": "T12", "position": [1, 2, 0], "carmreg": {"uv_px": ["a", "b"]}}])
    with pytest.raises(InputFileError, match="T12"):
        read_landmarks_2d(_write(tmp_path, "a.mrk.json", doc))
    with pytest.raises(InputFileError, match="not a Slicer markups file"):
        read_landmarks_2d(_write(tmp_path, "b.mrk.json", _mrk(["T12"])))


# ----------------------------------------------------------------------------------------------- pairing

def test_pair_by_label_not_by_index():
    xray = Landmarks2D(["L1", "T11", "T12"], [[30.0, 300.0], [10.0, 100.0], [20.0, 200.0]])
    pairs = pair_by_label(CT, xray)
    assert pairs.labels == ["T11", "T12", "L1"] and pairs.notes == []  # CT-only levels (L2) are normal: no note
    np.testing.assert_array_equal(pairs.uv_px, [[10.0, 100.0], [20.0, 200.0], [30.0, 300.0]])
    np.testing.assert_array_equal(pairs.points_lps_mm, CT.points_lps_mm[:3])


def test_pair_by_label_notes_xray_only_levels():
    xray = Landmarks2D(["T10", "T11", "T12", "L1", None], [[0, 50], [10, 100], [20, 200], [30, 300], [5, 5]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # notes are data, never Python warnings (the GUI runs this on a thread)
        pairs = pair_by_label(CT, xray)
    assert pairs.labels == ["T11", "T12", "L1"]
    assert pairs.notes == ["X-ray levels T10 have no CT centroid and are not used"]


def test_pair_by_label_needs_enough_common_levels():
    xray = Landmarks2D(["T12", "L1", "L4"], [[0, 0], [1, 1], [2, 2]])
    with pytest.raises(LandmarkError, match=r"only 2 level\(s\) \(T12, L1\).*at least 3"):
        pair_by_label(CT, xray)
    pairs = pair_by_label(CT, xray, minimum=2)
    assert pairs.labels == ["T12", "L1"] and any("L4" in n for n in pairs.notes)
    with pytest.raises(LandmarkError, match="none"):
        pair_by_label(CT, Landmarks2D([None, None, None], [[0, 0], [1, 1], [2, 2]]))
