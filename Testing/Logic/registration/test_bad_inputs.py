"""Bad input through the loaders and the logic class: each refusal is a CarmRegError naming the problem.

A registration tool that returns a confident overlay on wrong input is worse than one that refuses, so
every case asserts the message (what is wrong, where, what to do), not only the exception type. The inputs
are small and synthetic: a 64^3 CT (2 mm voxels) of a soft-tissue cylinder with four bright vertebral
bodies T11-L2 (28 mm apart) and rib-like bars, and a 200 x 200 px X-ray rendered from it with the exact
CPU DRR engine at a known C-arm pose, written as an XA DICOM with its geometry. ``prepare`` validates
without running any stage, so most cases take milliseconds; the few full registrations take ~2 s each.

Sections: geometry, landmarks, labelling mistakes (full registrations), huge headers (memory estimate
refuses before allocating), voxel and pixel values, transform files, the DRR database cache.
"""

from __future__ import annotations

import json
import struct
import time
import tracemalloc
import warnings
import zlib
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom
import pytest
from PIL import Image

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import CarmRegError, GeometryError, InputFileError, LandmarkError, RegistrationError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.geometry.volume import MuPyramid, Volume
from carmreg.logic.io.landmarks import (
    Landmarks2D,
    Landmarks3D,
    read_landmarks_2d,
    read_landmarks_3d,
    spine_order_warnings,
)
from carmreg.logic.io.transforms import read_tfm
from carmreg.logic.io.volumes import load_volume, write_dicom_series, write_volume_nrrd
from carmreg.logic.io.xray import load_xray, write_png16, write_xray_dicom
from carmreg.logic.registration.database import build_database
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters

LEVELS = ["T11", "T12", "L1", "L2"]
CENTROIDS_LPS_MM = np.array([[0.0, 15.0, z] for z in (42.0, 14.0, -14.0, -42.0)])
SDD_MM, SOD_MM, PIXEL_MM, SIZE_PX = 1000.0, 600.0, 1.0, (200, 200)
TRUE_POSE = CarmPose(10.0, 4.0, -6.0, 2.0, -1.0, 3.0)


# ----------------------------------------------------------------------------------------------- the case

def synthetic_ct() -> Volume:
    """64^3 voxels of 2 mm centred on the LPS origin: air, a body cylinder (40 HU), four vertebral bodies
    (700-1000 HU ellipsoids at CENTROIDS_LPS_MM) and rib-like bars (400 HU) every 28 mm."""
    n, s = 64, 2.0
    affine = np.diag([s, s, s, 1.0])
    affine[:3, 3] = -s * (n - 1) / 2
    lps = np.indices((n, n, n)).reshape(3, -1).T * s + affine[:3, 3]
    hu = np.full(n**3, -1000.0)
    body = lps[:, 0] ** 2 / 55**2 + lps[:, 1] ** 2 / 45**2 < 1
    hu[body] = 40
    for i, c in enumerate(CENTROIDS_LPS_MM):
        hu[np.linalg.norm((lps - c) / [9 + i, 7, 8], axis=1) < 1] = 700 + 100 * i
    hu[(np.abs(lps[:, 1] + 5) < 3) & (np.abs(lps[:, 2] % 28 - 14) < 2) & body] = 400
    return Volume(hu.reshape(n, n, n).astype(np.int16), affine, "synthetic-ct")


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict:
    """CT, its landmarks, the rendered X-ray (DICOM on disk) and the X-ray landmarks at the true pose."""
    folder = tmp_path_factory.mktemp("case")
    ct = synthetic_ct()
    intrinsics = CarmIntrinsics(SDD_MM, (PIXEL_MM, PIXEL_MM), SIZE_PX)
    geometry = CarmGeometry(intrinsics, tuple(ct.center_lps_mm()), SOD_MM)
    line = render_line_integrals(MuPyramid(ct).level(None), geometry, TRUE_POSE, intrinsics)
    pixels = np.clip(4000.0 * np.exp(-line), 0, 65535).astype(np.uint16)
    uv_px = project(geometry.projection_matrix(TRUE_POSE), CENTROIDS_LPS_MM)
    return {"folder": folder, "ct": ct, "ct_landmarks": Landmarks3D(LEVELS, CENTROIDS_LPS_MM, "ct.mrk.json"),
            "xray_path": write_xray_dicom(folder / "xa.dcm", pixels, intrinsics, sod_mm=SOD_MM),
            "pixels": pixels, "uv_px": uv_px, "xray_landmarks": Landmarks2D(LEVELS[:3], uv_px[:3], "xr.json")}


