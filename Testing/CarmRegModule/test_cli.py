"""The command line on real data: `carmreg drr` and `carmreg simulate` on the sample CT (in-process), and the
installed `carmreg` script as a real process."""

import json
import subprocess
import sys
from pathlib import Path

import nrrd
import numpy as np
import pytest

from carmreg.cli import main
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, project
from carmreg.logic.io.volumes import load_volume
from carmreg.logic.io.xray import load_xray


def test_drr_writes_png_and_nrrd_whose_geometry_matches(sample_case_dir, tmp_path, capsys):
    code = main(["drr", "--ct", str(sample_case_dir / "ct.nrrd"), "--out", str(tmp_path / "drr"),
                 "--pose", "10", "5", "-40", "2", "0", "3", "--size-px", "96", "80", "--sdd-mm", "1000",
                 "--pixel-spacing-mm", "2.0", "--sod-mm", "600"])
    assert code == 0 and "wrote" in capsys.readouterr().out
    data, header = nrrd.read(str(tmp_path / "drr.nrrd"))
    assert data.shape == (96, 80, 1) and (tmp_path / "drr.png").stat().st_size > 0
    ct = load_volume(sample_case_dir / "ct.nrrd")
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (2.0, 2.0), (96, 80)), tuple(ct.center_lps_mm()), 600.0)
    P = np.array([float(x) for x in header["projection_matrix"].split()]).reshape(3, 4)
    np.testing.assert_allclose(P, geometry.projection_matrix(np.array([10, 5, -40, 2, 0, 3.0])), rtol=1e-7)
    # the NRRD's embedding: pixel (u, v) sits on the detector where the ray through it meets the plane
    origin = np.asarray(header["space origin"], float)
    steps = np.asarray(header["space directions"], float)
    point = origin + 30 * steps[0] + 50 * steps[1]
    source = geometry.source_lps_mm(np.array([10, 5, -40, 2, 0, 3.0]))
    uv = project(P, (source + 0.5 * (point - source))[None])[0]  # any point on that ray
    np.testing.assert_allclose(uv, [30, 50], atol=1e-6)
    assert 0.5 < data.mean() < 20  # line integrals of a body, dimensionless
    normal = steps[2] / np.linalg.norm(steps[2])  # the one-slice axis: the detector normal, away from the source
    assert np.dot(normal, point - source) > 0 and abs(np.dot(normal, steps[0])) < 1e-9


def test_the_installed_script_ends_at_once_with_its_output_flushed_and_its_files_whole(sample_case_dir, tmp_path):
    """``carmreg.cli.run`` ends a windowless command with ``os._exit``: what it printed must still reach a pipe,
    the exit code must be main's, and the files it wrote must be whole."""
    script = Path(sys.executable).with_name("carmreg")
    if not script.is_file():
        pytest.skip(f"the console script {script} is not installed (pip install -e .)")
    done = subprocess.run([str(script), "drr", "--ct", str(sample_case_dir / "ct.nrrd"), "--out", str(tmp_path / "d"),
                           "--size-px", "64", "48", "--pixel-spacing-mm", "4.0"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stderr == ""
    assert done.stdout.startswith("DRR 64x48 px") and done.stdout.endswith(f"{tmp_path / 'd.nrrd'}\n")
    data, _ = nrrd.read(str(tmp_path / "d.nrrd"))
    assert data.shape == (64, 48, 1) and np.isfinite(data).all() and data.max() > 0.5
    refused = subprocess.run([str(script), "drr", "--out", str(tmp_path / "e"), "--size-px", "1", "48"],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.startswith("carmreg: error: --size-px 1 48")


@pytest.mark.slow
def test_simulate_writes_an_xray_with_its_ground_truth(tmp_path, capsys):
    code = main(["simulate", "--out", str(tmp_path / "sim"), "--seed", "3", "--size-px", "256", "--level", "T11"])
    assert code == 0
    truth = json.loads((tmp_path / "sim" / "ground_truth.json").read_text())
    xray = load_xray(tmp_path / "sim" / "xray.dcm")
    assert xray.size_px == (256, 256) and xray.intrinsics.sdd_mm == pytest.approx(truth["intrinsics"]["sdd_mm"])
    P = np.array(truth["projection_matrix"])
    assert P.shape == (3, 4)
    visible = [lb for lb, v in truth["levels"].items() if v["visible"]]
    assert len(visible) >= 3


def test_sample_ct_round_trips_through_a_dicom_series(sample_case_dir, tmp_path):
    from carmreg.logic.io.volumes import write_dicom_series

    ct = load_volume(sample_case_dir / "ct.nrrd")
    write_dicom_series(tmp_path / "dicom", ct)
    back = load_volume(tmp_path / "dicom")
    # same voxels at the same LPS positions (a left-handed grid comes back with its slice axis reversed)
    centre_hu = ct.hu[180, 134, 66]
    lps = (ct.ijk_to_lps @ [180, 134, 66, 1])[:3]
    ijk = np.round((np.linalg.inv(back.ijk_to_lps) @ np.append(lps, 1))[:3]).astype(int)
    assert back.hu[tuple(ijk)] == centre_hu
    np.testing.assert_allclose(sorted(back.spacing_mm), sorted(ct.spacing_mm), atol=1e-3)
    np.testing.assert_allclose(back.corners_lps_mm().min(0), ct.corners_lps_mm().min(0), atol=1e-2)
    assert back.hu.sum() == ct.hu.astype(np.int64).sum()
