"""A 3D Slicer scene of a registration: ``slicer/CarmReg.mrml`` and the files it names, all in one folder.

Open it in Slicer with File > Load Scene (or drag the ``.mrml`` onto the window); the folder can be moved or
zipped as a whole (file names in the scene are relative). What it holds, in the CT's world (Slicer shows RAS;
every file is LPS, as Slicer reads and writes them):

=====================  ===========================  ======================================================
node (name)            file                         what
=====================  ===========================  ======================================================
``CT`` volume          ``ct.nrrd``                  the CT in HU with its own ijk -> LPS geometry
``CT centroids``       ``ct_points.mrk.json``       the CT's labelled vertebral centroids (LPS mm)
``X-ray`` volume       ``xray.nrrd``                the X-ray as stored, a one-slice volume on the detector
                                                    plane at the registered pose (voxel (u, v, 0) = pixel)
``DRR`` volume         ``drr.nrrd``                 the DRR's line integrals on the same plane and grid
``X-ray clicks``       ``xray_points.mrk.json``     the clicks on the X-ray, on the detector plane (LPS mm;
                                                    exact ``uv_px`` under ``carmreg``)
``Projected levels``   ``projected_levels.mrk.json``  every CT-labelled level's centroid projected by P onto
                                                    the detector plane, named (``uv_px``, fitted, PDE);
                                                    names the image did not confirm (ambiguous,
                                                    contradicted, withheld) end in "?" on the
                                                    detector plane (``style.unsure_name``)
``C-arm`` transform    ``carm.tfm``                 ITK ``lps_to_camera`` (see ``io.transforms``): Slicer's
                                                    transform node then maps the camera frame (x, y flipped
                                                    as Slicer does for LPS files) to RAS; its translation is
                                                    the X-ray source in RAS
=====================  ===========================  ======================================================

A projected level lies on the ray from the X-ray source through its CT centroid, where that ray meets the
detector plane: ``pixel_to_detector_lps(geometry, pose, uv_px)`` with ``uv_px = project(P, centroid)`` (with an
image intensifier's distortion given, ``geometry.distortion``: where the X-ray shows it, off that ray by the
distortion, so that it sits on the level in the X-ray volume). The
X-ray and DRR voxels are laid out by ``result_files.detector_ijk_to_lps``, so a projected level sits on the
X-ray voxel of its pixel. The scene is MRML XML written here directly (no Slicer needed at run time); the
tests read it with Slicer's own scene loader (``slicer-core``).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from carmreg.logic.geometry.camera import pixel_to_detector_lps
from carmreg.logic.io.atomic import atomic_write, atomic_write_text
from carmreg.logic.io.landmarks import write_landmarks_3d, write_markups_lps
from carmreg.logic.io.nrrd_volume import write_volume_nrrd
from carmreg.logic.io.transforms import write_tfm
from carmreg.logic.report.result_files import detector_ijk_to_lps, write_detector_nrrd, write_drr_nrrd
from carmreg.logic.report.style import unsure_name

SCENE_FOLDER = "slicer"
SCENE_FILE = "CarmReg.mrml"
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])
CT_WINDOW_LEVEL = (1500.0, 300.0)  # HU, a bone window
GREY = "vtkMRMLColorTableNodeGrey"  # one of Slicer's default colour tables (present in every scene)
COLOURS = {"ct": (0.4, 1.0, 1.0), "clicks": (1.0, 0.24, 0.24), "projected": (1.0, 0.82, 0.16)}


def lps_to_camera_matrix(result) -> np.ndarray:
    """4x4 rigid lps_to_camera of the result's pose (what ``carm.tfm`` holds)."""
    rotation, t = result.geometry.extrinsics(result.pose)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, t
    return matrix


