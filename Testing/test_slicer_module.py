"""The 3D Slicer module (``CarmReg.py`` at the repository top), tested without a Slicer binary:

- the file imports as a top-level module outside Slicer, without Slicer, Qt, VTK or numpy, and its
  ``import_carmreg`` loads ``carmreg`` from the folders beside it (a fresh interpreter without site-packages);
- the layout follows Slicer's discovery rules and template (one ``*.py`` at the top of the module folder, the
  Module / Widget / Logic / Test classes on Slicer's bases, the icon, the extension's CMakeLists.txt);
- its MRML side runs against ``slicer-core``'s real nodes: nodes -> CarmReg objects, a result -> nodes, and a
  whole registration of the sample case from MRML nodes.
What is *not* tested here: the widget (needs Slicer's application, PythonQt, ctk) and pip_ensure itself.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
MODULE_FILE = ROOT / "CarmReg.py"
SLICER_BASES = {"CarmReg": "ScriptedLoadableModule", "CarmRegWidget": "ScriptedLoadableModuleWidget",
                "CarmRegLogic": "ScriptedLoadableModuleLogic", "CarmRegTest": "ScriptedLoadableModuleTest"}


def _module():
    """CarmReg.py imported as Slicer imports it: a top-level module named after the file."""
    if "CarmReg" in sys.modules:
        return sys.modules["CarmReg"]
    spec = importlib.util.spec_from_file_location("CarmReg", MODULE_FILE)
    module = importlib.util.module_from_spec(spec)
    sys.modules["CarmReg"] = module
    spec.loader.exec_module(module)
    return module


# ------------------------------------------------------------------------------------------------ import

IMPORT_CHECK = r"""
import importlib.resources, json, sys
sys.path.insert(0, sys.argv[1])
import CarmReg
heavy = sorted(m for m in ("slicer", "qt", "ctk", "vtk", "vtkmodules", "PySide6", "qtpy", "numpy") if m in sys.modules)
try:
    CarmReg.CarmRegLogic()
    refused = ""
except RuntimeError as exc:
    refused = str(exc)
carmreg = CarmReg.import_carmreg()
import carmreg.about, carmreg.logic
print(json.dumps({"in_slicer": CarmReg.IN_SLICER, "heavy": heavy, "refused": refused,
                  "carmreg": carmreg.__file__, "logic": carmreg.logic.__file__,
                  "resources": str(importlib.resources.files("carmreg.resources")),
                  "title": carmreg.about.TITLE, "classes": [hasattr(CarmReg, n) for n in CLASSES]}))
