"""ITK text transform files (``.tfm`` / ``.txt``) and RAS <-> LPS conversion of 4x4 transforms.

What CarmReg writes
-------------------
The registration result as the rigid 4x4 ``lps_to_camera``: it maps a CT point (LPS mm) to the C-arm
camera frame (origin at the X-ray source, mm; +z from the source toward the detector, +x along detector
columns, +y along detector rows; see ``geometry.camera``). In ITK terms a transform file holds the
*resampling* transform, which maps points of the **fixed** space to the **moving** space; here the fixed
space is the CT (LPS) and the moving space is the C-arm camera frame. 3D Slicer, which shows the inverse
("modelling", camera -> CT) transform in RAS, therefore places an object given in camera coordinates
into the CT when this file is applied to it.

File layout (ITK ``#Insight Transform File V1.0``)::

    #Insight Transform File V1.0
    #Transform 0
    Transform: AffineTransform_double_3_3
    Parameters: a00 a01 a02 a10 a11 a12 a20 a21 a22 tx ty tz
    FixedParameters: cx cy cz

meaning ``y = A (x - c) + c + t``. ``read_tfm`` also reads the float variant, MatrixOffsetTransformBase,
Rigid3D, Euler3D (``R = Rz Rx Ry`` by default, ``Rz Ry Rx`` when its 4th fixed parameter is 1),
VersorRigid3D, Similarity3D, Translation, and a composite of those (the last listed is applied first, as
in ITK).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError
from carmreg.logic.io.atomic import atomic_write_text

HEADER = "#Insight Transform File V1.0"
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def ras_to_lps_matrix(matrix4x4: np.ndarray) -> np.ndarray:
    """A 4x4 transform between RAS points expressed between LPS points: ``F @ T @ F``, F = diag(-1,-1,1,1).

    The conversion is its own inverse, so the same function converts LPS to RAS.
    """
    return LPS_FROM_RAS @ np.asarray(matrix4x4, dtype=float) @ LPS_FROM_RAS


lps_to_ras_matrix = ras_to_lps_matrix


def write_tfm(path: str | Path, matrix4x4: np.ndarray, center=None, comment: str = "") -> Path:
    """Write a 4x4 affine as an ITK AffineTransform_double_3_3 text file, atomically.

    center: ITK's centre of rotation c (FixedParameters), default the origin; the parameters are chosen
    so that the file maps x to ``matrix4x4 @ [x, 1]`` whatever the centre.
    comment: extra ``#`` lines (e.g. what the transform maps), placed after the header.
    """
    m = np.asarray(matrix4x4, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError("write_tfm needs a finite 4x4 affine matrix with last row 0 0 0 1")
    c = np.zeros(3) if center is None else np.asarray(center, dtype=float).reshape(3)
    a = m[:3, :3]
    t = m[:3, 3] - c + a @ c  # y = A (x - c) + c + t  ==  A x + m[:3, 3]
    lines = [HEADER]
    lines += [f"# {line}" for line in comment.splitlines() if line.strip()]
    lines += ["#Transform 0", "Transform: AffineTransform_double_3_3",
              "Parameters: " + " ".join(_num(x) for x in (*a.ravel(), *t)),
              "FixedParameters: " + " ".join(_num(x) for x in c)]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def _num(x: float) -> str:
    return repr(float(x))


def read_tfm(path: str | Path) -> np.ndarray:
    """Read an ITK text transform file as the 4x4 (resampling, LPS) matrix it applies: fixed -> moving."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: transform file not found")
    if path.suffix.lower() in (".h5", ".hdf5", ".mat"):
        raise InputFileError(f"{path}: binary transform files are not read; save it as a text .tfm or .txt")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a text ITK transform file; save it as .tfm or .txt") from None
    if not text.startswith("#Insight Transform File"):
        raise InputFileError(f"{path}: not an ITK transform file (first line must be '{HEADER}')")
    transforms = _parse_blocks(text, path)
    if not transforms:
        raise InputFileError(f"{path}: holds no transform")
    result = np.eye(4)
    for name, params, fixed in transforms:  # composite: the last listed is applied first
        if name.startswith("CompositeTransform"):
            continue
        result = result @ _to_matrix(name, params, fixed, path)
    _check_matrix(result, path)
    return result


def _check_matrix(m: np.ndarray, path: Path) -> None:
    """Refuse a transform that cannot place anything: non-finite entries or a singular 3x3 part."""
    if not np.all(np.isfinite(m)):
        raise InputFileError(f"{path}: the transform holds NaN or infinite parameters; save it again")
    det = float(np.linalg.det(m[:3, :3]))
    if not abs(det) > 1e-9:
        raise InputFileError(f"{path}: the transform is singular (determinant {det:.3g}): it flattens space "
                             "and cannot be a pose; save the right transform")


def _parse_blocks(text: str, path: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    blocks, current = [], None
    for raw in text.splitlines():
        key, sep, value = raw.partition(":")
        key = key.strip()
        if not sep or key.startswith("#"):
            continue
        if key == "Transform":
            current = [value.strip(), np.zeros(0), np.zeros(0)]
            blocks.append(current)
        elif key in ("Parameters", "FixedParameters") and current is not None:
            try:
                numbers = np.array([float(x) for x in value.split()])
            except ValueError:
                raise InputFileError(f"{path}: {key} of {current[0]} are not numbers") from None
            current[1 if key == "Parameters" else 2] = numbers
    return [tuple(b) for b in blocks]


def _to_matrix(name: str, params: np.ndarray, fixed: np.ndarray, path: Path) -> np.ndarray:
    """4x4 of one ITK 3D transform: y = R (x - c) + c + t."""
    kind = name.split("_")[0]
    dims = name.rsplit("_", 2)[-2:]
    if dims != ["3", "3"]:
        raise InputFileError(f"{path}: transform {name} is not 3D -> 3D")
    c = fixed[:3] if fixed.size >= 3 else np.zeros(3)
    if kind in ("AffineTransform", "MatrixOffsetTransformBase", "Rigid3DTransform") and params.size == 12:
        a, t = params[:9].reshape(3, 3), params[9:12]
    elif kind == "Euler3DTransform" and params.size == 6:
        a, t = _euler_zxy(params[:3], zyx=fixed.size > 3 and fixed[3] == 1), params[3:6]
    elif kind == "VersorRigid3DTransform" and params.size == 6:
        a, t = _versor(params[:3]), params[3:6]
    elif kind == "Similarity3DTransform" and params.size == 7:
        a, t = params[6] * _versor(params[:3]), params[3:6]
    elif kind == "TranslationTransform" and params.size == 3:
        a, t, c = np.eye(3), params, np.zeros(3)
    else:
        raise InputFileError(f"{path}: transform type {name} with {params.size} parameters is not "
                             "supported; save it as an AffineTransform_double_3_3 (e.g. from Slicer's "
                             "Transforms module)")
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = t + c - a @ c
    return m


def _euler_zxy(angles_rad: np.ndarray, zyx: bool = False) -> np.ndarray:
    """ITK Euler3DTransform: R = Rz Rx Ry (default) or Rz Ry Rx, angles in radians."""
    ax, ay, az = angles_rad
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx if zyx else rz @ rx @ ry


def _versor(v: np.ndarray) -> np.ndarray:
    """Rotation of the unit quaternion with vector part v (w = sqrt(1 - |v|^2)); like ITK, a v of norm >= 1
    is scaled to a unit vector (w = 0, a half turn)."""
    norm = float(np.linalg.norm(v))
    if norm >= 1.0:
        v = v / norm
    x, y, z = v
    w = np.sqrt(max(0.0, 1.0 - float(v @ v)))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