def prepare(case, *, ct=None, ct_landmarks=None, xray=None, xray_landmarks=None):
    """The logic class's validation (no stage run) on the case with one input replaced."""
    return CarmRegLogic().prepare(ct or case["ct"], ct_landmarks or case["ct_landmarks"],
                                  xray or load_xray(case["xray_path"]),
                                  xray_landmarks or case["xray_landmarks"])


def edited_dicom(case, name: str, **changes) -> Path:
    """A copy of the case X-ray with DICOM attributes changed (None deletes)."""
    ds = pydicom.dcmread(case["xray_path"])
    for key, value in changes.items():
        if value is None:
            delattr(ds, key)
        else:
            setattr(ds, key, value)
    path = case["folder"] / name
    ds.save_as(path)
    return path


def test_the_clean_case_passes_validation_without_warnings(case):
    """The control: every refusal below is caused by its one change."""
    state = prepare(case)
    assert state.pairs.labels == ["T11", "T12", "L1"] and state.warnings == []
    assert spine_order_warnings(case["ct_landmarks"], case["xray_landmarks"]) == []
    assert np.all((case["uv_px"] > 10) & (case["uv_px"] < 190))  # every level well inside the image


# ----------------------------------------------------------------------------------------------- geometry

def test_missing_sdd_or_pixel_spacing_without_manual_value(case):
    no_sdd = load_xray(edited_dicom(case, "nosdd.dcm", DistanceSourceToDetector=None))
    with pytest.raises(GeometryError, match=r"nosdd.dcm: the source-to-detector distance \(give --sdd-mm, "
                                            r"about 1000 for a C-arm\) is not in the file"):
        prepare(case, xray=no_sdd)
    no_spacing = load_xray(edited_dicom(case, "nospacing.dcm", ImagerPixelSpacing=None))
    with pytest.raises(GeometryError, match=r"nospacing.dcm: the detector pixel spacing \(give "
                                            r"--pixel-spacing-mm.*\) is not in the file"):
        prepare(case, xray=no_spacing)
    png = write_png16(case["folder"] / "bare.png", case["pixels"])
    with pytest.raises(GeometryError, match=r"bare.png: the source-to-detector distance .* and the detector "
                                            r"pixel spacing .* are not in the file"):
        prepare(case, xray=load_xray(png))
    state = prepare(case, xray=load_xray(png, sdd_mm=SDD_MM, pixel_spacing_mm=PIXEL_MM, sod_mm=SOD_MM))
    assert state.geometry.intrinsics.sources["sdd_mm"] == "manual"  # the manual values complete it