""".replace("CLASSES", repr(list(SLICER_BASES)))


def test_module_file_imports_as_a_top_level_module_outside_slicer_and_finds_carmreg_beside_it(tmp_path):
    # -I -S: no site-packages (no installed carmreg, numpy, vtk or slicer-core), not the checkout as cwd
    out = subprocess.run([sys.executable, "-I", "-S", "-c", IMPORT_CHECK, str(ROOT)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert doc["in_slicer"] is False and doc["heavy"] == []
    assert "runs inside 3D Slicer only" in doc["refused"]
    assert Path(doc["carmreg"]) == ROOT / "CarmRegModule" / "__init__.py"
    assert Path(doc["logic"]) == ROOT / "Logic" / "__init__.py"
    assert Path(doc["resources"]) == ROOT / "Resources"
    assert doc["title"] == "CarmReg" and all(doc["classes"])


def test_package_dirs_match_pyproject():
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert _module().PACKAGE_DIRS == project["tool"]["setuptools"]["package-dir"]


# ------------------------------------------------------------------------------------------------ layout

def test_layout_follows_slicers_discovery_rules_and_template():
    # Slicer takes every *.py at the top of a module path for a module: only CarmReg.py may be there
    assert sorted(p.name for p in ROOT.glob("*.py")) == ["CarmReg.py"]
    tree = ast.parse(MODULE_FILE.read_text())
    classes = {node.name: [ast.unparse(b) for b in node.bases] for node in tree.body if isinstance(node, ast.ClassDef)}
    for name, base in SLICER_BASES.items():
        assert classes.get(name) == [base], name
    # no relative import (Slicer imports the file as a top-level module); Slicer-only imports inside functions
    top_imports = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    assert all(not (isinstance(n, ast.ImportFrom) and n.level) for n in ast.walk(tree))
    assert {a.name for n in top_imports for a in getattr(n, "names", [])} <= {"importlib.util", "os", "sys"}
    assert (ROOT / "Resources" / "Icons" / "CarmReg.png").is_file()  # ScriptedLoadableModule's icon lookup
    # the widget uses Slicer's qt / ctk / slicer widgets, never the desktop application's binding
    source = MODULE_FILE.read_text()
    assert "qMRMLNodeComboBox" in source and "ctkCollapsibleButton" in source
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert {"qt", "ctk", "slicer", "vtk"} <= imported and not imported & {"qtpy", "PySide6", "PyQt5", "PyQt6"}


def test_extension_cmakelists_builds_the_scripted_module_with_every_listed_file():
    text = (ROOT / "CMakeLists.txt").read_text()
    for needle in ("find_package(Slicer REQUIRED)", "include(${Slicer_USE_FILE})", "slicerMacroBuildScriptedModule",
                   "slicer_add_python_unittest", "Resources/Icons/CarmReg.png", "include(${Slicer_EXTENSION_CPACK})"):
        assert needle in text, needle
    block = text[text.index("set(MODULE_PYTHON_SCRIPTS"):text.index("slicerMacroBuildScriptedModule(")]
    words = block.replace("${MODULE_NAME}", "CarmReg").replace("(", " ").replace(")", " ").split()
    listed = [w for w in words if "/" in w or w.endswith(".py")]
    assert "CarmReg.py" in listed and "Resources/Icons/CarmReg.png" in listed
    for name in listed:  # every file named exists; every glob matches something
        assert list(ROOT.glob(name)) if "*" in name else (ROOT / name).is_file(), name


def test_requirements_for_slicer_are_pyprojects_without_vtk_or_qt():
    tomllib = pytest.importorskip("tomllib")
    module = _module()
    requirements = module.read_requirements(ROOT / "Resources" / "requirements.txt")
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert sorted(requirements) == sorted(d for d in deps if module.requirement_name(d).lower() != "vtk")
    assert not [r for r in requirements if module.requirement_name(r).lower() in module.FORBIDDEN_IN_SLICER]
    assert module.requirement_name("pylibjpeg-libjpeg>=2.1") == "pylibjpeg-libjpeg"
    assert module.missing_requirements(["numpy>=1", "no-such-distribution-carmreg>=1"]) == [
        "no-such-distribution-carmreg>=1"]


# ------------------------------------------------------------------------------------------- MRML side

@pytest.fixture(scope="module")
def mrml():
    """slicer-core's MRML scene with the logics Slicer's application sets up (skips when not installed)."""
    slicer = pytest.importorskip("slicer", reason="slicer-core is not installed")
    if not hasattr(slicer, "vtkMRMLScene"):
        pytest.skip("the installed 'slicer' package is not slicer-core")
    scene = slicer.vtkMRMLScene()
    app_logic = slicer.vtkMRMLApplicationLogic()
    app_logic.SetMRMLScene(scene)
    logics = {}
    for key, cls in (("colors", slicer.vtkSlicerColorLogic), ("markups", slicer.vtkSlicerMarkupsLogic),
                     ("volumes", slicer.vtkSlicerVolumesLogic)):
        logics[key] = cls()
        logics[key].SetMRMLApplicationLogic(app_logic)
        logics[key].SetMRMLScene(scene)
    return scene, logics, app_logic


@pytest.fixture(scope="module")
def sample_nodes(mrml, sample_case_dir):
    """The sample case loaded by Slicer's readers; the X-ray clicks placed on the X-ray volume."""
    from carmreg.logic.io.landmarks import read_landmarks_2d

    scene, logics, _ = mrml
    module = _module()
    ct = logics["volumes"].AddArchetypeVolume(str(sample_case_dir / "ct.nrrd"), "CT", 0)
    points = scene.GetNodeByID(logics["markups"].LoadMarkups(str(sample_case_dir / "ct_centroids.mrk.json")))
    xray = logics["volumes"].AddArchetypeVolume(str(sample_case_dir / "xray.dcm"), "X-ray", 0)
    clicks = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    clicks_node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "X-ray clicks")
    matrix = module.slicer_nodes().ijk_to_ras(xray)
    for label, (u, v) in zip(clicks.labels, clicks.uv_px, strict=True):
        ras = (matrix @ [u, v, 0.0, 1.0])[:3]
        clicks_node.AddControlPoint(*map(float, ras), label)
    parameter_node = scene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", "CarmReg")
    module.slicer_nodes().set_default_parameters(parameter_node)
    for role, node in (("CT", ct), ("CTPoints", points), ("Xray", xray), ("XrayPoints", clicks_node)):
        parameter_node.SetNodeReferenceID(role, node.GetID())
    return {"ct": ct, "points": points, "xray": xray, "clicks": clicks_node, "parameters": parameter_node,
            "clicks_uv": clicks}