def detector_points_lps(result, uv_px) -> np.ndarray:
    """(n, 3) LPS mm of detector pixels (n, 2) (column, row) on the detector plane at the result's pose."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    return pixel_to_detector_lps(result.geometry, result.pose, uv) if len(uv) else np.zeros((0, 3))


def _clicks(result, clicked: dict | None) -> dict:
    if clicked is not None:
        return {label: uv for label, uv in clicked.items() if uv is not None}
    return {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv.get("clicked_uv_px") is not None}


def write_scene_files(folder: Path, result, ct, ct_landmarks, xray_pixels: np.ndarray,
                      clicked: dict | None, drr_nrrd: Path | None = None) -> dict[str, Path]:
    """Every data file of the scene into ``folder`` (atomic writes); returns {key: path}. ``drr_nrrd``: the
    result's DRR already written by ``write_drr_nrrd`` (copied, not encoded again)."""
    pixels = np.asarray(xray_pixels)
    pixel_type = pixels.dtype if pixels.dtype.kind in "iu" else np.float32
    check = getattr(result, "level_check", None)
    clicks = {unsure_name(label, check): uv for label, uv in _clicks(result, clicked).items()}
    levels = list(result.levels)
    files = {
        "ct": write_volume_nrrd(folder / "ct.nrrd", ct),
        "ct_points": write_landmarks_3d(folder / "ct_points.mrk.json", ct_landmarks),
        "xray": write_detector_nrrd(folder / "xray.nrrd", pixels, result.geometry, result.pose,
                                    "CarmReg X-ray as stored; axis 0 = column u, axis 1 = row v, axis 2 = one "
                                    "slice on the detector plane at the registered pose", dtype=pixel_type),
        "xray_points": write_markups_lps(folder / "xray_points.mrk.json", list(clicks),
                                         detector_points_lps(result, list(clicks.values())),
                                         [{"uv_px": [float(x) for x in uv]} for uv in clicks.values()]),
        "projected_levels": write_markups_lps(
            folder / "projected_levels.mrk.json", [unsure_name(lv["label"], check) for lv in levels],
            detector_points_lps(result, [lv["uv_px"] for lv in levels]),
            [{"uv_px": [float(x) for x in lv["uv_px"]], "fitted": bool(lv["fitted"]),
              "in_image": bool(lv.get("in_image", True)), "pde_mm": lv.get("pde_mm")} for lv in levels]),
        "carm": write_tfm(folder / "carm.tfm", lps_to_camera_matrix(result),
                          comment="lps_to_camera: CT LPS mm -> C-arm camera mm (origin at the X-ray source)"),
    }
    if drr_nrrd is not None:
        files["drr"] = atomic_write(folder / "drr.nrrd", lambda tmp: shutil.copyfile(drr_nrrd, tmp))
    elif result.drr_line_integral is not None:
        files["drr"] = write_drr_nrrd(folder / "drr.nrrd", result.drr_line_integral, result.geometry, result.pose)
    return files


# ------------------------------------------------------------------------------------------------ MRML text

def _element(tag: str, attributes: dict) -> str:
    body = " ".join(f"{key}={quoteattr(str(value))}" for key, value in attributes.items())
    return f"<{tag} {body}>\n</{tag}>"


def _numbers(values) -> str:
    return " ".join(f"{float(x):.10g}" for x in np.asarray(values, float).ravel())


def _volume_geometry(ijk_to_lps: np.ndarray) -> dict:
    """MRML's ``spacing``, ``origin`` (RAS) and ``ijkToRASDirections`` (row-major, unit columns) attributes."""
    matrix = np.asarray(ijk_to_lps, float)
    spacing = np.linalg.norm(matrix[:3, :3], axis=0)
    directions_ras = LPS_TO_RAS @ (matrix[:3, :3] / spacing)
    return {"spacing": _numbers(spacing), "origin": _numbers(LPS_TO_RAS @ matrix[:3, 3]),
            "ijkToRASDirections": _numbers(directions_ras)}


def _volume_nodes(n: int, name: str, file_name: str, ijk_to_lps: np.ndarray,
                  window_level: tuple[float, float] | None) -> list[str]:
    display = {"id": f"vtkMRMLScalarVolumeDisplayNode{n}", "name": f"{name} display", "hideFromEditors": "true",
               "colorNodeID": GREY, "interpolate": "1", "visibility": "true",
               "autoWindowLevel": "0" if window_level else "1"}
    if window_level:
        display.update(window=f"{window_level[0]:g}", level=f"{window_level[1]:g}")
    storage = {"id": f"vtkMRMLVolumeArchetypeStorageNode{n}", "name": f"{name} storage",
               "hideFromEditors": "true", "fileName": file_name, "useCompression": "1"}
    volume = {"id": f"vtkMRMLScalarVolumeNode{n}", "name": name, "hideFromEditors": "false",
              "references": f"display:{display['id']};storage:{storage['id']};", **_volume_geometry(ijk_to_lps)}
    return [_element("VolumeDisplay", display), _element("VolumeArchetypeStorage", storage),
            _element("Volume", volume)]


