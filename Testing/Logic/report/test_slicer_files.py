"""Every file CarmReg writes for 3D Slicer opens with Slicer's own readers (``slicer-core``: Kitware's MRML
libraries for Python, the same C++ storage nodes and scene loader as the Slicer application, no GUI).

Positions are checked in RAS, as Slicer shows them: RAS = diag(-1, -1, 1) LPS. Small synthetic data made by
the test (an oblique CT, a 64 x 48 detector); skipped when ``slicer-core`` is not installed.
"""

from __future__ import annotations

import numpy as np
import pytest

slicer = pytest.importorskip("slicer", reason="slicer-core (Kitware's MRML libraries) is not installed")
if not hasattr(slicer, "vtkMRMLScene"):
    pytest.skip("the installed 'slicer' package is not slicer-core", allow_module_level=True)

from vtkmodules.util.numpy_support import vtk_to_numpy  # noqa: E402 - after the skip

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, pixel_to_detector_lps  # noqa: E402
from carmreg.logic.geometry.camera import project as project_points  # noqa: E402
from carmreg.logic.geometry.volume import Volume  # noqa: E402
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, write_landmarks_2d, write_landmarks_3d  # noqa: E402
from carmreg.logic.io.transforms import write_tfm  # noqa: E402
from carmreg.logic.io.volumes import write_volume_nrrd  # noqa: E402
from carmreg.logic.io.xray import write_xray_dicom  # noqa: E402
from carmreg.logic.registration.pipeline import RegistrationParameters, RegistrationResult  # noqa: E402
from carmreg.logic.report.result_files import write_drr_nrrd  # noqa: E402
from carmreg.logic.report.slicer_scene import lps_to_camera_matrix, write_slicer_scene  # noqa: E402

RAS = np.diag([-1.0, -1.0, 1.0])
F4 = np.diag([-1.0, -1.0, 1.0, 1.0])
POSE = CarmPose.from_array([10.0, 5.0, -20.0, 2.0, 1.0, 3.0])