def test_mrml_nodes_become_carmregs_objects_as_its_own_readers_give_them(sample_nodes, sample_case_dir):
    from carmreg.logic.io.landmarks import read_landmarks_3d
    from carmreg.logic.io.volumes import load_volume
    from carmreg.logic.io.xray import load_xray

    module = _module()
    ct, ct_file = module.slicer_nodes().ct_from_node(sample_nodes["ct"]), load_volume(sample_case_dir / "ct.nrrd")
    # Slicer's reader makes the IJK axes right-handed (here: k reversed): the same voxels at the same LPS places
    node_to_file_ijk = np.linalg.inv(ct_file.ijk_to_lps) @ ct.ijk_to_lps
    np.testing.assert_allclose(node_to_file_ijk, np.round(node_to_file_ijk), atol=1e-4)
    assert ct.shape == ct_file.shape and np.linalg.det(ct.ijk_to_lps[:3, :3]) > 0
    index = np.indices(ct.shape).reshape(3, -1)
    file_index = np.round(node_to_file_ijk[:3, :3]) @ index + np.round(node_to_file_ijk[:3, 3])[:, None]
    assert np.array_equal(ct.hu.reshape(-1), ct_file.hu[tuple(file_index.astype(int))])
    points, points_file = module.slicer_nodes().ct_points_from_node(sample_nodes["points"]), read_landmarks_3d(
        sample_case_dir / "ct_centroids.mrk.json")
    assert points.labels == points_file.labels
    np.testing.assert_allclose(points.points_lps_mm, points_file.points_lps_mm, atol=1e-6)
    clicks = module.slicer_nodes().xray_points_from_node(sample_nodes["clicks"], sample_nodes["xray"])
    assert clicks.labels == sample_nodes["clicks_uv"].labels
    np.testing.assert_allclose(clicks.uv_px, sample_nodes["clicks_uv"].uv_px, atol=1e-6)
    nodes = module.slicer_nodes()
    xray, xray_file = nodes.xray_from_node(sample_nodes["xray"]), load_xray(sample_case_dir / "xray.dcm")
    assert xray.intrinsics.sdd_mm == xray_file.intrinsics.sdd_mm and xray.source == xray_file.source
    assert np.array_equal(module.slicer_nodes().voxels_kji(sample_nodes["xray"])[0], np.asarray(xray_file.pixels))
    manual = module.slicer_nodes().xray_from_node(sample_nodes["xray"], sdd_mm=1100.0, sod_mm=700.0,
                                                  distortion_mm=2.5)
    assert manual.intrinsics.sdd_mm == 1100.0 and manual.sod_mm == 700.0 and manual.intrinsics.distortion_mm == 2.5


