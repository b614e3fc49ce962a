"""Broken inputs through the real command line: exit code 2 and one line ``carmreg: error: ...``.

Each case starts from a small valid case on disk (a 40^3 CT with four vertebral bodies, an XA DICOM rendered
from it with its geometry, landmarks named T11-L2) and breaks one thing. ``main([...])`` runs in-process with
stderr captured; two cases also run as real subprocesses (``python -m CarmRegModule.cli`` and the installed
``carmreg`` script), which is what a user's shell sees. Every error must be: exit code 2, exactly one line on
stderr starting ``carmreg: error:``, no traceback, and the message naming the problem.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pydicom
import pytest
from PIL import Image

from carmreg.cli import main
from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.geometry.volume import MuPyramid, Volume
from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d
from carmreg.logic.io.volumes import load_volume, write_dicom_series, write_volume_nrrd
from carmreg.logic.io.xray import load_xray, write_png16, write_xray_dicom
from carmreg.logic.registration.pipeline import CarmRegLogic

REPO = Path(__file__).resolve().parents[2]
LEVELS = ["T11", "T12", "L1", "L2"]


def _phantom() -> Volume:
    """40^3 voxels of 3 mm: a body cylinder and four bright vertebral bodies 28 mm apart along LPS z."""
    n, s = 40, 3.0
    affine = np.diag([s, s, s, 1.0])
    affine[:3, 3] = -s * (n - 1) / 2
    lps = np.indices((n, n, n)).reshape(3, -1).T * s + affine[:3, 3]
    hu = np.where(lps[:, 0] ** 2 + lps[:, 1] ** 2 < 50**2, 40.0, -1000.0)
    for z in (42.0, 14.0, -14.0, -42.0):
        hu[np.linalg.norm((lps - [0.0, 15.0, z]) / [10, 8, 8], axis=1) < 1] = 900
    return Volume(hu.reshape(n, n, n).astype(np.int16), affine, "phantom")


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict:
    """The valid files: ct.nrrd, xa.dcm (with SDD, SOD, pixel spacing), ct.json, xr.json."""
    folder = tmp_path_factory.mktemp("cli-case")
    ct = _phantom()
    centroids = {lb: [0.0, 15.0, z] for lb, z in zip(LEVELS, (42.0, 14.0, -14.0, -42.0), strict=True)}
    intrinsics = CarmIntrinsics(1000.0, (1.5, 1.5), (120, 120))
    geometry = CarmGeometry(intrinsics, tuple(ct.center_lps_mm()), 600.0)
    line = render_line_integrals(MuPyramid(ct).level(None), geometry, CarmPose(), intrinsics)
    pixels = np.clip(4000.0 * np.exp(-line), 0, 65535).astype(np.uint16)
    uv = project(geometry.projection_matrix(CarmPose()), np.array(list(centroids.values())))
    files = {"folder": folder, "pixels": pixels, "ct": write_volume_nrrd(folder / "ct.nrrd", ct),
             "xray": write_xray_dicom(folder / "xa.dcm", pixels, intrinsics, sod_mm=600.0),
             "ct_landmarks": folder / "ct.json", "xray_landmarks": folder / "xr.json"}
    files["ct_landmarks"].write_text(json.dumps(centroids))
    files["xray_landmarks"].write_text(json.dumps({lb: list(p) for lb, p in zip(LEVELS[:3], uv[:3].tolist(),
                                                                                  strict=True)}))
    return files


def register_args(case, **replace) -> list[str]:
    """``carmreg register`` on the case with some options replaced (value None drops the option)."""
    options = {"--ct": case["ct"], "--ct-landmarks": case["ct_landmarks"], "--xray": case["xray"],
               "--xray-landmarks": case["xray_landmarks"], "--out": case["folder"] / "out", "--no-cache": ""}
    options.update({f"--{k.replace('_', '-')}": v for k, v in replace.items()})
    argv = ["register"]
    for flag, value in options.items():
        if value is None:
            continue
        argv.append(flag)
        argv += [str(v) for v in value] if isinstance(value, (list, tuple)) else ([str(value)] if value != ""
                                                                                  else [])
    return argv


def assert_one_line_error(code: int, err: str, message: str) -> None:
    assert code == 2, (code, err)
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), err
    assert lines[0].startswith("carmreg: error: "), err
    assert message in lines[0], (message, lines[0])


def run(capsys, argv: list[str]) -> tuple[int, str]:
    code = main(argv)
    return code, capsys.readouterr().err


def test_the_valid_case_passes_validation(case):
    """The control: every case below fails because of its one broken input."""
    xray = load_xray(case["xray"])
    state = CarmRegLogic().prepare(load_volume(case["ct"]), read_landmarks_3d(case["ct_landmarks"]), xray,
                                   read_landmarks_2d(case["xray_landmarks"]))
    assert state.pairs.labels == ["T11", "T12", "L1"] and state.warnings == []


# ----------------------------------------------------------------------------------------------- broken files

def _write(case, name: str, content) -> Path:
    path = case["folder"] / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


def _mr_series(case) -> Path:
    folder = case["folder"] / "mr"
    if not folder.is_dir():
        for path in write_dicom_series(folder, Volume(np.zeros((8, 8, 4), np.int16), np.eye(4), "mr")):
            ds = pydicom.dcmread(path)
            ds.Modality = "MR"
            ds.save_as(path)
    return folder


def _multiframe(case) -> Path:
    ds = pydicom.dcmread(case["xray"])
    ds.NumberOfFrames = 3
    ds.PixelData = ds.PixelData * 3
    path = case["folder"] / "run.dcm"
    ds.save_as(path)
    return path


def _colour_png(case) -> Path:
    grey = (case["pixels"] // 16).astype(np.uint8)
    path = case["folder"] / "colour.png"
    Image.fromarray(np.stack([grey, grey, 255 - grey], -1)).save(path)
    return path


def _names_reversed(c) -> dict:
    """The case's named clicks with their names reversed along the spine (a display shown head-down, named right)."""
    clicks = json.loads(c["xray_landmarks"].read_text())
    return {"T11": clicks["L1"], "T12": clicks["T12"], "L1": clicks["T11"]}