def _matrix(vtk_matrix) -> np.ndarray:
    return np.array([[vtk_matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def _new_scene():
    """An MRML scene set up as Slicer's application sets it up for loading data (default colour tables,
    selection/interaction singletons, markups and volumes logic)."""
    scene = slicer.vtkMRMLScene()
    app_logic = slicer.vtkMRMLApplicationLogic()
    app_logic.SetMRMLScene(scene)
    logics = [app_logic]
    for cls in (slicer.vtkSlicerColorLogic, slicer.vtkSlicerMarkupsLogic, slicer.vtkSlicerVolumesLogic):
        logic = cls()
        logic.SetMRMLApplicationLogic(app_logic)
        logic.SetMRMLScene(scene)
        logics.append(logic)
    return scene, logics


def _load_volume(path):
    scene, logics = _new_scene()
    node = logics[-1].AddArchetypeVolume(str(path), path.stem, 0)
    return node, (scene, logics)


def _voxels(node) -> np.ndarray:
    """The volume's voxels as [k, j, i] (VTK order), from the loaded image data."""
    image = node.GetImageData()
    nx, ny, nz = image.GetDimensions()
    return vtk_to_numpy(image.GetPointData().GetScalars()).reshape(nz, ny, nx)


def _ijk_to_ras(node) -> np.ndarray:
    import vtk

    m = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(m)
    return _matrix(m)


def _points(node) -> tuple[list[str], np.ndarray]:
    n = node.GetNumberOfControlPoints()
    return ([node.GetNthControlPointLabel(i) for i in range(n)],
            np.array([node.GetNthControlPointPositionWorld(i) for i in range(n)]).reshape(-1, 3))


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A registration result on an oblique CT: levels projected by P, clicks 0.7 px off, a DRR and an X-ray."""
    from scipy.spatial.transform import Rotation

    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("xyz", [20, -15, 30], degrees=True).as_matrix() * [0.7, 0.8, 2.0]
    affine[:3, 3] = [-101.25, 37.5, 812.125]
    hu = np.random.default_rng(7).integers(-1000, 3000, size=(24, 20, 9)).astype(np.int16)
    ct = Volume(hu, affine, "synthetic-oblique")
    centre = ct.center_lps_mm()
    landmarks = Landmarks3D(["T11", "T12", "L1"], centre + np.array([[3.0, 0, 25], [0, 2.0, 0], [-2.0, 0, -25]]))
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (2.0, 2.0), (64, 48)), tuple(centre), 600.0)
    P = geometry.projection_matrix(POSE)
    levels = []
    for label, point in zip(landmarks.labels, landmarks.points_lps_mm, strict=True):
        uv = project_points(P, point[None])[0]
        levels.append({"label": label, "uv_px": uv.tolist(), "fitted": label != "L1", "pde_mm": 0.4,
                       "in_image": True, "clicked_uv_px": (uv + 0.7).tolist() if label != "L1" else None,
                       "name_margin": None})
    drr = np.linspace(0.0, 5.0, 64 * 48, dtype=np.float32).reshape(48, 64)
    xray = np.random.default_rng(1).integers(0, 4000, size=(48, 64)).astype(np.uint16)
    result = RegistrationResult(pose=POSE, projection_matrix=P, geometry=geometry, stages=[], levels=levels,
                                drr_line_integral=drr, xray_line_integral=drr, convergence=[], trajectory=[],
                                similarity_maps={}, database_grid={}, ok=True, warnings=[],
                                parameters=RegistrationParameters())
    out = tmp_path_factory.mktemp("slicer_files")
    paths = write_slicer_scene(out, result, ct, landmarks, xray)
    return {"ct": ct, "landmarks": landmarks, "result": result, "xray": xray, "drr": drr, "paths": paths,
            "out": out}


# ------------------------------------------------------------------------------------------- single files

def test_ct_nrrd_opens_in_slicer_with_its_oblique_geometry_and_values(case, tmp_path):
    path = write_volume_nrrd(tmp_path / "ct.nrrd", case["ct"])
    node, _keep = _load_volume(path)
    assert node is not None
    np.testing.assert_allclose(_ijk_to_ras(node), F4 @ case["ct"].ijk_to_lps, atol=1e-4)
    voxels = _voxels(node)
    assert voxels.shape == (9, 20, 24)
    assert voxels[4, 7, 11] == case["ct"].hu[11, 7, 4] and np.array_equal(voxels.T, case["ct"].hu)


def test_drr_nrrd_opens_in_slicer_on_the_detector_plane(case, tmp_path):
    result = case["result"]
    path = write_drr_nrrd(tmp_path / "drr.nrrd", case["drr"], result.geometry, result.pose)
    node, _keep = _load_volume(path)
    assert node is not None, "Slicer's volume reader refused drr.nrrd"
    voxels = _voxels(node)
    assert voxels.shape == (1, 48, 64)
    np.testing.assert_allclose(voxels[0], case["drr"])
    uv = np.array([[0.0, 0.0], [63.0, 0.0], [17.0, 41.0]])
    ijk = np.c_[uv, np.zeros(3), np.ones(3)]
    ras = (_ijk_to_ras(node) @ ijk.T).T[:, :3]
    np.testing.assert_allclose(ras, pixel_to_detector_lps(result.geometry, result.pose, uv) @ RAS, atol=1e-3)


def test_a_2d_nrrd_embedded_in_3d_is_what_slicer_refuses(case, tmp_path):
    """Why drr.nrrd is a one-slice 3D volume: the earlier 2D layout does not load."""
    import nrrd

    header = {"space": "left-posterior-superior", "space origin": np.zeros(3),
              "space directions": np.array([[2.0, 0, 0], [0, 2.0, 0]]), "kinds": ["domain", "domain"]}
    nrrd.write(str(tmp_path / "drr2d.nrrd"), case["drr"].T.copy(), header)
    node, _keep = _load_volume(tmp_path / "drr2d.nrrd")
    assert node is None or node.GetImageData() is None


def test_markups_open_in_slicer_at_their_ras_positions(case, tmp_path):
    scene, logics = _new_scene()
    lm = case["landmarks"]
    node = scene.GetNodeByID(logics[2].LoadMarkups(str(write_landmarks_3d(tmp_path / "ct.mrk.json", lm))))
    labels, ras = _points(node)
    assert labels == ["T11", "T12", "L1"]
    np.testing.assert_allclose(ras, lm.points_lps_mm @ RAS, atol=1e-6)
    clicks = Landmarks2D(["T12", None], np.array([[10.0, 20.0], [30.5, 40.25]]))
    node2 = scene.GetNodeByID(logics[2].LoadMarkups(str(write_landmarks_2d(tmp_path / "xr.mrk.json", clicks,
                                                                          (0.5, 0.25)))))
    labels2, ras2 = _points(node2)
    assert labels2 == ["T12", ""]
    np.testing.assert_allclose(ras2, np.array([[5.0, 5.0, 0.0], [15.25, 10.0625, 0.0]]) @ RAS, atol=1e-6)


def test_carm_tfm_opens_in_slicer_as_the_camera_to_ras_transform(case, tmp_path):
    result = case["result"]
    lps_to_camera = lps_to_camera_matrix(result)
    path = write_tfm(tmp_path / "carm.tfm", lps_to_camera)
    scene, _logics = _new_scene()
    node = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(path))
    assert storage.ReadData(node) == 1
    import vtk

    m = vtk.vtkMatrix4x4()
    node.GetMatrixTransformToParent(m)
    to_parent = _matrix(m)
    np.testing.assert_allclose(to_parent, F4 @ np.linalg.inv(lps_to_camera) @ F4, atol=1e-9)
    # its translation is the X-ray source, in RAS
    np.testing.assert_allclose(to_parent[:3, 3], result.geometry.source_lps_mm(result.pose) @ RAS, atol=1e-6)


def test_xray_dicom_opens_in_slicer_with_its_pixels(case, tmp_path):
    intrinsics = case["result"].geometry.intrinsics
    path = write_xray_dicom(tmp_path / "xray.dcm", case["xray"], intrinsics, sod_mm=600.0)
    node, _keep = _load_volume(path)
    assert node is not None
    voxels = _voxels(node)
    assert voxels.shape == (1, 48, 64) and np.array_equal(voxels[0], case["xray"])
    spacing = node.GetSpacing()
    assert spacing[0] == pytest.approx(2.0) and spacing[1] == pytest.approx(2.0)


# ------------------------------------------------------------------------------------------------ the scene

@pytest.fixture(scope="module")
def loaded_scene(case):
    scene, logics = _new_scene()
    scene.SetURL(str(case["paths"]["slicer_scene"]))
    assert scene.Import() == 1  # what File > Load Scene does (qSlicerSceneReader)
    return scene, logics


NAMES = {"CT": "vtkMRMLScalarVolumeNode", "X-ray": "vtkMRMLScalarVolumeNode", "DRR": "vtkMRMLScalarVolumeNode",
         "CT centroids": "vtkMRMLMarkupsFiducialNode", "X-ray clicks": "vtkMRMLMarkupsFiducialNode",
         "Projected levels": "vtkMRMLMarkupsFiducialNode", "C-arm": "vtkMRMLLinearTransformNode"}


def test_scene_loads_every_node_with_its_references_and_data(case, loaded_scene):
    scene, _ = loaded_scene
    for name, cls in NAMES.items():
        node = scene.GetFirstNodeByName(name)
        assert node is not None and node.IsA(cls), name
        storage = node.GetStorageNode()
        assert storage is not None and storage.GetFileName().startswith(str(case["out"] / "slicer")), name
        for r in range(node.GetNumberOfNodeReferenceRoles()):
            role = node.GetNthNodeReferenceRole(r)
            for j in range(node.GetNumberOfNodeReferences(role)):
                assert scene.GetNodeByID(node.GetNthNodeReferenceID(role, j)) is not None, (name, role)
    for name in ("CT", "X-ray", "DRR"):
        volume = scene.GetFirstNodeByName(name)
        assert volume.GetImageData() is not None and volume.GetDisplayNode() is not None, name
        assert volume.GetDisplayNode().GetColorNode() is not None, name
    assert np.array_equal(_voxels(scene.GetFirstNodeByName("X-ray"))[0], case["xray"])
    np.testing.assert_allclose(_voxels(scene.GetFirstNodeByName("DRR"))[0], case["drr"])
    assert np.array_equal(_voxels(scene.GetFirstNodeByName("CT")).T, case["ct"].hu)
    assert _points(scene.GetFirstNodeByName("X-ray clicks"))[0] == ["T11", "T12"]


def test_scene_positions_in_ras_are_where_carmreg_says(case, loaded_scene):
    scene, _ = loaded_scene
    result, lm = case["result"], case["landmarks"]
    labels, ct_ras = _points(scene.GetFirstNodeByName("CT centroids"))
    assert labels == lm.labels
    np.testing.assert_allclose(ct_ras, lm.points_lps_mm @ RAS, atol=1e-6)
    labels, projected_ras = _points(scene.GetFirstNodeByName("Projected levels"))
    assert labels == [lv["label"] for lv in result.levels]
    uv = np.array([lv["uv_px"] for lv in result.levels])
    np.testing.assert_allclose(projected_ras, pixel_to_detector_lps(result.geometry, result.pose, uv) @ RAS,
                               atol=1e-6)
    # a projected level is on the X-ray voxel of its pixel ...
    ijk = np.c_[uv, np.zeros(len(uv)), np.ones(len(uv))]
    xray_ras = (_ijk_to_ras(scene.GetFirstNodeByName("X-ray")) @ ijk.T).T[:, :3]
    np.testing.assert_allclose(xray_ras, projected_ras, atol=1e-4)
    # ... and on the ray from the X-ray source (the C-arm transform's origin) through its CT centroid
    import vtk

    m = vtk.vtkMatrix4x4()
    scene.GetFirstNodeByName("C-arm").GetMatrixTransformToParent(m)
    source_ras = _matrix(m)[:3, 3]
    np.testing.assert_allclose(source_ras, result.geometry.source_lps_mm(result.pose) @ RAS, atol=1e-6)
    for ct_point, level_point in zip(ct_ras, projected_ras, strict=True):
        a, b = ct_point - source_ras, level_point - source_ras
        assert np.linalg.norm(np.cross(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b)) < 1e-9
        assert np.linalg.norm(b) > np.linalg.norm(a)  # the detector is beyond the patient
    clicks_ras = _points(scene.GetFirstNodeByName("X-ray clicks"))[1]
    clicked_uv = np.array([lv["clicked_uv_px"] for lv in result.levels if lv["clicked_uv_px"] is not None])
    np.testing.assert_allclose(clicks_ras, pixel_to_detector_lps(result.geometry, result.pose, clicked_uv) @ RAS,
                               atol=1e-6)


def test_a_refused_images_scene_names_its_points_on_the_detector_with_a_question_mark(case, tmp_path):
    """Names withheld (the X-ray refused: ``LevelCheck.withheld_for``): Slicer shows the clicks and the projected
    levels with a "?" after each name; the CT's own centroids keep theirs."""
    import dataclasses

    from carmreg.logic.registration.level_check import LevelCheck

    check = LevelCheck("unnamed", "confident", assigned_labels=["T11", "T12"]).withheld_for("display mirrored")
    refused = dataclasses.replace(case["result"], level_check=check, ok=False)
    paths = write_slicer_scene(tmp_path, refused, case["ct"], case["landmarks"], case["xray"])
    scene, _ = _new_scene()
    scene.SetURL(str(paths["slicer_scene"]))
    assert scene.Import() == 1
    assert _points(scene.GetFirstNodeByName("X-ray clicks"))[0] == ["T11?", "T12?"]
    assert _points(scene.GetFirstNodeByName("Projected levels"))[0] == ["T11?", "T12?", "L1?"]
    assert _points(scene.GetFirstNodeByName("CT centroids"))[0] == ["T11", "T12", "L1"]
