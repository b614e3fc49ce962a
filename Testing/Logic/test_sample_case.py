"""The embedded sample case (Resources/SampleCase): files load, landmarks T1..L1 inside the CT, the X-ray
clicks sit near the ground truth, and the ground truth is consistent with itself and with the images.
Skipped when the case has not been generated (scripts/make_sample_case.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.geometry.vertebrae import CARMREG_VERTEBRAE, centroids_from_labels, level_ordinals
from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d
from carmreg.logic.io.volumes import load_volume
from carmreg.logic.io.xray import load_xray
from carmreg.logic.simulation.detector import IntensifierDistortion

LEVELS = [f"T{i}" for i in range(1, 13)] + ["L1"]


@pytest.fixture(scope="module")
def case(sample_case_dir):
    names = ("ct.nrrd", "vertebrae.nrrd", "ct_centroids.mrk.json", "xray.dcm", "xray.png",
             "xray_centroids.mrk.json", "ground_truth.json", "README.md")
    missing = [n for n in names if not (sample_case_dir / n).is_file()]
    if missing:
        pytest.skip(f"sample case incomplete: {missing}")
    return sample_case_dir


@pytest.fixture(scope="module")
def truth(case):
    return json.loads((case / "ground_truth.json").read_text())


def test_size_small_enough_to_commit(case):
    total = sum(p.stat().st_size for p in case.iterdir() if p.is_file())
    assert total < 8.5e6


def test_ct_and_labels_share_one_lps_grid(case):
    ct = load_volume(case / "ct.nrrd")
    labels = load_volume(case / "vertebrae.nrrd")
    assert ct.hu.dtype == np.int16 and ct.hu.min() >= -1024 and ct.hu.max() <= 3071
    assert labels.shape == ct.shape
    np.testing.assert_allclose(labels.ijk_to_lps, ct.ijk_to_lps)
    assert np.all(ct.spacing_mm[:2] <= 1.01) and ct.spacing_mm[2] == pytest.approx(2.5)
    assert set(np.unique(labels.hu).tolist()) - {0} <= set(CARMREG_VERTEBRAE)
    # vertebra voxels are bone-like on average; the body is surrounded by air at exactly -1000 HU
    assert np.median(ct.hu[labels.hu > 0]) > 150
    assert np.mean(ct.hu == -1000) > 0.1


def test_ct_centroids_are_t1_to_l1_inside_the_ct_and_match_the_labels(case):
    ct = load_volume(case / "ct.nrrd")
    labels = load_volume(case / "vertebrae.nrrd")
    landmarks = read_landmarks_3d(case / "ct_centroids.mrk.json")
    assert landmarks.labels == LEVELS
    assert np.all(ct.contains_lps(landmarks.points_lps_mm, margin_vox=0.0))
    recomputed = centroids_from_labels(labels.hu, labels.ijk_to_lps, CARMREG_VERTEBRAE)
    assert recomputed.labels == LEVELS
    np.testing.assert_allclose(landmarks.points_lps_mm, recomputed.points_lps_mm, atol=1e-4)
    steps = np.linalg.norm(np.diff(landmarks.points_lps_mm, axis=0), axis=1)
    assert np.all((steps > 14.0) & (steps < 40.0))  # adjacent vertebral centroids, head to foot
    assert np.all(np.diff(landmarks.points_lps_mm[:, 2]) < 0)


def test_xray_files_carry_the_ground_truth_geometry(case, truth):
    xray = load_xray(case / "xray.dcm")
    intr = truth["intrinsics"]
    assert xray.intrinsics.sdd_mm == pytest.approx(intr["sdd_mm"])
    np.testing.assert_allclose(xray.intrinsics.pixel_spacing_mm, intr["pixel_spacing_mm"])
    assert list(xray.intrinsics.size_px) == intr["size_px"]
    assert xray.sod_mm == pytest.approx(truth["sod_mm"])
    assert xray.bone_dark
    png = load_xray(case / "xray.png", sdd_mm=1000.0, pixel_spacing_mm=(0.25, 0.25))
    np.testing.assert_array_equal(png.pixels, xray.pixels)
    rows, cols = xray.pixels.shape
    assert xray.pixels[rows // 2, 2] == 0 and xray.pixels[rows // 2, cols // 2] > 0  # circular field


def test_ground_truth_projection_is_consistent(case, truth):
    intr = truth["intrinsics"]
    geometry = CarmGeometry(CarmIntrinsics(intr["sdd_mm"], tuple(intr["pixel_spacing_mm"]), tuple(intr["size_px"]),
                                           tuple(intr["principal_point_px"])),
                            tuple(truth["isocenter_lps_mm"]), truth["sod_mm"])
    P = np.array(truth["projection_matrix"])
    np.testing.assert_allclose(geometry.projection_matrix(CarmPose(**truth["pose"])), P, atol=1e-9)
    ct = read_landmarks_3d(case / "ct_centroids.mrk.json").as_dict()
    distortion = IntensifierDistortion.from_dict(truth["distortion"])
    assert 1.2 < truth["magnification_isocenter"] < 2.2
    for name, level in truth["levels"].items():
        np.testing.assert_allclose(level["centroid_lps_mm"], ct[name], atol=1e-6)
        np.testing.assert_allclose(level["uv_projected_px"], project(P, ct[name][None])[0], atol=1e-6)
        moved = np.array(level["motion_matrix_lps"]) @ np.append(ct[name], 1.0)
        np.testing.assert_allclose(level["uv_true_px"], distortion.distort(project(P, moved[None, :3])[0]),
                                   atol=1e-6)
    visible = [n for n, level in truth["levels"].items() if level["visible"]]
    assert 4 <= len(visible) <= 7


def test_xray_clicks_are_three_adjacent_visible_levels_near_the_truth(case, truth):
    clicks = read_landmarks_2d(case / "xray_centroids.mrk.json")
    assert len(clicks.labels) == 3
    ordinal = level_ordinals(clicks.labels)
    assert np.diff([ordinal[n] for n in clicks.labels]).tolist() == [1, 1]
    spacing = np.array(truth["intrinsics"]["pixel_spacing_mm"])
    for name, uv in clicks.as_dict().items():
        level = truth["levels"][name]
        assert level["visible"]
        error_mm = np.linalg.norm((uv - np.array(level["uv_true_px"])) * spacing)
        assert error_mm < 4.0                   # surgeon-style click noise, about 1.3 mm rms
        np.testing.assert_allclose(uv, truth["clicks_uv_px"][name])