def _transposed(c) -> list:
    """The case's clicks unnamed, columns and rows swapped (a display turned a quarter and mirrored)."""
    return [[v, u] for u, v in json.loads(c["xray_landmarks"].read_text()).values()]


CASES = {
    "missing CT file": (lambda c: {"ct": c["folder"] / "nope.nrrd"}, "nope.nrrd: CT not found"),
    "empty X-ray file": (lambda c: {"xray": _write(c, "empty.png", b"")}, "empty.png: X-ray file is empty"),
    "X-ray that is not an image": (lambda c: {"xray": _write(c, "notes.png", "meeting notes\n")},
                                   "notes.png: not a readable image"),
    "truncated CT": (lambda c: {"ct": _write(c, "cut.nrrd", c["ct"].read_bytes()[:300])},
                     "cut.nrrd: the NRRD voxel data cannot be read; the file or its data file is probably "
                     "truncated"),
    "RGB PNG with different channels": (lambda c: {"xray": _colour_png(c), "sdd_mm": 1000,
                                                   "pixel_spacing_mm": 1.5},
                                        "colour.png: is a colour image (its channels differ)"),
    "MR DICOM given as CT": (lambda c: {"ct": _mr_series(c)}, "has modality MR, not CT"),
    "multi-frame X-ray without --frame": (lambda c: {"xray": _multiframe(c)},
                                          "run.dcm: holds 3 frames; choose one with --frame N (0 to 2)"),
    "frame that does not exist": (lambda c: {"frame": 7}, "frame 7 does not exist; the file holds 1 frame"),
    "X-ray PNG without --sdd-mm": (lambda c: {"xray": write_png16(c["folder"] / "x.png", c["pixels"]),
                                              "pixel_spacing_mm": 1.5},
                                   "x.png: the source-to-detector distance (give --sdd-mm, about 1000 for a "
                                   "C-arm) is not in the file"),
    "landmarks with 2 pairs": (lambda c: {"xray_landmarks": _write(c, "two.json", {
        k: v for k, v in json.loads(c["xray_landmarks"].read_text()).items() if k != "L1"})},
                               "only 2 level(s) (T11, T12) are labelled on both the CT"),
    "two unnamed clicks": (lambda c: {"xray_landmarks": _write(c, "two_unnamed.json", [[60, 40], [60, 70]])},
                           "only 2 X-ray click(s): click the centres of at least 3"),
    "named clicks head-down": (lambda c: {"xray_landmarks": _write(c, "head_down.json", _names_reversed(c))},
                               "the named X-ray clicks run head-down (T11 lies below L1 on the image)"),
    "unnamed clicks across the image": (lambda c: {"xray_landmarks": _write(c, "across.json", _transposed(c))},
                                        "the X-ray clicks run across the image ("),
    "unknown level name": (lambda c: {"xray_landmarks": _write(c, "t14.json", {"T11": [1, 2],
                                                                             "T14": [3, 4]})},
                           "t14.json: landmark label 'T14' is not a vertebral level"),
    "NaN in landmarks": (lambda c: {"ct_landmarks": _write(c, "nan.json", '{"T11": [0, 15, NaN]}')},
                         "nan.json: a landmark position is not a finite number (NaN or infinity)"),
    "JSON that is not landmarks": (lambda c: {"ct_landmarks": _write(c, "session.json",
                                                                     {"version": 1, "ct": "ct.nrrd"})},
                                   "session.json: not a landmark file"),
    "CT landmarks outside the CT": (lambda c: {"ct_landmarks": _write(c, "far.json", {
        "T11": [0, 15, 442], "T12": [0, 15, 414], "L1": [0, 15, 386]})},
                                    "lie outside the CT volume"),
    "absurd --sdd-mm": (lambda c: {"sdd_mm": -1000}, "source-to-detector distance -1000.0 mm is not "
                                                     "plausible: give --sdd-mm between 100 and 3000"),
    "zero --pixel-spacing-mm": (lambda c: {"pixel_spacing_mm": 0}, "pixel spacing (0.0, 0.0) mm is not "
                                                                   "plausible"),
    "three --pixel-spacing-mm values": (lambda c: {"pixel_spacing_mm": [0.3, 0.3, 0.3]},
                                        "--pixel-spacing-mm takes one value, or column spacing then row"),
    "principal point off the detector": (lambda c: {"principal_point_px": [5000, 60]},
                                         "principal point (5000.0, 60.0) px lies off the 120x120 detector"),
    "--sod-mm beyond the detector": (lambda c: {"sod_mm": 1500}, "source-to-patient distance 1500 mm is not "
                                                                 "shorter than the source-to-detector"),
    "--distortion-mm of a typo": (lambda c: {"distortion_mm": 40}, "distortion 40 mm at 100 mm from the centre is "
                                                                  "not plausible: give --distortion-mm"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_broken_input_gives_one_line_and_exit_code_2(case, capsys, name):
    change, message = CASES[name]
    code, err = run(capsys, register_args(case, **change(case)))
    assert_one_line_error(code, err, message)


def test_argparse_errors_exit_2_without_traceback(case, capsys):
    """Malformed options are argparse's: exit 2, its usage line and one error line (not CarmReg's format)."""
    with pytest.raises(SystemExit) as stop:
        main(register_args(case, sdd_mm="abc"))
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "Traceback" not in err
    assert err.splitlines()[-1] == "carmreg register: error: argument --sdd-mm: invalid float value: 'abc'"


def test_drr_with_nan_pose_is_refused(case, capsys):
    code, err = run(capsys, ["drr", "--ct", str(case["ct"]), "--out", str(case["folder"] / "drr"),
                             "--size-px", "16", "16", "--pose", "nan", "0", "0", "0", "0", "0"])
    assert_one_line_error(code, err, "--pose")


def test_out_that_is_a_file_is_refused_before_registering(case, capsys):
    blocker = _write(case, "out-file", "not a folder")
    code, err = run(capsys, register_args(case, out=blocker))
    assert_one_line_error(code, err, "out-file")


# ----------------------------------------------------------------------------------------- real processes

def _subprocess(argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=REPO)


def test_real_process_python_m_missing_file(case):
    done = _subprocess([sys.executable, "-m", "carmreg.cli",
                        *register_args(case, xray=case["folder"] / "missing.dcm")])
    assert_one_line_error(done.returncode, done.stderr, "missing.dcm: X-ray file not found")
    assert done.stdout == ""


def test_real_process_installed_script_absurd_sdd(case):
    script = Path(sys.executable).with_name("carmreg")
    if not script.is_file():
        pytest.skip(f"the console script {script} is not installed (pip install -e .)")
    done = _subprocess([str(script), *register_args(case, sdd_mm=0)])
    assert_one_line_error(done.returncode, done.stderr, "source-to-detector distance 0.0 mm is not plausible")


def test_real_process_library_warnings_stay_off_stderr(case):
    """A non-conformant DICOM makes pydicom warn; the user still sees one line (the warning goes to meta)."""
    ds = pydicom.dcmread(case["xray"])
    del ds.DistanceSourceToDetector
    ds.save_as(case["folder"] / "nosdd.dcm")
    raw = (case["folder"] / "nosdd.dcm").read_bytes()
    uid_at = raw.index(b"\x08\x00\x18\x00UI") + 8  # SOPInstanceUID value made invalid ("x.2.826...")
    damaged = _write(case, "uid.dcm", raw[:uid_at] + b"x" + raw[uid_at + 1:])
    with pytest.warns(UserWarning, match="Invalid value for VR UI"):
        pydicom.dcmread(damaged).SOPInstanceUID  # noqa: B018 - the library does warn on this file
    done = _subprocess([sys.executable, "-m", "carmreg.cli", *register_args(case, xray=damaged)])
    assert_one_line_error(done.returncode, done.stderr, "uid.dcm: the source-to-detector distance")
    assert load_xray(damaged, sdd_mm=1000.0).meta["library_warnings"][0].startswith("Invalid value for VR UI")


def test_window_geometry_without_an_xray_is_refused(capsys):
    code, err = run(capsys, ["gui", "--sample", "--sdd-mm", "1000"])
    assert_one_line_error(code, err, "--sdd-mm and --pixel-spacing-mm describe the X-ray given with --xray")


def test_a_cache_dir_that_is_a_file_is_refused(case, capsys):
    blocker = _write(case, "cache-file", "not a folder")
    code, err = run(capsys, register_args(case, cache_dir=blocker, no_cache=None))
    assert_one_line_error(code, err, "this is a file, not a folder")