def test_parameter_node_defaults_and_bad_values(mrml):
    scene, _, _ = mrml
    module = _module()
    node = scene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", "CarmReg parameters")
    node.SetParameter("SddMm", "1020")
    module.slicer_nodes().set_default_parameters(node)
    assert module.slicer_nodes().parameters_from_node(node) == (1020.0, 0.0, 0.0, "gc", True, 0.0)
    node.SetParameter("Metric", "psnr")
    node.SetParameter("CheckLevels", "false")
    node.SetParameter("DistortionMm", "-1.5")  # barrel distortion is a negative pincushion, kept as given
    assert module.slicer_nodes().parameters_from_node(node)[3:] == ("psnr", False, -1.5)
    node.SetParameter("Metric", "best")
    with pytest.raises(ValueError, match="Metric = 'best'; choose one of gc"):
        module.slicer_nodes().parameters_from_node(node)
    node.SetParameter("Metric", "gc")
    node.SetParameter("SodMm", "six hundred")
    with pytest.raises(ValueError, match="SodMm = 'six hundred' is not a number"):
        module.slicer_nodes().parameters_from_node(node)


def test_the_pincushion_is_measured_on_a_bead_grid_volume_slicer_loaded(mrml, tmp_path):
    """A bead-grid X-ray (DICOM) loaded by Slicer's volume reader, measured: the parameter node's DistortionMm is
    set to the grid's pincushion (drawn at 3 mm); without a grid selected, one clear line."""
    from grid_images import PIXEL_MM, grid_image

    from carmreg.logic.geometry.camera import CarmIntrinsics
    from carmreg.logic.io.xray_write import write_xray_dicom

    scene, logics, _ = mrml
    module = _module()
    pixels = grid_image(3.0).astype(np.uint16)
    dcm = write_xray_dicom(tmp_path / "grid.dcm", pixels, CarmIntrinsics(1000.0, (PIXEL_MM, PIXEL_MM),
                                                                          pixels.shape[::-1]))
    grid = logics["volumes"].AddArchetypeVolume(str(dcm), "Bead grid", 0)
    node = scene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", "CarmReg grid")
    module.slicer_nodes().set_default_parameters(node)
    with pytest.raises(ValueError, match="select the bead-grid X-ray"):
        module.slicer_nodes().measure_distortion(node)
    node.SetNodeReferenceID("GridXray", grid.GetID())  # its pixel spacing: the DICOM file's
    calibration = module.slicer_nodes().measure_distortion(node)
    assert calibration.distortion_mm == pytest.approx(3.0, abs=0.05) and calibration.beads > 300
    assert node.GetParameter("DistortionMm") == "3" and module.slicer_nodes().parameters_from_node(node)[5] == 3.0


@pytest.fixture(scope="module")
def sample_registered(sample_nodes, drr_cache_dir):
    """The sample case registered from its MRML nodes, named clicks taken as named (one labelling, faster):
    (result, ct, ct_landmarks, xray)."""
    parameters = sample_nodes["parameters"]
    parameters.SetParameter("CheckLevels", "false")
    return _module().slicer_nodes().register_nodes(parameters, cache_dir=drr_cache_dir)