@pytest.mark.parametrize("manual, message", [
    ({"sdd_mm": -5.0}, r"source-to-detector distance -5.0 mm is not plausible: give --sdd-mm between 100"),
    ({"sdd_mm": 0.0}, r"source-to-detector distance 0.0 mm is not plausible"),
    ({"sdd_mm": float("nan")}, r"source-to-detector distance nan mm is not plausible"),
    ({"sdd_mm": 1e6}, r"source-to-detector distance 1000000.0 mm is not plausible"),
    ({"pixel_spacing_mm": 0.0}, r"pixel spacing \(0.0, 0.0\) mm is not plausible: give --pixel-spacing-mm"),
    ({"pixel_spacing_mm": (0.3, float("nan"))}, r"pixel spacing \(0.3, nan\) mm is not plausible"),
    ({"pixel_spacing_mm": -0.3}, r"pixel spacing \(-0.3, -0.3\) mm is not plausible"),
    ({"principal_point_px": (500.0, 80.0)}, r"principal point \(500.0, 80.0\) px lies off the 200x200 "
                                            r"detector"),
    ({"principal_point_px": (float("nan"), 80.0)}, r"principal point \(nan, 80.0\) px lies off"),
    ({"sod_mm": 0.0}, r"source-to-patient distance 0.0 mm is not positive; give --sod-mm"),
    ({"distortion_mm": 12.0}, r"distortion 12 mm at 100 mm from the centre is not plausible: give "
                              r"--distortion-mm from the C-arm's calibration"),
    ({"distortion_mm": float("nan")}, r"distortion nan mm at 100 mm from the centre is not plausible"),
    ({"sod_mm": 1500.0}, r"source-to-patient distance 1500 mm is not shorter than the source-to-detector "
                         r"distance 1000 mm"),
])
def test_absurd_manual_geometry_is_refused(case, manual, message):
    with pytest.raises(GeometryError, match="xa.dcm: " + message):
        load_xray(case["xray_path"], **manual)


@pytest.mark.parametrize("changes, message", [
    ({"DistanceSourceToDetector": "0"}, r"source-to-detector distance 0.0 mm is not plausible.*\(the value "
                                        r"was read from DICOM \(0018,1110\) DistanceSourceToDetector; the "
                                        r"manual value overrides it\)"),
    ({"ImagerPixelSpacing": ["0", "0"]}, r"pixel spacing \(0.0, 0.0\) mm .*read from DICOM \(0018,1164\)"),
    ({"DistanceSourceToPatient": "1200"}, r"source-to-patient distance 1200 mm \(from DICOM \(0018,1111\) "
                                          r"DistanceSourceToPatient\) is not shorter"),
])
def test_absurd_geometry_in_the_file_names_the_tag_it_came_from(case, changes, message):
    path = edited_dicom(case, "absurd.dcm", **changes)
    with pytest.raises(GeometryError, match="absurd.dcm: " + message):
        load_xray(path)


# ----------------------------------------------------------------------------------------------- landmarks

def _xr(labels, uv):
    return Landmarks2D(labels, uv, "xr.json")


def test_fewer_than_three_pairs(case):
    with pytest.raises(LandmarkError, match=r"only 2 level\(s\) \(T11, T12\) are labelled on both the CT "
                                            r"\(ct.mrk.json\) and the X-ray \(xr.json\); label at least 3"):
        prepare(case, xray_landmarks=_xr(["T11", "T12"], case["uv_px"][:2]))
    with pytest.raises(LandmarkError, match=r"only 2 X-ray click\(s\): click the centres of at least 3"):
        prepare(case, xray_landmarks=_xr([None, "T12"], case["uv_px"][:2]))  # too few to identify levels by
    state = prepare(case, xray_landmarks=_xr([None, None, None], case["uv_px"][:3]))  # unnamed: identified later
    assert state.pairs is None


def test_a_label_on_one_side_only_uses_the_common_levels_and_warns(case):
    uv = np.vstack([case["uv_px"][0] - [0, 28], case["uv_px"][:3]])  # T10 above T11, not in the CT
    state = prepare(case, xray_landmarks=_xr(["T10", "T11", "T12", "L1"], uv))
    assert state.pairs.labels == ["T11", "T12", "L1"]
    np.testing.assert_allclose(state.pairs.uv_px, case["uv_px"][:3])
    assert state.warnings == ["X-ray levels T10 have no CT centroid and are not used"]
    # CT-only levels (L2 here) are normal: the CT is labelled once, the X-ray shows a few levels
    assert "L2" in case["ct_landmarks"].labels and prepare(case).warnings == []


