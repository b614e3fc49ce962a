"""The C-arm pinhole model: round trips, decomposition, nominal pose, intrinsics scaling, validation."""

import numpy as np
import pytest

from carmreg.logic.errors import GeometryError
from carmreg.logic.geometry.camera import (
    CarmGeometry,
    CarmIntrinsics,
    CarmPose,
    backproject,
    decompose_projection,
    pixel_to_detector_lps,
    project,
)

ISO_LPS_MM = (12.0, -30.0, 250.0)


def make_geometry(size=(400, 300), spacing=(0.5, 0.6), principal=None, sdd=1020.0, sod=600.0):
    intr = CarmIntrinsics(sdd, spacing, size, principal)
    return CarmGeometry(intr, ISO_LPS_MM, sod)


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-50, 50, (n, 3)), rng.uniform(-15, 15, (n, 3))])


def random_points(n, seed=1):
    rng = np.random.default_rng(seed)
    return np.asarray(ISO_LPS_MM) + rng.uniform(-80, 80, (n, 3))


@pytest.mark.parametrize("principal", [None, (150.3, 170.8)])
def test_project_then_backproject_passes_through_point(principal):
    geometry = make_geometry(principal=principal)
    points = random_points(50)
    for pose_values in random_poses(5):
        pose = CarmPose.from_array(pose_values)
        uv = project(geometry.projection_matrix(pose), points)
        source, directions = backproject(geometry, pose, uv)
        to_point = points - source
        along = np.einsum("ij,ij->i", to_point, directions)
        miss_mm = np.linalg.norm(to_point - along[:, None] * directions, axis=1)
        assert np.all(along > 0)
        assert miss_mm.max() < 1e-6
        # the ray reaches the detector plane at the pixel it was cast through
        on_detector = pixel_to_detector_lps(geometry, pose, uv)
        assert np.allclose(project(geometry.projection_matrix(pose), on_detector), uv, atol=1e-6)


def test_projection_decomposes_into_k_r_t():
    geometry = make_geometry(principal=(180.0, 140.0))
    for pose_values in random_poses(4, seed=3):
        P = geometry.projection_matrix(pose_values)
        K, R, t = decompose_projection(P * 3.7)  # P is defined up to scale
        R_true, t_true = geometry.extrinsics(pose_values)
        assert np.allclose(K, geometry.intrinsics.K, atol=1e-8)
        assert np.allclose(R, R_true, atol=1e-10)
        assert np.allclose(t, t_true, atol=1e-8)


def test_rotations_are_proper():
    geometry = make_geometry()
    R, _ = geometry.extrinsics(random_poses(20, seed=4))
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_nominal_pose_source_anterior_at_sod():
    geometry = make_geometry(sod=600.0)
    source = geometry.source_lps_mm(CarmPose())
    assert np.allclose(source, np.asarray(ISO_LPS_MM) + [0.0, -600.0, 0.0])  # anterior = -y in LPS


def test_nominal_pose_principal_point_projects_isocentre():
    geometry = make_geometry(principal=(210.5, 120.25))
    uv = project(geometry.projection_matrix(CarmPose()), np.array([ISO_LPS_MM]))[0]
    assert np.allclose(uv, (210.5, 120.25), atol=1e-9)


def test_rotation_about_isocentre_keeps_it_on_the_principal_point():
    geometry = make_geometry()
    for rotation in ([10, 0, 0], [0, -12, 0], [0, 0, 25], [5, 7, -9]):
        pose = CarmPose(0, 0, 0, *rotation)
        uv = project(geometry.projection_matrix(pose), np.array([ISO_LPS_MM]))[0]
        assert np.allclose(uv, geometry.intrinsics.principal_point_px, atol=1e-9)


def test_image_axes_point_left_and_inferior():
    geometry = make_geometry()
    P = geometry.projection_matrix(CarmPose())
    iso = np.asarray(ISO_LPS_MM)
    uv_iso, uv_left, uv_sup = project(P, np.array([iso, iso + [10, 0, 0], iso + [0, 0, 10]]))
    assert uv_left[0] > uv_iso[0] + 5 and abs(uv_left[1] - uv_iso[1]) < 1e-9
    assert uv_sup[1] < uv_iso[1] - 5 and abs(uv_sup[0] - uv_iso[0]) < 1e-9


def test_tx_moves_source_toward_patient_and_magnifies():
    geometry = make_geometry(sdd=1020.0, sod=600.0)
    assert geometry.magnification(CarmPose()) == pytest.approx(1020.0 / 600.0)
    assert geometry.magnification(CarmPose(tx_mm=50.0)) == pytest.approx(1020.0 / 550.0)
    P0, P1 = geometry.projection_matrix(CarmPose()), geometry.projection_matrix(CarmPose(tx_mm=50.0))
    iso = np.asarray(ISO_LPS_MM)
    span0 = np.diff(project(P0, np.array([iso, iso + [20, 0, 0]])), axis=0)
    span1 = np.diff(project(P1, np.array([iso, iso + [20, 0, 0]])), axis=0)
    assert span1[0, 0] / span0[0, 0] == pytest.approx(600.0 / 550.0)


