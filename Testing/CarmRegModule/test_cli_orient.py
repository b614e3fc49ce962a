"""`carmreg register --orient-xray`: an X-ray whose display was stored mirrored is turned back, with its clicks,
before registering (``image.turn``), and registers as the acquisition itself does; the turn is recorded."""

import json

import numpy as np
import pytest

from carmreg.cli import main
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


def test_a_display_stored_mirrored_and_turned_back_registers_as_the_acquisition(sample_case_dir, tmp_path,
                                                                                  drr_cache_dir, capsys):
    """The sample X-ray written mirrored left-right (the same header), with its named clicks as that image shows
    them, registered with ``--orient-xray mirrored-left-right``: confident, every level the acquisition shows named
    where it shows it (within 5 mm on the detector), and result.json says it was turned. (That a turned-back display
    gives the acquisition's own matrix: ``Testing/test_slicer_module.py``, the same turn from Slicer's nodes; the
    window's: ``test_orientation_gui.py``.)"""
    xray = load_xray(sample_case_dir / "xray.dcm")
    pixels = xray.pixels.astype(np.uint16)
    assert np.array_equal(pixels, xray.pixels)  # 16-bit integers: written again exactly
    cols = xray.size_px[0]
    truth = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    write_xray_dicom(tmp_path / "mirrored.dcm", np.ascontiguousarray(pixels[:, ::-1]), xray.intrinsics,
                     sod_mm=xray.sod_mm)
    clicks = {lb: [float(cols - 1 - u), float(v)] for lb, (u, v) in zip(truth.labels, truth.uv_px, strict=True)}
    (tmp_path / "mirrored.json").write_text(json.dumps(clicks))
    turned = _register(sample_case_dir, tmp_path / "mirrored.dcm", tmp_path / "mirrored.json", tmp_path / "m",
                       drr_cache_dir, "--orient-xray", "mirrored-left-right")
    assert "(turned mirrored-left-right)" in capsys.readouterr().out
    assert turned["level_check"]["status"] == "confident" and turned["ok"]
    assert turned["appearance"]["orientation"] == "as-stored"
    assert "mirrored left right as the user asked" in turned["inputs"]["geometry_sources"]["orientation"]
    assert turned["inputs"]["xray_turned"] == "mirrored-left-right"
    levels = json.loads((sample_case_dir / "ground_truth.json").read_text())["levels"]
    visible = {lb for lb, level in levels.items() if level["visible"]}
    assert {lv["label"] for lv in turned["levels"] if lv["in_image"]} >= visible and len(visible) >= 4
    for lv in turned["levels"]:
        if lv["label"] in visible:  # where the acquisition shows it, not where the mirrored file does
            error_px = np.hypot(*(np.asarray(lv["uv_px"]) - levels[lv["label"]]["uv_true_px"]))
            assert error_px * xray.intrinsics.pixel_spacing_mm[0] < 5.0, lv
