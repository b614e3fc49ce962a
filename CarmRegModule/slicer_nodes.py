"""3D Slicer's MRML nodes <-> CarmReg's objects, for the Slicer module (``CarmReg.py``): the CT volume and its
centroids, the X-ray volume and its clicks, and the result laid back into the scene (the C-arm transform, the DRR
and the overlay on the X-ray volume's grid, the projected levels). Needs VTK and numpy only, so the tests run it
against ``slicer-core``'s real MRML nodes outside Slicer.

Frames: Slicer's world is RAS; CarmReg's is the CT's LPS (RAS = diag(-1, -1, 1) LPS). The X-ray volume's voxel
(i, j, 0) is detector pixel (u, v) = (column, row) of the image as stored. With an X-ray orientation other than
as stored (``XrayOrientation``, ``image.turn``: a display stored mirrored or rotated), the X-ray and its clicks are
turned before registering, and the outputs turned back onto the stored volume's grid.
"""

from __future__ import annotations

import os

import numpy as np

from carmreg.logic.image.appearance import POLARITY_SETTINGS
from carmreg.logic.image.field import FIELDS
from carmreg.logic.image.prepare import STORAGE_SETTINGS
from carmreg.logic.image.turn import ORIENTATIONS
from carmreg.logic.similarity.metrics import METRICS

LPS_TO_RAS_4 = ((-1.0, 0, 0, 0), (0, -1.0, 0, 0), (0, 0, 1.0, 0), (0, 0, 0, 1.0))

# Parameter node: node references (role -> MRML class) and parameters (name -> default, as text)
NODE_ROLES = {"CT": "vtkMRMLScalarVolumeNode", "CTPoints": "vtkMRMLMarkupsFiducialNode",
              "Xray": "vtkMRMLScalarVolumeNode", "XrayPoints": "vtkMRMLMarkupsFiducialNode",
              "CarmTransform": "vtkMRMLLinearTransformNode", "DRR": "vtkMRMLScalarVolumeNode",
              "Overlay": "vtkMRMLVectorVolumeNode", "ProjectedLevels": "vtkMRMLMarkupsFiducialNode",
              "GridXray": "vtkMRMLScalarVolumeNode"}
OUTPUT_NAMES = {"CarmTransform": "C-arm", "DRR": "DRR", "Overlay": "Overlay", "ProjectedLevels": "Projected levels"}
DEFAULT_PARAMETERS = {"SddMm": "0", "PixelSpacingMm": "0", "SodMm": "0", "DistortionMm": "0", "Metric": "gc",
                      "CheckLevels": "true", "EstimatePincushion": "true", "Polarity": "auto", "Storage": "auto",
                      "Field": "auto", "XrayOrientation": "as-stored"}
"""0 = take the value from the X-ray file (DICOM tags) or CarmReg's default; EstimatePincushion: a round field
with no DistortionMm given gets its pincushion estimated from the image (``registration.pincushion``); Polarity:
auto (found from the image against the CT), bone-dark or bone-bright; Storage (a bone-dark X-ray's): auto (as its
DICOM states, else found from the image), linear-intensity or log-display; Field: auto (the exposed field found from
the image) or whole; XrayOrientation: ``image.turn.ORIENTATIONS`` (module docstring)."""


