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
    """The sample X-ray written twice, as acquired and mirrored left-right (the same header), with its named clicks
    as each shows them: the mirrored one registered with ``--orient-xray mirrored-left-right`` finds the pose and
    the level answer of the acquisition, and result.json says it was turned."""
    xray = load_xray(sample_case_dir / "xray.dcm")
    pixels = xray.pixels.astype(np.uint16)
    assert np.array_equal(pixels, xray.pixels)  # 16-bit integers: written again exactly
    cols = xray.size_px[0]
    truth = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    as_shown = (("acquired", pixels, truth.uv_px[:, 0]), ("mirrored", pixels[:, ::-1], cols - 1 - truth.uv_px[:, 0]))
    for name, image, u in as_shown:
        write_xray_dicom(tmp_path / f"{name}.dcm", np.ascontiguousarray(image), xray.intrinsics, sod_mm=xray.sod_mm)
        clicks = {lb: [float(uu), float(v)] for lb, uu, v in zip(truth.labels, u, truth.uv_px[:, 1], strict=True)}
        (tmp_path / f"{name}.json").write_text(json.dumps(clicks))
    acquired = _register(sample_case_dir, tmp_path / "acquired.dcm", tmp_path / "acquired.json", tmp_path / "a",
                         drr_cache_dir)
    capsys.readouterr()
    turned = _register(sample_case_dir, tmp_path / "mirrored.dcm", tmp_path / "mirrored.json", tmp_path / "m",
                       drr_cache_dir, "--orient-xray", "mirrored-left-right")
    assert "(turned mirrored-left-right)" in capsys.readouterr().out
    np.testing.assert_allclose(turned["projection_matrix"], acquired["projection_matrix"], rtol=1e-6, atol=1e-6)
    assert turned["level_check"]["status"] == acquired["level_check"]["status"] == "confident"
    assert [(lv["label"], lv["in_image"]) for lv in turned["levels"]] == [(lv["label"], lv["in_image"])
                                                                          for lv in acquired["levels"]]
    assert turned["appearance"]["orientation"] == "as-stored" and turned["ok"]
    assert "mirrored left right as the user asked" in turned["inputs"]["geometry_sources"]["orientation"]
    assert "orientation" not in acquired["inputs"]["geometry_sources"]