def _markups_nodes(n: int, name: str, file_name: str, rgb: tuple[float, float, float]) -> list[str]:
    display = {"id": f"vtkMRMLMarkupsFiducialDisplayNode{n}", "name": f"{name} display",
               "hideFromEditors": "true", "color": _numbers(rgb), "selectedColor": _numbers(rgb),
               "visibility": "true", "pointLabelsVisibility": "true", "glyphScale": "3", "textScale": "3"}
    storage = {"id": f"vtkMRMLMarkupsJsonStorageNode{n}", "name": f"{name} storage", "hideFromEditors": "true",
               "fileName": file_name, "coordinateSystem": "LPS"}
    markups = {"id": f"vtkMRMLMarkupsFiducialNode{n}", "name": name, "hideFromEditors": "false",
               "references": f"display:{display['id']};storage:{storage['id']};", "locked": "true"}
    return [_element("MarkupsFiducialDisplay", display), _element("MarkupsJsonStorage", storage),
            _element("MarkupsFiducial", markups)]


def _transform_nodes(name: str, file_name: str) -> list[str]:
    storage = {"id": "vtkMRMLTransformStorageNode1", "name": f"{name} storage", "hideFromEditors": "true",
               "fileName": file_name}
    transform = {"id": "vtkMRMLLinearTransformNode1", "name": name, "hideFromEditors": "false",
                 "references": f"storage:{storage['id']};"}
    return [_element("TransformStorage", storage), _element("LinearTransform", transform)]


def scene_xml(result, ct, files: dict[str, Path]) -> str:
    """The MRML document naming ``files`` by their base names (relative to the scene's folder)."""
    detector = detector_ijk_to_lps(result.geometry, result.pose)
    elements = _volume_nodes(1, "CT", files["ct"].name, ct.ijk_to_lps, CT_WINDOW_LEVEL)
    elements += _volume_nodes(2, "X-ray", files["xray"].name, detector, None)
    if "drr" in files:
        elements += _volume_nodes(3, "DRR", files["drr"].name, detector, None)
    elements += _markups_nodes(1, "CT centroids", files["ct_points"].name, COLOURS["ct"])
    elements += _markups_nodes(2, "X-ray clicks", files["xray_points"].name, COLOURS["clicks"])
    elements += _markups_nodes(3, "Projected levels", files["projected_levels"].name, COLOURS["projected"])
    elements += _transform_nodes("C-arm", files["carm"].name)
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<MRML version="Slicer4.4.0" userTags="">\n'
            + "\n".join(elements) + "\n</MRML>\n")


def write_slicer_scene(out_dir: str | Path, result, ct, ct_landmarks, xray_pixels: np.ndarray,
                       clicked: dict | None = None, drr_nrrd: Path | None = None) -> dict[str, Path]:
    """Write ``out_dir/slicer/CarmReg.mrml`` and its files; returns {"slicer_scene": mrml path, key: path}.

    ct: the registered CT (``Volume``, HU, ``ijk_to_lps``); ct_landmarks: its ``Landmarks3D``; xray_pixels:
    the X-ray ``[row, column]`` as stored; clicked: {label: (u, v) px} of the clicks (default: the result's
    paired clicks); drr_nrrd: the result's ``drr.nrrd`` when already written (copied into the scene).
    """
    folder = Path(out_dir) / SCENE_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    files = write_scene_files(folder, result, ct, ct_landmarks, xray_pixels, clicked, drr_nrrd)
    scene = atomic_write_text(folder / SCENE_FILE, scene_xml(result, ct, files))
    return {"slicer_scene": scene, **{f"slicer_{key}": path for key, path in files.items()}}