@pytest.mark.parametrize("doc, error, message", [
    ({"T12": [1, 2], "t 12": [3, 4]}, LandmarkError, r"bad.json: level T12 is labelled more than once"),
    ({"T12": [1, 2], "T14": [3, 4]}, LandmarkError, r"bad.json: landmark label 'T14' is not a vertebral"),
    ({"T12": [1, 2], "L7": [3, 4]}, LandmarkError, r"bad.json: landmark label 'L7' is not a vertebral level"),
    ({"T12": [1, 2], "vertebra 3": [3, 4]}, LandmarkError, r"'vertebra 3' is not a vertebral level: name "
                                                           r"points C1-C7, T1-T13, L1-L6 or S1"),
    ({"T12": [float("nan"), 2]}, LandmarkError, r"bad.json: a landmark position is not a finite number"),
    ({"version": 1, "ct": "ct.nrrd"}, InputFileError, r"bad.json: not a landmark file: expected a Slicer "
                                                      r"\.mrk\.json, or JSON mapping level names"),
    ({"markups": [{"controlPoints": [{"label": "T12", "position": [1, 2, 0]}],
                   "carmreg": {"pixel_spacing_mm": [0, 0.3]}}]}, InputFileError,
     r"bad.json: pixel spacing \(0.0, 0.3\) mm for the X-ray points is not positive"),
])
def test_bad_xray_landmark_files_name_the_file_and_the_problem(case, doc, error, message):
    path = case["folder"] / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(error, match=message):
        read_landmarks_2d(path)


def test_bad_ct_landmark_files_name_the_file_and_the_problem(case):
    path = case["folder"] / "bad3d.json"
    for doc, message in [({"T12": [1, 2, 3], "Q3": [1, 2, 4]}, r"bad3d.json: landmark label 'Q3' is not"),
                         ({"T12": [1, 2, float("inf")]}, r"bad3d.json: a landmark position is not a finite"),
                         ({"patient": "x"}, r"bad3d.json: not a landmark file")]:
        path.write_text(json.dumps(doc))
        with pytest.raises(CarmRegError, match=message):
            read_landmarks_3d(path)


def test_points_outside_the_ct_or_the_image(case):
    far = CENTROIDS_LPS_MM.copy()
    far[2] += [0.0, 0.0, 400.0]  # L1 400 mm above the scan
    with pytest.raises(LandmarkError, match=r"CT landmark\(s\) L1 in ct lie outside the CT volume synthetic-ct: "
                                            r"check the landmark file's coordinate system \(LPS vs RAS\)"):
        prepare(case, ct_landmarks=Landmarks3D(LEVELS, far, "ct"))
    off = case["uv_px"][:3].copy()
    off[0] = [-40.0, 20.0]
    with pytest.raises(LandmarkError, match=r"X-ray landmark\(s\) T11 lie outside the 200x200 image .*: "
                                            r"check they are \(column, row\) pixels"):
        prepare(case, xray_landmarks=_xr(LEVELS[:3], off))


def test_coincident_points(case):
    close = CENTROIDS_LPS_MM.copy()
    close[2] = close[1] + [0.3, 0.0, 0.4]  # L1 0.5 mm from T12
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the spacing warning comes first; the error is what matters
        with pytest.raises(LandmarkError, match="two CT landmarks are less than 1 mm apart"):
            prepare(case, ct_landmarks=Landmarks3D(LEVELS, close, "ct"))
    uv = case["uv_px"][:3].copy()
    uv[1] = uv[0] + 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(LandmarkError, match="two X-ray landmarks are less than 1 px apart"):
            prepare(case, xray_landmarks=_xr(LEVELS[:3], uv))


def test_nan_points_are_refused_at_construction():
    with pytest.raises(LandmarkError, match="ct.json: a landmark position is not a finite number"):
        Landmarks3D(["T12", "L1"], [[0, 0, 0], [np.nan, 0, 0]], "ct.json")
    with pytest.raises(LandmarkError, match="xr.json: a landmark position is not a finite number"):
        Landmarks2D(["T12", None], [[0, 0], [0, np.inf]], "xr.json")


