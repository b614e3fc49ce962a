"""`carmreg register --orient-xray`: an X-ray whose display was stored transposed (a quarter turn and a mirror) is
turned back, with its clicks, before registering (``image.turn``), and registers as the acquisition itself does; the
turn is recorded. One whose clicks run across the image is refused at once, naming the quarter turn that undoes it
(``preflight.across``); without clicks, the image checks find the transpose and refuse it, naming it."""

import json

import numpy as np
import pytest

from carmreg.cli import main
from carmreg.logic.image.turn import turned_intrinsics
from carmreg.logic.io.landmarks import read_landmarks_2d
from carmreg.logic.io.xray import load_xray
from carmreg.logic.io.xray_write import write_xray_dicom

pytestmark = pytest.mark.slow


def _register(case_dir, xray, clicks, out, cache_dir, *extra) -> dict:
    code = main(["register", "--ct", str(case_dir / "ct.nrrd"), "--ct-landmarks",
                 str(case_dir / "ct_centroids.mrk.json"), "--xray", str(xray), "--xray-landmarks", str(clicks),
                 "--out", str(out), "--cache-dir", cache_dir, *extra])
    assert code == 0
    return json.loads((out / "result.json").read_text())


def test_a_display_stored_transposed_and_turned_back_registers_as_the_acquisition(sample_case_dir, tmp_path,
                                                                                    drr_cache_dir, capsys):
    """The sample X-ray written transposed (turned a quarter and mirrored: rows for columns, the same header), with its
    named clicks as that image shows them, registered with ``--orient-xray turned-270-and-mirrored``: confident,
    every level the acquisition shows named where it shows it (within 5 mm on the detector), and result.json says
    it was turned. (A display stored mirrored, turned back from Slicer's nodes to the acquisition's own matrix:
    ``Testing/test_slicer_module.py``; in the window: ``test_orientation_gui.py``.)"""
    xray = load_xray(sample_case_dir / "xray.dcm")
    pixels = xray.pixels.astype(np.uint16)
    assert np.array_equal(pixels, xray.pixels)  # 16-bit integers: written again exactly
    truth = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    intrinsics = turned_intrinsics(xray.intrinsics, "turned-270-and-mirrored")  # the detector as the file shows it
    write_xray_dicom(tmp_path / "transposed.dcm", np.ascontiguousarray(pixels.T), intrinsics, sod_mm=xray.sod_mm)
    clicks = {lb: [float(v), float(u)] for lb, (u, v) in zip(truth.labels, truth.uv_px, strict=True)}
    (tmp_path / "transposed.json").write_text(json.dumps(clicks))
    turned = _register(sample_case_dir, tmp_path / "transposed.dcm", tmp_path / "transposed.json", tmp_path / "m",
                       drr_cache_dir, "--orient-xray", "turned-270-and-mirrored")
    assert "(turned turned-270-and-mirrored)" in capsys.readouterr().out
    assert turned["level_check"]["status"] == "confident" and turned["ok"]
    assert turned["appearance"]["orientation"] == "as-stored"
    assert "turned 270 and mirrored as the user asked" in turned["inputs"]["geometry_sources"]["orientation"]
    assert turned["inputs"]["xray_turned"] == "turned-270-and-mirrored"
    levels = json.loads((sample_case_dir / "ground_truth.json").read_text())["levels"]
    visible = {lb for lb, level in levels.items() if level["visible"]}
    assert {lv["label"] for lv in turned["levels"] if lv["in_image"]} >= visible and len(visible) >= 4
    for lv in turned["levels"]:
        if lv["label"] in visible:  # where the acquisition shows it, not where the transposed file does
            error_px = np.hypot(*(np.asarray(lv["uv_px"]) - levels[lv["label"]]["uv_true_px"]))
            assert error_px * xray.intrinsics.pixel_spacing_mm[0] < 5.0, lv


def test_a_display_stored_turned_a_quarter_is_refused_at_once_naming_the_turn_that_undoes_it(
        sample_case_dir, tmp_path, capsys):
    """The sample X-ray written turned a quarter counter-clockwise, with its named clicks as that image shows them:
    one line, exit code 2, before any stage, naming ``--orient-xray turned-270``, the turn that puts the clicks back
    where the acquisition shows them (registering a display so turned back: ``test_orientation_gui.py``)."""
    from carmreg.logic.image.turn import ORIENTATIONS, orient_uv

    xray = load_xray(sample_case_dir / "xray.dcm")
    write_xray_dicom(tmp_path / "turned.dcm", np.ascontiguousarray(ORIENTATIONS["turned-90"](
        xray.pixels.astype(np.uint16))), xray.intrinsics, sod_mm=xray.sod_mm)
    truth = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    stored_uv = orient_uv(truth.uv_px, "turned-90", xray.size_px)
    (tmp_path / "turned.json").write_text(json.dumps(dict(zip(truth.labels, stored_uv.tolist(), strict=True))))
    code = main(["register", "--ct", str(sample_case_dir / "ct.nrrd"), "--ct-landmarks",
                 str(sample_case_dir / "ct_centroids.mrk.json"), "--xray", str(tmp_path / "turned.dcm"),
                 "--xray-landmarks", str(tmp_path / "turned.json"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and not (tmp_path / "out").exists()
    assert err.startswith("carmreg: error: the X-ray clicks run across the image (") and err.endswith(
        "--orient-xray turned-270")
    np.testing.assert_allclose(orient_uv(stored_uv, "turned-270", xray.size_px[::-1]), truth.uv_px, atol=1e-9)


def test_a_display_stored_transposed_without_clicks_is_refused_naming_the_transpose(sample_case_dir, tmp_path,
                                                                                    drr_cache_dir, capsys):
    """The sample X-ray written transposed (rows for columns), registered without clicks: the database's orientation
    scores include the transposes (``appearance.orientation_scores``), so the image is refused (exit 1, no level
    named) as matching the CT transposed, ``--orient-xray turned-270-and-mirrored`` advised (until stop 58 it ended
    ambiguous, every scored orientation at 0.18-0.26 GC)."""
    xray = load_xray(sample_case_dir / "xray.dcm")
    intrinsics = turned_intrinsics(xray.intrinsics, "turned-270-and-mirrored")
    write_xray_dicom(tmp_path / "transposed.dcm", np.ascontiguousarray(xray.pixels.astype(np.uint16).T), intrinsics,
                     sod_mm=xray.sod_mm)
    code = main(["register", "--ct", str(sample_case_dir / "ct.nrrd"), "--ct-landmarks",
                 str(sample_case_dir / "ct_centroids.mrk.json"), "--xray", str(tmp_path / "transposed.dcm"),
                 "--no-clicks", "--out", str(tmp_path / "out"), "--cache-dir", drr_cache_dir])
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    scores = doc["appearance"]["orientation_scores"]
    assert code == 1 and not doc["ok"] and doc["level_check"]["status"] != "confident"
    assert doc["appearance"]["orientation"] == "turned-270-and-mirrored"
    assert scores["turned-270-and-mirrored"] - scores["as-stored"] > 0.2 and len(scores) == 8
    assert "--orient-xray turned-270-and-mirrored" in capsys.readouterr().out
