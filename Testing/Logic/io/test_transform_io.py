"""ITK .tfm transform files and RAS <-> LPS conversion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose
from carmreg.logic.io.transforms import lps_to_ras_matrix, ras_to_lps_matrix, read_tfm, write_tfm


def rigid(angles_deg=(10.0, -25.0, 40.0), translation=(12.5, -7.0, 300.0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()
    m[:3, 3] = translation
    return m


def test_round_trip_with_and_without_centre(tmp_path):
    m = rigid()
    for center in (None, (5.0, -60.0, 812.0)):
        path = write_tfm(tmp_path / "t.tfm", m, center=center, comment="lps_to_camera\nCT LPS -> C-arm")
        np.testing.assert_allclose(read_tfm(path), m, atol=1e-12)
    text = path.read_text().splitlines()
    assert text[0] == "#Insight Transform File V1.0" and text[1] == "# lps_to_camera"
    assert "Transform: AffineTransform_double_3_3" in text
    fixed = [float(x) for x in text[-1].split(":")[1].split()]
    assert text[-1].startswith("FixedParameters:") and fixed == [5.0, -60.0, 812.0]


def test_parameters_are_row_major_matrix_then_translation(tmp_path):
    m = np.array([[1.0, 2, 3, 10], [4, 5, 6, 20], [7, 8, 9.5, 30], [0, 0, 0, 1]])
    line = [ln for ln in write_tfm(tmp_path / "a.tfm", m).read_text().splitlines()
            if ln.startswith("Parameters:")][0]
    assert [float(x) for x in line.split(":")[1].split()] == [1, 2, 3, 4, 5, 6, 7, 8, 9.5, 10, 20, 30]


def test_centre_semantics_match_itk(tmp_path):
    """y = A (x - c) + c + t: with A = 90 deg about z, c = (10, 0, 0), t = 0, x = c stays fixed."""
    (tmp_path / "c.tfm").write_text("#Insight Transform File V1.0\n#Transform 0\n"
                                    "Transform: AffineTransform_double_3_3\n"
                                    "Parameters: 0 -1 0 1 0 0 0 0 1 0 0 0\nFixedParameters: 10 0 0\n")
    m = read_tfm(tmp_path / "c.tfm")
    np.testing.assert_allclose(m @ [10, 0, 0, 1], [10, 0, 0, 1])
    np.testing.assert_allclose(m @ [11, 0, 0, 1], [10, 1, 0, 1])


def test_ras_lps_conversion():
    m = rigid()
    f = np.diag([-1.0, -1.0, 1.0])
    p_ras = np.array([3.0, -4.0, 5.0])
    q_ras = m[:3, :3] @ p_ras + m[:3, 3]
    lps = ras_to_lps_matrix(m)
    np.testing.assert_allclose(lps[:3, :3] @ (f @ p_ras) + lps[:3, 3], f @ q_ras)
    np.testing.assert_allclose(lps_to_ras_matrix(lps), m)


def test_euler_versor_translation_and_composite(tmp_path):
    ax, ay, az = 0.1, -0.2, 0.3
    expected_zxy = (Rotation.from_euler("z", az) * Rotation.from_euler("x", ax)
                    * Rotation.from_euler("y", ay)).as_matrix()
    expected_zyx = (Rotation.from_euler("z", az) * Rotation.from_euler("y", ay)
                    * Rotation.from_euler("x", ax)).as_matrix()
    for fixed, expected in [("1 2 3", expected_zxy), ("1 2 3 0", expected_zxy), ("1 2 3 1", expected_zyx)]:
        (tmp_path / "e.tfm").write_text("#Insight Transform File V1.0\n#Transform 0\n"
                                        "Transform: Euler3DTransform_double_3_3\n"
                                        f"Parameters: {ax} {ay} {az} 5 6 7\nFixedParameters: {fixed}\n")
        m = read_tfm(tmp_path / "e.tfm")
        np.testing.assert_allclose(m[:3, :3], expected, atol=1e-12)
        np.testing.assert_allclose(m @ [1, 2, 3, 1], [6, 8, 10, 1], atol=1e-12)  # centre -> centre + t
    q = Rotation.from_rotvec([0.2, -0.1, 0.4])
    x, y, z, _ = q.as_quat()
    (tmp_path / "v.tfm").write_text("#Insight Transform File V1.0\n#Transform 0\n"
                                    "Transform: VersorRigid3DTransform_double_3_3\n"
                                    f"Parameters: {x} {y} {z} 1 2 3\nFixedParameters: 0 0 0\n"
                                    "#Transform 1\nTransform: TranslationTransform_double_3_3\n"
                                    "Parameters: 10 0 0\nFixedParameters:\n")
    m = read_tfm(tmp_path / "v.tfm")  # composite file: translation applied first, then the versor
    np.testing.assert_allclose(m[:3, :3], q.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], q.as_matrix() @ [10, 0, 0] + [1, 2, 3], atol=1e-12)


def test_lps_to_camera_of_a_pose_round_trips(tmp_path):
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (0.3, 0.3), (512, 512)), (10.0, 20.0, -150.0), 600.0)
    rotation, t = geometry.extrinsics(CarmPose(5.0, -3.0, 12.0, 2.0, -4.0, 7.0))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, t
    back = read_tfm(write_tfm(tmp_path / "pose.tfm", m, center=geometry.isocenter_lps_mm))
    np.testing.assert_allclose(back, m, atol=1e-12)
    np.testing.assert_allclose(back @ [*geometry.source_lps_mm(CarmPose(5.0, -3.0, 12.0, 2.0, -4.0, 7.0)), 1],
                               [0, 0, 0, 1], atol=1e-9)  # the source is the camera origin


def test_bad_files(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_tfm(tmp_path / "none.tfm")
    (tmp_path / "a.txt").write_text("hello\n")
    with pytest.raises(InputFileError, match="not an ITK transform file"):
        read_tfm(tmp_path / "a.txt")
    (tmp_path / "b.h5").write_bytes(b"\x89HDF")
    with pytest.raises(InputFileError, match="binary transform"):
        read_tfm(tmp_path / "b.h5")
    header = "#Insight Transform File V1.0\n#Transform 0\n"
    cases = {"bspline": ("Transform: BSplineTransform_double_3_3\nParameters: 1 2 3\n", "not supported"),
             "2d": ("Transform: AffineTransform_double_2_2\nParameters: 1 0 0 1 0 0\n", "not 3D"),
             "nan": ("Transform: AffineTransform_double_3_3\nParameters: a b\n", "not numbers"),
             "short": ("Transform: AffineTransform_double_3_3\nParameters: 1 0 0\n", "3 parameters"),
             "empty": ("", "holds no transform")}
    for name, (body, message) in cases.items():
        (tmp_path / f"{name}.tfm").write_text(header + body)
        with pytest.raises(InputFileError, match=message):
            read_tfm(tmp_path / f"{name}.tfm")
    (tmp_path / "bin.tfm").write_bytes(b"\xff\xfe\x00" * 10)
    with pytest.raises(InputFileError, match="not a text ITK transform"):
        read_tfm(tmp_path / "bin.tfm")


def test_write_refuses_non_affine(tmp_path):
    bad = np.eye(4)
    bad[3, 0] = 1.0
    with pytest.raises(ValueError, match="4x4 affine"):
        write_tfm(tmp_path / "x.tfm", bad)
    with pytest.raises(ValueError, match="4x4 affine"):
        write_tfm(tmp_path / "x.tfm", np.full((4, 4), np.nan))