def test_ty_tz_translate_the_carm():
    geometry = make_geometry()
    shift = geometry.source_lps_mm(CarmPose(ty_mm=7.0, tz_mm=-4.0)) - geometry.source_lps_mm(CarmPose())
    assert np.allclose(shift, [7.0, 0.0, -4.0])


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_binned_intrinsics_keep_points_on_the_same_detector_spot(factor):
    geometry = make_geometry(size=(480, 360), principal=(250.0, 170.0))
    binned = geometry.with_intrinsics(geometry.intrinsics.binned(factor))
    pose = CarmPose(3, -5, 8, 2, -3, 4)
    points = random_points(20, seed=5)
    uv = project(geometry.projection_matrix(pose), points)
    uv_binned = project(binned.projection_matrix(pose), points)
    assert np.allclose(uv, factor * uv_binned + (factor - 1) / 2.0, atol=1e-9)
    assert np.allclose(pixel_to_detector_lps(geometry, pose, uv), pixel_to_detector_lps(binned, pose, uv_binned),
                       atol=1e-9)


@pytest.mark.parametrize("size", [(64, 64), (100, 75), (1024, 1024)])
def test_scaled_intrinsics_keep_points_on_the_same_detector_spot(size):
    geometry = make_geometry(size=(400, 300), principal=(190.0, 160.0))
    scaled = geometry.with_intrinsics(geometry.intrinsics.scaled_to(size))
    pose = CarmPose(-4, 6, 2, -1, 3, 2)
    points = random_points(20, seed=6)
    uv = project(geometry.projection_matrix(pose), points)
    uv_scaled = project(scaled.projection_matrix(pose), points)
    assert np.allclose(pixel_to_detector_lps(geometry, pose, uv), pixel_to_detector_lps(scaled, pose, uv_scaled),
                       atol=1e-9)
    # the detector keeps its physical outline
    assert np.allclose(geometry.detector_corners_lps_mm(pose), scaled.detector_corners_lps_mm(pose), atol=1e-9)


def test_batch_of_poses_equals_loop():
    geometry = make_geometry(principal=(199.0, 151.0))
    poses = random_poses(7, seed=7)
    P_batch = geometry.projection_matrix(poses)
    R_batch, t_batch = geometry.extrinsics(poses)
    points = random_points(10)
    uv_batch = project(P_batch, points)
    for i, values in enumerate(poses):
        pose = CarmPose.from_array(values)
        assert np.allclose(P_batch[i], geometry.projection_matrix(pose), atol=1e-12)
        R, t = geometry.extrinsics(pose)
        assert np.allclose(R_batch[i], R) and np.allclose(t_batch[i], t)
        assert np.allclose(geometry.source_lps_mm(poses)[i], geometry.source_lps_mm(pose))
        assert np.allclose(geometry.magnification(poses)[i], geometry.magnification(pose))
        assert np.allclose(uv_batch[i], project(geometry.projection_matrix(pose), points), atol=1e-9)


def test_pose_array_round_trip():
    pose = CarmPose(1, 2, 3, 4, 5, 6)
    assert CarmPose.from_array(pose.as_array()) == pose
    assert list(pose.as_dict()) == ["tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg"]


@pytest.mark.parametrize("kwargs", [
    dict(sdd_mm=0.0), dict(sdd_mm=-1000.0), dict(sdd_mm=float("nan")),
    dict(pixel_spacing_mm=(0.0, 0.2)), dict(pixel_spacing_mm=(0.2, float("nan"))),
    dict(size_px=(0, 512)), dict(size_px=(512, 1)),
    dict(principal_point_px=(600.0, 256.0)), dict(principal_point_px=(256.0, -3.0)),
    dict(principal_point_px=(float("nan"), 256.0)),
])
def test_impossible_intrinsics_raise_geometry_error(kwargs):
    values = dict(sdd_mm=1020.0, pixel_spacing_mm=(0.2, 0.2), size_px=(512, 512), principal_point_px=None)
    values.update(kwargs)
    with pytest.raises(GeometryError):
        CarmIntrinsics(**values)


@pytest.mark.parametrize("sod", [0.0, -10.0, 1020.0, 1500.0, float("nan")])
def test_impossible_sod_raises_geometry_error(sod):
    with pytest.raises(GeometryError):
        CarmGeometry(CarmIntrinsics(1020.0, (0.2, 0.2), (512, 512)), ISO_LPS_MM, sod)


def test_geometry_error_messages_say_what_to_do():
    with pytest.raises(GeometryError, match="sdd"):
        CarmIntrinsics(-5.0, (0.2, 0.2), (512, 512))
    with pytest.raises(GeometryError, match="principal"):
        CarmIntrinsics(1000.0, (0.2, 0.2), (512, 512), (900.0, 10.0))