def matrix_to_numpy(vtk_matrix):
    return np.array([[vtk_matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def numpy_to_matrix(array):
    import vtk

    m = vtk.vtkMatrix4x4()
    for i in range(4):
        for j in range(4):
            m.SetElement(i, j, float(array[i][j]))
    return m


def ijk_to_ras(volume_node):
    """4x4 IJK -> RAS of a volume node (its own geometry; a parent transform is not applied)."""
    import vtk

    m = vtk.vtkMatrix4x4()
    volume_node.GetIJKToRASMatrix(m)
    return matrix_to_numpy(m)


def voxels_kji(volume_node):
    """A copy of the volume's voxels indexed [k, j, i] (numpy order of VTK image data)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    image = volume_node.GetImageData()
    if image is None:
        raise ValueError(f"volume '{volume_node.GetName()}' has no image data")
    nx, ny, nz = image.GetDimensions()
    scalars = vtk_to_numpy(image.GetPointData().GetScalars())
    components = image.GetNumberOfScalarComponents()
    shape = (nz, ny, nx) if components == 1 else (nz, ny, nx, components)
    return scalars.reshape(shape).copy()


def ct_from_node(volume_node):
    """The CT volume node as CarmReg's ``Volume`` (HU [i, j, k], ijk_to_lps = diag(-1, -1, 1, 1) IJKToRAS)."""
    from carmreg.logic.geometry.volume import Volume

    lps = np.asarray(LPS_TO_RAS_4) @ ijk_to_ras(volume_node)
    return Volume(np.ascontiguousarray(voxels_kji(volume_node).transpose(2, 1, 0)), lps,
                  f"Slicer volume '{volume_node.GetName()}'")


def _control_points_ras(markups_node):
    n = markups_node.GetNumberOfControlPoints()
    labels = [markups_node.GetNthControlPointLabel(i) for i in range(n)]
    return labels, np.array([markups_node.GetNthControlPointPositionWorld(i) for i in range(n)]).reshape(-1, 3)


def ct_points_from_node(markups_node):
    """The CT centroids (labels = level names) as ``Landmarks3D`` in LPS mm."""
    from carmreg.logic.io.landmarks import Landmarks3D

    labels, ras = _control_points_ras(markups_node)
    return Landmarks3D(labels, ras * [-1.0, -1.0, 1.0], f"Slicer markups '{markups_node.GetName()}'") \
        if len(labels) else Landmarks3D([], np.zeros((0, 3)), markups_node.GetName())


def xray_points_from_node(markups_node, xray_node):
    """Clicks on the X-ray volume as ``Landmarks2D``: (u, v) = (i, j) of each point's RAS in the X-ray's IJK.

    An empty label is an unnamed click."""
    from carmreg.logic.io.landmarks import Landmarks2D

    labels, ras = _control_points_ras(markups_node)
    ras_to_ijk = np.linalg.inv(ijk_to_ras(xray_node))
    ijk = (ras_to_ijk @ np.c_[ras, np.ones(len(ras))].T).T[:, :3] if len(ras) else np.zeros((0, 3))
    return Landmarks2D([lb or None for lb in labels], ijk[:, :2], f"Slicer markups '{markups_node.GetName()}'")


def _storage_file(node):
    storage = node.GetStorageNode()
    path = storage.GetFileName() if storage is not None else None
    return path if path and os.path.isfile(path) else None


def xray_from_node(xray_node, sdd_mm=0.0, pixel_spacing_mm=0.0, sod_mm=0.0, distortion_mm=0.0):
    """The X-ray as ``XrayImage``. Loaded from a file: ``load_xray`` on it (DICOM geometry tags), with the
    non-zero values given overriding; else its pixels with the given geometry (pixel spacing default: the
    volume's spacing)."""
    from carmreg.logic.geometry.camera import CarmIntrinsics
    from carmreg.logic.io.xray import XrayImage, load_xray

    voxels = voxels_kji(xray_node)
    if voxels.ndim != 3 or voxels.shape[0] != 1:
        raise ValueError(f"X-ray '{xray_node.GetName()}' must be a single 2D image (one slice, one component), "
                         f"got voxels {voxels.shape}")
    path = _storage_file(xray_node)
    overrides = {"sdd_mm": sdd_mm or None, "pixel_spacing_mm": pixel_spacing_mm or None, "sod_mm": sod_mm or None,
                 "distortion_mm": distortion_mm or None}
    if path is not None:
        xray = load_xray(path, **overrides)
        if xray.pixels.shape == voxels.shape[1:]:
            return xray
    spacing = pixel_spacing_mm or float(xray_node.GetSpacing()[0])
    rows, cols = voxels.shape[1:]
    intrinsics = CarmIntrinsics(float(sdd_mm or 1000.0), (spacing, spacing), (cols, rows), None,
                                {"sdd_mm": "manual" if sdd_mm else "default"}, float(distortion_mm or 0.0))
    return XrayImage(np.asarray(voxels[0], np.float32), intrinsics, sod_mm or None, True,
                     f"Slicer volume '{xray_node.GetName()}'")


def measure_distortion(parameter_node):
    """The pincushion measured on the parameter node's bead-grid X-ray ("GridXray",
    ``grid_calibration.calibrate_for_detector``) and set as its ``DistortionMm``; returns the ``GridCalibration``.
    The grid's pixel spacing: the panel's, else its file's or volume's (``xray_from_node``); its principal point:
    the selected X-ray's when the grid image has its size. Raises CarmReg's errors (one clear line)."""
    from carmreg.logic.image.grid_calibration import calibrate_for_detector

    grid_node = parameter_node.GetNodeReference("GridXray")
    if grid_node is None:
        raise ValueError("CarmReg: select the bead-grid X-ray (C-arm geometry) before measuring its pincushion")
    _, spacing_mm, _, _, _, _ = parameters_from_node(parameter_node)
    grid = xray_from_node(grid_node, pixel_spacing_mm=spacing_mm)
    xray_node = parameter_node.GetNodeReference("Xray")
    detector = xray_from_node(xray_node, pixel_spacing_mm=spacing_mm).intrinsics if xray_node is not None else None
    calibration = calibrate_for_detector(grid.pixels, grid.intrinsics.pixel_spacing_mm, detector, grid.source)
    parameter_node.SetParameter("DistortionMm", f"{round(calibration.distortion_mm, 2):g}")
    return calibration


def set_transform(transform_node, result):
    """The C-arm transform: to-parent = camera frame (x, y flipped, as Slicer reads LPS files) -> CT RAS,
    i.e. F inv(lps_to_camera) F with F = diag(-1, -1, 1, 1) - what Slicer makes of ``carm.tfm``."""
    rotation, t = result.geometry.extrinsics(result.pose)
    lps_to_camera = np.eye(4)
    lps_to_camera[:3, :3], lps_to_camera[:3, 3] = rotation, t
    f = np.asarray(LPS_TO_RAS_4)
    transform_node.SetMatrixTransformToParent(numpy_to_matrix(f @ np.linalg.inv(lps_to_camera) @ f))


def set_image_on_xray_grid(volume_node, image, xray_node):
    """Put ``image[row, column]`` (scalar, or (rows, cols, 3) RGB uint8) into a volume node on the X-ray's grid
    (voxel (u, v, 0) = pixel (u, v) of the X-ray)."""
    import vtk
    from vtkmodules.util.numpy_support import numpy_to_vtk

    array = np.ascontiguousarray(image)
    rows, cols = array.shape[:2]
    components = 1 if array.ndim == 2 else array.shape[2]
    vtk_image = vtk.vtkImageData()
    vtk_image.SetDimensions(cols, rows, 1)
    vtk_image.GetPointData().SetScalars(numpy_to_vtk(array.reshape(rows * cols, components) if components > 1
                                                     else array.ravel(), deep=True))
    volume_node.SetAndObserveImageData(vtk_image)
    volume_node.SetIJKToRASMatrix(numpy_to_matrix(ijk_to_ras(xray_node)))
    if volume_node.GetDisplayNode() is None:
        volume_node.CreateDefaultDisplayNodes()


def set_projected_levels(markups_node, result, xray_node, orientation="as-stored"):
    """Every CT-labelled level's projected centroid, named, on the X-ray volume (RAS of its voxel (u, v, 0) as
    stored: ``result``'s (u, v) on the X-ray turned by ``orientation`` taken back, ``image.turn.stored_uv``); with a
    "?" after each name the image did not confirm (``style.unsure_name``: ambiguous, contradicted, or the X-ray
    refused)."""
    from carmreg.logic.image.turn import stored_uv
    from carmreg.logic.report.style import unsure_name

    markups_node.RemoveAllControlPoints()
    matrix = ijk_to_ras(xray_node)
    check = getattr(result, "level_check", None)
    stored_size_px = tuple(xray_node.GetImageData().GetDimensions()[:2])
    for level in result.levels:
        (u, v), = stored_uv(np.array([level["uv_px"]], float), orientation, stored_size_px)
        ras = (matrix @ np.array([u, v, 0.0, 1.0]))[:3]
        index = markups_node.AddControlPoint(float(ras[0]), float(ras[1]), float(ras[2]),
                                             unsure_name(level["label"], check))
        markups_node.SetNthControlPointDescription(
            index, ("fitted" if level["fitted"] else "not fitted")
            + (f", PDE {level['pde_mm']:.2f} mm" if level.get("pde_mm") is not None else ""))
    markups_node.SetLocked(True)


def overlay_rgb(result, xray):
    """The overlay as the window and ``overlay.png`` draw it (``report.overlay.result_overlay_image``: the X-ray
    bone-bright whatever its stored polarity, the DRR's bone, the named levels, the level answer) as (rows, cols,
    3) uint8."""
    from carmreg.logic.report.overlay import result_overlay_image

    clicked = {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv.get("clicked_uv_px") is not None}
    return np.asarray(result_overlay_image(result, xray.pixels, clicked).convert("RGB"), np.uint8)


def set_default_parameters(parameter_node):
    """Fill the parameters the node lacks with DEFAULT_PARAMETERS."""
    for name, value in DEFAULT_PARAMETERS.items():
        if not parameter_node.GetParameter(name):
            parameter_node.SetParameter(name, value)


def parameters_from_node(parameter_node):
    """The registration settings of a parameter node: (sdd_mm, pixel_spacing_mm, sod_mm, metric, check_levels,
    distortion_mm); 0 = from the file or the default."""
    def number(name, least=0.0):
        text = parameter_node.GetParameter(name) or "0"
        try:
            return max(least, float(text))
        except ValueError:
            raise ValueError(f"CarmReg parameter {name} = {text!r} is not a number; set it in the module panel") \
                from None

    return (number("SddMm"), number("PixelSpacingMm"), number("SodMm"), _choice(parameter_node, "Metric", METRICS),
            (parameter_node.GetParameter("CheckLevels") or "true") == "true", number("DistortionMm", -np.inf))


def display_from_node(parameter_node):
    """(polarity, storage, field, orientation) of a parameter node's X-ray, each one of its settings, the first the
    default: ``POLARITY_SETTINGS``, ``STORAGE_SETTINGS``, ``FIELDS``, ``ORIENTATIONS`` (the words the module shows
    them in: ``xray_settings``)."""
    return tuple(_choice(parameter_node, name, tuple(choices)) for name, choices in (
        ("Polarity", POLARITY_SETTINGS), ("Storage", STORAGE_SETTINGS), ("Field", FIELDS),
        ("XrayOrientation", ORIENTATIONS)))


def _choice(parameter_node, name: str, choices: tuple) -> str:
    """A parameter node's setting ``name``: one of ``choices``, the first when unset; anything else a ValueError in
    words."""
    value = parameter_node.GetParameter(name) or choices[0]
    if value not in choices:
        raise ValueError(f"CarmReg parameter {name} = {value!r}; choose one of {', '.join(choices)}")
    return value


def output_node(scene, parameter_node, role):
    """The output node the parameter node references for ``role``, created (and referenced) when absent."""
    node = parameter_node.GetNodeReference(role)
    if node is None:
        node = scene.AddNewNodeByClass(NODE_ROLES[role], OUTPUT_NAMES[role])
        parameter_node.SetNodeReferenceID(role, node.GetID())
    return node


def register_nodes(parameter_node, logic=None, cache_dir=None):
    """Register the parameter node's CT, CT points, X-ray and X-ray clicks with ``logic`` (a
    ``carmreg.logic`` CarmRegLogic: progress, cancel); returns (result, ct, ct_landmarks, xray), ``xray`` turned by
    the node's XrayOrientation as registered. Raises CarmReg's errors (one clear line) on bad input."""
    from carmreg.logic.image.turn import turned_clicks, turned_xray
    from carmreg.logic.registration import pipeline

    nodes = {role: parameter_node.GetNodeReference(role) for role in ("CT", "CTPoints", "Xray", "XrayPoints")}
    missing = [role for role in ("CT", "CTPoints", "Xray") if nodes[role] is None]
    if missing:
        raise ValueError(f"CarmReg: select the {', '.join(missing)} input(s) first")
    sdd_mm, spacing_mm, sod_mm, metric, check_levels, distortion_mm = parameters_from_node(parameter_node)
    polarity, storage, field, orientation = display_from_node(parameter_node)
    ct = ct_from_node(nodes["CT"])
    ct_landmarks = ct_points_from_node(nodes["CTPoints"])
    xray = xray_from_node(nodes["Xray"], sdd_mm, spacing_mm, sod_mm, distortion_mm)
    clicks = xray_points_from_node(nodes["XrayPoints"], nodes["Xray"]) if nodes["XrayPoints"] else None
    if clicks is not None:
        clicks = turned_clicks(clicks, orientation, xray.size_px)
    xray = turned_xray(xray, orientation)
    params = pipeline.RegistrationParameters(
        metric=metric, level_check=check_levels, cache_dir=cache_dir, polarity=polarity, storage=storage,
        xray_field=field,
        estimate_pincushion=parameter_node.GetParameter("EstimatePincushion") != "false")
    result = (logic or pipeline.CarmRegLogic()).register(ct, ct_landmarks, xray, clicks, params)
    return result, ct, ct_landmarks, xray


def show_result(scene, parameter_node, result, xray):
    """Write a result into the output nodes (created when absent): C-arm transform, DRR and overlay volumes
    on the X-ray's grid, projected named levels. ``xray``: as registered (``register_nodes``); images and levels
    drawn on it go back onto the stored X-ray volume's grid by the node's XrayOrientation."""
    from carmreg.logic.image.turn import stored_image

    xray_node = parameter_node.GetNodeReference("Xray")
    orientation = display_from_node(parameter_node)[3]
    set_transform(output_node(scene, parameter_node, "CarmTransform"), result)
    if result.drr_line_integral is not None:
        for role, image in (("DRR", result.drr_line_integral), ("Overlay", overlay_rgb(result, xray))):
            set_image_on_xray_grid(output_node(scene, parameter_node, role), stored_image(image, orientation),
                                   xray_node)
    set_projected_levels(output_node(scene, parameter_node, "ProjectedLevels"), result, xray_node, orientation)


def result_summary(result):
    """A few lines for the panel: status, the level answer, mPDE per stage (and the PDE per clicked level, unless
    the answer withholds the names)."""
    from carmreg.logic.report.style import level_banner, names_shown

    lines = ["OK" if result.ok else "CHECKS FAILED: " + "; ".join(result.failed_checks)]
    banner = level_banner(result.level_check)
    if banner:
        lines.append(banner[0])
    lines += [f"{s.name}: mPDE {s.mpde_mm:.2f} mm, {s.seconds:.1f} s" for s in result.stages
              if s.mpde_mm is not None]
    fitted = [f"{lv['label']} {lv['pde_mm']:.2f} mm" for lv in result.levels if lv.get("pde_mm") is not None]
    if fitted and names_shown(result.level_check):
        lines.append("PDE per clicked level: " + ", ".join(fitted))
    return "\n".join(lines)