@pytest.mark.slow
def test_the_sample_case_registers_from_mrml_nodes_and_the_outputs_land_on_the_xray(mrml, sample_nodes,
                                                                                    sample_registered):
    from carmreg.logic.geometry.camera import project

    scene = mrml[0]
    module = _module()
    parameters = sample_nodes["parameters"]
    result, ct, ct_landmarks, xray = sample_registered
    assert result.level_check is None or result.level_check.mode == "named"
    assert result.ok, result.warnings
    pdes = [lv["pde_mm"] for lv in result.levels if lv.get("pde_mm") is not None]
    assert len(pdes) == 3 and max(pdes) < 5.0
    module.slicer_nodes().show_result(scene, parameters, result, xray)
    # C-arm: camera origin -> the X-ray source in RAS; a CT centroid -> camera frame -> projects by K
    to_parent = module.slicer_nodes().matrix_to_numpy(_to_parent(parameters.GetNodeReference("CarmTransform")))
    f = np.diag([-1.0, -1.0, 1.0, 1.0])
    np.testing.assert_allclose(to_parent[:3, 3], np.diag([-1.0, -1, 1]) @ result.geometry.source_lps_mm(result.pose),
                               atol=1e-6)
    t12 = ct_landmarks.as_dict()["T12"]
    camera = (f @ np.linalg.inv(to_parent) @ np.r_[np.diag([-1.0, -1, 1]) @ t12, 1.0])[:3]
    uv_k = (result.geometry.intrinsics.K @ camera)[:2] / camera[2]
    np.testing.assert_allclose(uv_k, project(result.projection_matrix, t12[None])[0], atol=1e-6)
    # DRR and overlay on the X-ray's grid; projected levels on the X-ray voxel of their pixel
    xray_matrix = module.slicer_nodes().ijk_to_ras(sample_nodes["xray"])
    drr, overlay = parameters.GetNodeReference("DRR"), parameters.GetNodeReference("Overlay")
    np.testing.assert_allclose(module.slicer_nodes().ijk_to_ras(drr), xray_matrix)
    np.testing.assert_allclose(module.slicer_nodes().voxels_kji(drr)[0], result.drr_line_integral, rtol=1e-6)
    assert module.slicer_nodes().voxels_kji(overlay).shape == (1, *xray.pixels.shape, 3)
    levels = parameters.GetNodeReference("ProjectedLevels")
    assert levels.GetNumberOfControlPoints() == len(result.levels)
    for i, level in enumerate(result.levels):
        assert levels.GetNthControlPointLabel(i) == level["label"]
        expected = (xray_matrix @ [*level["uv_px"], 0.0, 1.0])[:3]
        np.testing.assert_allclose(levels.GetNthControlPointPositionWorld(i), expected, atol=1e-6)