def test_points_in_the_wrong_unit_and_swapped_labels_warn(case):
    in_cm = Landmarks3D(LEVELS, CENTROIDS_LPS_MM / 10.0, "ct_cm.json")  # 2.8 cm apart read as 2.8 mm
    state = prepare(case, ct_landmarks=in_cm, xray_landmarks=_xr(LEVELS[:3], case["uv_px"][:3]))
    assert any("CT centroid spacing per level is implausible (T11-T12 2.8 mm, T12-L1 2.8 mm, L1-L2 2.8 mm;"
               in w for w in state.warnings)  # T12-L1 is one level: the rare T13 is not counted
    swapped = _xr(["T12", "T11", "L1"], case["uv_px"][:3])
    state = prepare(case, xray_landmarks=swapped)
    assert state.warnings == ["X-ray levels are not in spine order: T12 does not follow T11 along the spine "
                              "from T11 to L1; two labels are probably swapped or misnamed, check them"]
    reversed_ct = Landmarks3D(LEVELS, CENTROIDS_LPS_MM[::-1], "ct")  # T11 lowest: a mislabelled file
    assert any("CT levels are not in spine order: T12" in w for w in spine_order_warnings(reversed_ct))


def test_many_duplicate_labels_are_refused_quickly():
    start = time.perf_counter()
    with pytest.raises(LandmarkError, match="T12 is labelled more than once"):
        Landmarks2D(["T12"] * 50_000, np.zeros((50_000, 2)), "huge.json")
    assert time.perf_counter() - start < 2.0


@pytest.mark.parametrize("setting, message", [
    ({"polarity": "bone-grey"}, "polarity 'bone-grey': use auto, bone-dark or bone-bright"),
    ({"storage": "raw"}, "storage 'raw': use auto, linear-intensity or log-display"),
    ({"xray_field": "round"}, "field 'round': use auto or whole"),
])
def test_a_polarity_storage_or_field_not_offered_is_refused_before_any_work(case, setting, message):
    with pytest.raises(RegistrationError, match=message):
        CarmRegLogic().prepare(case["ct"], case["ct_landmarks"], load_xray(case["xray_path"]),
                               case["xray_landmarks"], RegistrationParameters(**setting))


# ------------------------------------------------------------------------------------- labelling (full runs)

def test_swapped_labels_end_in_failed_checks_not_a_confident_pose(case):
    swapped = _xr(["T12", "T11", "L1"], case["uv_px"][:3])
    result = CarmRegLogic().register(case["ct"], case["ct_landmarks"], load_xray(case["xray_path"]), swapped,
                                     RegistrationParameters())
    assert not result.ok
    assert any("not in spine order" in w for w in result.warnings)
    assert any("mPDE" in w and "check the level names" in w for w in result.warnings)


def test_labels_shifted_by_one_level_are_flagged(case):
    """Every X-ray label one level too low (T11 clicked as T12, ...): the landmarks alone fit perfectly one
    vertebra away (wrong-level surgery), only the image can tell: the level check flags it."""
    shifted = _xr(["T12", "L1", "L2"], case["uv_px"][:3])
    result = CarmRegLogic().register(case["ct"], case["ct_landmarks"], load_xray(case["xray_path"]), shifted,
                                     RegistrationParameters())
    assert not result.ok or any("level" in w for w in result.warnings), result.warnings


# ----------------------------------------------------------------------------------------------- huge headers

def _refused_cheaply(load, path, message: str) -> None:
    """``load(path)`` refuses with ``message`` within 2 s and without allocating more than 50 MB."""
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(InputFileError, match=message):
            load(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - start < 2.0 and peak < 50e6, (time.perf_counter() - start, peak)


def test_huge_volume_headers_are_refused_before_allocating(tmp_path):
    (tmp_path / "huge.nrrd").write_bytes(b"NRRD0004\ntype: short\ndimension: 3\nsizes: 4000 4000 4000\n"
                                         b"encoding: raw\nendian: little\n\n" + bytes(64))
    _refused_cheaply(load_volume, tmp_path / "huge.nrrd", r"huge.nrrd: the volume 4000x4000x4000 needs 357.6 "
                                                          r"GiB, more than the 8 GiB limit; crop it")
    (tmp_path / "huge.mha").write_bytes(b"ObjectType = Image\nNDims = 3\nDimSize = 3000 3000 3000\n"
                                        b"ElementType = MET_FLOAT\nElementDataFile = LOCAL\n" + bytes(64))
    _refused_cheaply(load_volume, tmp_path / "huge.mha", r"huge.mha: the volume 3000x3000x3000 needs .* GiB")
    header = nib.Nifti1Header()
    header.set_data_shape((5000, 5000, 5000))
    header.set_data_dtype(np.int16)
    (tmp_path / "huge.nii").write_bytes(header.binaryblock + bytes(4) + bytes(64))
    _refused_cheaply(load_volume, tmp_path / "huge.nii", r"huge.nii: the volume 5000x5000x5000 needs .* GiB")


def test_huge_dicom_series_is_refused_before_allocating(tmp_path):
    files = write_dicom_series(tmp_path / "s", Volume(np.zeros((4, 4, 3), np.int16), np.eye(4), "tiny"))
    for f in files:
        ds = pydicom.dcmread(f)
        ds.Rows = ds.Columns = 40000
        ds.save_as(f)
    _refused_cheaply(load_volume, tmp_path / "s", r"s: the volume 40000x40000x3 needs .* GiB")


def _png_claiming(cols: int, rows: int) -> bytes:
    """A valid PNG header claiming a cols x rows 16-bit grey image, with a few bytes of image data."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", cols, rows, 16, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(64)))
            + chunk(b"IEND", b""))


def test_huge_xray_headers_are_refused_before_allocating(case, tmp_path):
    (tmp_path / "huge.png").write_bytes(_png_claiming(100_000, 100_000))
    _refused_cheaply(load_xray, tmp_path / "huge.png", r"huge.png: the image claims more than \d+ million")
    (tmp_path / "big.png").write_bytes(_png_claiming(9000, 9000))  # under Pillow's limit, over CarmReg's
    _refused_cheaply(load_xray, tmp_path / "big.png", r"big.png: a frame of 9000 x 9000 px is larger than "
                                                      r"any X-ray detector")
    path = edited_dicom(case, "rows.dcm", Rows=60000, Columns=60000)
    _refused_cheaply(load_xray, path, r"rows.dcm: a frame of 60000 x 60000 px is larger than any X-ray")
    path = edited_dicom(case, "run.dcm", Rows=2048, Columns=2048, NumberOfFrames=1000)
    _refused_cheaply(load_xray, path, r"run.dcm: 1000 frames of 2048 x 2048 px need 7.8 GiB, more than the "
                                      r"4 GiB limit; export the frame you want")


# ----------------------------------------------------------------------------------------------- values

def test_ct_with_nan_voxels_or_a_single_slice_is_refused(tmp_path):
    hu = np.zeros((8, 8, 6), np.float32)
    hu[2, 3, 4] = np.nan
    write_volume_nrrd(tmp_path / "nan.nrrd", Volume(hu, np.eye(4), "x"))
    with pytest.raises(InputFileError, match=r"nan.nrrd: 1 voxel\(s\) are NaN or infinite; fill them"):
        load_volume(tmp_path / "nan.nrrd")
    write_volume_nrrd(tmp_path / "flat.nrrd", Volume(np.zeros((64, 64, 1), np.int16), np.eye(4), "x"))
    with pytest.raises(InputFileError, match=r"flat.nrrd: the volume is 64x64x1 voxels; a CT for "
                                             r"registration needs at least 2 voxels along every axis"):
        load_volume(tmp_path / "flat.nrrd")


def test_blank_or_non_finite_xray_is_refused(case, tmp_path):
    write_png16(tmp_path / "blank.png", np.zeros((50, 60), np.uint16))
    with pytest.raises(InputFileError, match=r"blank.png: the image is blank \(every pixel is 0\)"):
        load_xray(tmp_path / "blank.png", sdd_mm=SDD_MM, pixel_spacing_mm=PIXEL_MM)
    pixels = np.ones((50, 60), np.float32)
    pixels[5, 5] = np.nan
    Image.fromarray(pixels).save(tmp_path / "nan.tif")
    with pytest.raises(InputFileError, match=r"nan.tif: 1 pixel\(s\) are not finite numbers"):
        load_xray(tmp_path / "nan.tif")


def test_damaged_slice_in_a_series_is_named_not_skipped(tmp_path):
    files = write_dicom_series(tmp_path / "s", Volume(np.zeros((6, 5, 4), np.int16), np.eye(4), "tiny"))
    raw = files[0].read_bytes()  # the first slice: skipping it would silently shorten the volume
    at = raw.index(b"\x20\x00\x32\x00")  # (0020,0032) ImagePositionPatient
    files[0].write_bytes(raw[:at + 4] + b"ZZ" + raw[at + 6:])  # its VR made unknown
    with pytest.raises(InputFileError, match=r"slice_0000.dcm: the DICOM header is damaged: \(0020,0032\) "
                                             r"ImagePositionPatient cannot be read"):
        load_volume(tmp_path / "s")
    files[0].write_bytes(raw)
    ds = pydicom.dcmread(files[1])
    ds.add_new(0x00091010, "US", 7)  # a vendor private element that will be damaged: not needed, dropped
    ds.save_as(files[1])
    raw = files[1].read_bytes()
    at = raw.index(b"\x09\x00\x10\x10US")
    files[1].write_bytes(raw[:at + 6] + b"\x03\x00" + raw[at + 8:at + 10] + b"\x00" + raw[at + 10:])
    assert load_volume(tmp_path / "s").shape == (6, 5, 4)


# ----------------------------------------------------------------------------------------------- transforms

@pytest.mark.parametrize("parameters, message", [
    ("1 0 0 0 1 0 0 0 1 nan 0 0", "NaN or infinite parameters"),
    ("0 0 0 0 0 0 0 0 0 1 2 3", r"singular \(determinant 0\)"),
])
def test_transform_with_nan_or_singular_matrix_is_refused(tmp_path, parameters, message):
    path = tmp_path / "t.tfm"
    path.write_text(f"#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
                    f"Parameters: {parameters}\nFixedParameters: 0 0 0\n")
    with pytest.raises(InputFileError, match="t.tfm: the transform .*" + message):
        read_tfm(path)


def test_versor_longer_than_one_is_normalised_like_itk(tmp_path):
    path = tmp_path / "v.tfm"
    path.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                    "Transform: VersorRigid3DTransform_double_3_3\nParameters: 0 0 2 0 0 0\n"
                    "FixedParameters: 0 0 0\n")
    rotation = read_tfm(path)[:3, :3]
    np.testing.assert_allclose(rotation, np.diag([-1.0, -1.0, 1.0]), atol=1e-12)  # half turn about z


# ----------------------------------------------------------------------------------------------- DRR cache
# Written against whatever files ``build_database`` puts in the cache folder for a key (``db-<key>.*``: the
# largest is the DRR data, any other a sidecar), so the tests hold whatever the cache format.



def _cache_files(folder: Path, key: str) -> list[Path]:
    """The cache files of one database, largest (the DRR data) first."""
    return sorted(folder.glob(f"db-{key}*"), key=lambda f: f.stat().st_size, reverse=True)


@pytest.fixture(scope="module")
def reference_db(tiny_db_inputs, tmp_path_factory):
    """A database rendered into a fresh cache, its cache files' bytes, and those of another database with
    the same grid size (tx = 5 mm: another key, other DRRs) renamed to this key: a foreign cache."""
    folder = tmp_path_factory.mktemp("cache-ref")
    db = build_database(*tiny_db_inputs, 0.0, folder)
    other = build_database(*tiny_db_inputs, 5.0, folder)
    assert other.key != db.key and not np.array_equal(other.drrs, db.drrs)
    files = {f.name: f.read_bytes() for f in _cache_files(folder, db.key)}
    foreign = {f.name.replace(other.key, db.key): f.read_bytes() for f in _cache_files(folder, other.key)}
    assert files and set(foreign) == set(files)
    return db, files, foreign


def _restore(folder: Path, files: dict) -> list[Path]:
    for name, raw in files.items():
        (folder / name).write_bytes(raw)
    return sorted((folder / n for n in files), key=lambda f: len(files[f.name]), reverse=True)


def _nan_tail(path: Path) -> None:
    """Overwrite the last 64 bytes (DRR values in an uncompressed store) with float32 NaN."""
    raw = path.read_bytes()
    path.write_bytes(raw[:-64] + np.full(16, np.nan, "<f4").tobytes())


CORRUPTIONS = {  # (data file, sidecars) -> None
    "data_garbage": lambda data, side: data.write_bytes(np.random.default_rng(1).bytes(700)),
    "data_empty": lambda data, side: data.write_bytes(b""),
    "data_truncated_half": lambda data, side: data.write_bytes(data.read_bytes()[: data.stat().st_size // 2]),
    "data_truncated_tail": lambda data, side: data.write_bytes(data.read_bytes()[:-40]),
    "data_missing": lambda data, side: data.unlink(),
    "data_text": lambda data, side: data.write_text("not a cache"),
    "sidecars_garbage": lambda data, side: [f.write_bytes(b"\x00{garbage") for f in side],
    "sidecars_missing": lambda data, side: [f.unlink() for f in side],
}


@pytest.mark.parametrize("corruption", [*CORRUPTIONS, "foreign_cache"])
def test_corrupt_or_foreign_cache_is_rebuilt(tiny_db_inputs, reference_db, tmp_path, corruption):
    db, files, foreign = reference_db
    data, *sidecars = _restore(tmp_path, foreign if corruption == "foreign_cache" else files)
    if corruption.startswith("sidecars") and not sidecars:
        pytest.skip("this cache format has no sidecar file")
    if corruption in CORRUPTIONS:
        CORRUPTIONS[corruption](data, sidecars)
    rebuilt = build_database(*tiny_db_inputs, 0.0, tmp_path)
    assert not rebuilt.from_cache
    np.testing.assert_array_equal(rebuilt.drrs, db.drrs)
    again = build_database(*tiny_db_inputs, 0.0, tmp_path)  # the rebuilt cache is valid again
    assert again.from_cache
    np.testing.assert_array_equal(again.drrs, db.drrs)


def test_intact_cache_is_used(tiny_db_inputs, reference_db, tmp_path):
    db, files, _ = reference_db
    _restore(tmp_path, files)
    cached = build_database(*tiny_db_inputs, 0.0, tmp_path)
    assert cached.from_cache
    np.testing.assert_array_equal(cached.drrs, db.drrs)


def test_cache_with_nan_drrs_is_not_trusted(tiny_db_inputs, reference_db, tmp_path):
    """Same key and shape, DRR values damaged in place: needs a checksum (or a finite check) on load."""
    db, files, _ = reference_db
    data, *_ = _restore(tmp_path, files)
    _nan_tail(data)
    rebuilt = build_database(*tiny_db_inputs, 0.0, tmp_path)
    assert np.all(np.isfinite(rebuilt.drrs))


@pytest.mark.parametrize("blocker", ["directory_where_the_data_goes", "cache_dir_is_a_file"])
def test_unwritable_cache_only_loses_the_cache(tiny_db_inputs, reference_db, tmp_path, blocker):
    db, files, _ = reference_db
    cache_dir = tmp_path / "cache"
    if blocker == "cache_dir_is_a_file":
        cache_dir.write_text("a file where the cache folder should be")
    else:
        cache_dir.mkdir()
        (cache_dir / max(files, key=lambda n: len(files[n]))).mkdir()
    rebuilt = build_database(*tiny_db_inputs, 0.0, cache_dir)
    np.testing.assert_array_equal(rebuilt.drrs, db.drrs)
    assert len(rebuilt.notes) == 1 and "could not write the DRR database cache" in rebuilt.notes[0]