@pytest.mark.slow
def test_an_xray_volume_stored_mirrored_registers_turned_back_and_its_outputs_land_on_it_as_stored(
        mrml, sample_nodes, sample_registered, sample_case_dir, drr_cache_dir, tmp_path):
    """The sample X-ray written mirrored (the same header) and loaded by Slicer's reader, its clicks placed where
    that volume shows them; with XrayOrientation = mirrored-left-right (and a polarity given) it registers as the
    acquisition does, and the DRR, overlay and projected levels come back onto the mirrored volume's own grid. A
    storage given (the one the image gives) is taken as set; a polarity, storage or orientation not offered is refused
    in words."""
    from carmreg.logic.image.appearance import STORAGE_FROM_USER
    from carmreg.logic.io.xray import load_xray
    from carmreg.logic.io.xray_write import write_xray_dicom

    scene, logics, _ = mrml
    nodes = _module().slicer_nodes()
    acquired = load_xray(sample_case_dir / "xray.dcm")
    cols = acquired.size_px[0]
    path = write_xray_dicom(tmp_path / "mirrored.dcm", np.ascontiguousarray(acquired.pixels.astype(np.uint16)[:, ::-1]),
                            acquired.intrinsics, sod_mm=acquired.sod_mm)
    xray_node = logics["volumes"].AddArchetypeVolume(str(path), "X-ray mirrored", 0)
    clicks_node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "X-ray clicks mirrored")
    matrix = nodes.ijk_to_ras(xray_node)
    clicks = sample_nodes["clicks_uv"]
    for label, (u, v) in zip(clicks.labels, clicks.uv_px, strict=True):
        clicks_node.AddControlPoint(*map(float, (matrix @ [cols - 1 - u, v, 0.0, 1.0])[:3]), label)
    parameters = scene.AddNewNodeByClass("vtkMRMLScriptedModuleNode", "CarmReg mirrored")
    nodes.set_default_parameters(parameters)
    for role, node in (("CT", sample_nodes["ct"]), ("CTPoints", sample_nodes["points"]), ("Xray", xray_node),
                       ("XrayPoints", clicks_node)):
        parameters.SetNodeReferenceID(role, node.GetID())
    parameters.SetParameter("CheckLevels", "false")
    parameters.SetParameter("XrayOrientation", "mirrored-left-right")
    parameters.SetParameter("Polarity", "bone-dark")
    parameters.SetParameter("Storage", expected_storage := sample_registered[0].appearance.storage)  # as found
    result, _, _, xray = nodes.register_nodes(parameters, cache_dir=drr_cache_dir)
    expected = sample_registered[0]
    np.testing.assert_allclose(result.projection_matrix, expected.projection_matrix, rtol=1e-6, atol=1e-6)
    assert result.appearance.polarity == "bone-dark" and result.appearance.decided_by == "user"
    assert (result.appearance.storage, result.appearance.storage_from) == (expected_storage, STORAGE_FROM_USER)
    np.testing.assert_array_equal(xray.pixels, acquired.pixels)
    nodes.show_result(scene, parameters, result, xray)
    drr = nodes.voxels_kji(parameters.GetNodeReference("DRR"))[0]
    np.testing.assert_allclose(drr, expected.drr_line_integral[:, ::-1], rtol=1e-6)
    np.testing.assert_allclose(nodes.ijk_to_ras(parameters.GetNodeReference("Overlay")), matrix)
    levels = parameters.GetNodeReference("ProjectedLevels")
    for i, level in enumerate(expected.levels):
        u, v = level["uv_px"]
        np.testing.assert_allclose(levels.GetNthControlPointPositionWorld(i),
                                   (matrix @ [cols - 1 - u, v, 0.0, 1.0])[:3], atol=1e-6)
    parameters.SetParameter("XrayOrientation", "sideways")
    with pytest.raises(ValueError, match="XrayOrientation = 'sideways'; choose one of as-stored"):
        nodes.register_nodes(parameters)
    parameters.SetParameter("Storage", "raw")
    with pytest.raises(ValueError, match="Storage = 'raw'; choose one of auto, linear-intensity, log-display"):
        nodes.register_nodes(parameters)
    parameters.SetParameter("Storage", "auto")
    parameters.SetParameter("Field", "round")
    with pytest.raises(ValueError, match="Field = 'round'; choose one of auto, whole"):
        nodes.register_nodes(parameters)


def _to_parent(transform_node):
    import vtk

    m = vtk.vtkMatrix4x4()
    transform_node.GetMatrixTransformToParent(m)
    return m


def test_a_refused_images_projected_levels_in_slicer_carry_a_question_mark(mrml, sample_nodes):
    """Names withheld (the X-ray refused): the live Slicer scene's projected levels are named "T11?" ..., and the
    panel's summary gives no per-level PDE."""
    from types import SimpleNamespace

    from carmreg.logic.registration.level_check import LevelCheck

    scene, nodes = mrml[0], _module().slicer_nodes()
    check = LevelCheck("unnamed", "ambiguous", assigned_labels=["T11", "T12"]).withheld_for("display mirrored")
    levels = [{"label": lb, "uv_px": [10.0 * i, 20.0], "fitted": i < 2, "pde_mm": 1.0 if i < 2 else None}
              for i, lb in enumerate(["T11", "T12", "L1"])]
    result = SimpleNamespace(levels=levels, level_check=check, ok=False, warnings=["display mirrored"],
                             failed_checks=["display mirrored"], stages=[])
    markups = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "refused")
    nodes.set_projected_levels(markups, result, sample_nodes["xray"])
    assert [markups.GetNthControlPointLabel(i) for i in range(3)] == ["T11?", "T12?", "L1?"]
    summary = nodes.result_summary(result)
    assert "IMAGE REFUSED - NO LEVEL NAMED" in summary and "PDE per clicked level" not in summary
