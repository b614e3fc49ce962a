"""Rendering the moved anatomy exactly (``simulator`` step 2): ``L = DRR(mu_bg) + sum_k DRR(e_k moved by M_k)``
(line integrals, dimensionless), thick CT slices refined along their axis first, K-wires added, only the
detector window a vertebra can reach rendered for it.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.geometry.vertebrae import CARMREG_VERTEBRAE
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.jit import njit
from carmreg.logic.simulation.scene import Kwire, LevelMotion, kwire_path_lengths

# ----------------------------------------------------------------------------------------------- rendering

def add_kwire(line: np.ndarray, wire: Kwire, geometry: CarmGeometry, pose: CarmPose, mu_per_mm: float) -> None:
    """line += mu * (path length of every pixel ray inside the wire), only over the window the wire covers."""
    from carmreg.logic.geometry.camera import pixel_to_detector_lps

    rows, cols = line.shape
    uv = project(geometry.projection_matrix(pose), np.array([wire.tip_lps_mm, wire.end_lps_mm]))
    pad = 3 + wire.diameter_mm * float(np.max(geometry.magnification(pose, wire.end_lps_mm))) / min(
        geometry.intrinsics.pixel_spacing_mm)
    u_lo, v_lo = np.maximum(np.floor(uv.min(axis=0) - pad).astype(int), 0)
    u_hi, v_hi = np.minimum(np.ceil(uv.max(axis=0) + pad).astype(int) + 1, (cols, rows))
    if u_hi <= u_lo or v_hi <= v_lo:
        return
    vv, uu = np.mgrid[v_lo:v_hi, u_lo:u_hi]
    pixels = pixel_to_detector_lps(geometry, pose, np.stack([uu.ravel(), vv.ravel()], -1))
    chord = kwire_path_lengths(wire, geometry.source_lps_mm(pose), pixels)
    line[v_lo:v_hi, u_lo:u_hi] += (mu_per_mm * chord).reshape(vv.shape).astype(np.float32)


@njit(parallel=True)
def _refine_last_axis(src, f, out):
    """out[a, b, m] = linear interpolation of src[a, b, :] at x = (m + 0.5) / f - 0.5 (clamped)."""
    n0, n1, n = src.shape
    for i in numba.prange(n0):
        for j in range(n1):
            for m in range(n * f):
                x = min(max((m + 0.5) / f - 0.5, 0.0), n - 1.0)
                k = min(int(x), max(n - 2, 0))
                w = x - k
                out[i, j, m] = src[i, j, k] * (1.0 - w) + src[i, j, min(k + 1, n - 1)] * w


def refine_thick_slices(values: np.ndarray, ijk_to_lps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Refine every axis more than 1.5 x coarser than the finest one by f = ceil(s / s_min), linearly.

    New voxel n of a refined axis sits at old index x = (n + 0.5) / f - 0.5 (same physical box; clamped at
    the ends). Linear in ``values``, so refining the parts of a sum equals refining the sum. Removes the
    stair-steps of thick slices from the simulated image (the patient is continuous, the CT is not).
    """
    out, affine = np.asarray(values, np.float32), np.asarray(ijk_to_lps, float).copy()
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    for axis in range(3):
        f = int(np.ceil(spacing[axis] / spacing.min() - 1e-6))
        if spacing[axis] <= 1.5 * spacing.min() or f <= 1:
            continue
        src = np.ascontiguousarray(np.moveaxis(out, axis, 2))
        refined = np.empty(src.shape[:2] + (src.shape[2] * f,), np.float32)
        _refine_last_axis(src, f, refined)
        out = np.moveaxis(refined, 2, axis)
        origin_shift = np.zeros(3)
        origin_shift[axis] = 0.5 / f - 0.5
        affine[:3, 3] = affine[:3, :3] @ origin_shift + affine[:3, 3]
        affine[:3, axis] /= f
    return np.ascontiguousarray(out, dtype=np.float32), affine


def _prepared(values: np.ndarray, ijk_to_lps: np.ndarray, refine: bool) -> MuLevel:
    if refine:
        return MuLevel(*refine_thick_slices(values, ijk_to_lps), None)
    return MuLevel(np.ascontiguousarray(values, dtype=np.float32), ijk_to_lps, None)


def render_moved_anatomy(mu: np.ndarray, labels: np.ndarray | None, ijk_to_lps: np.ndarray,
                         motions: dict[str, LevelMotion], mu_soft: float, geometry: CarmGeometry,
                         pose: CarmPose, refine: bool = False) -> np.ndarray:
    """Line integrals of the CT with each labelled vertebra moved rigidly (module docstring, step 2).

    With ``refine`` every part goes through ``refine_thick_slices`` before rendering (exact additivity is
    kept because the refinement is linear).
    """
    values = {v: n for v, n in CARMREG_VERTEBRAE.items() if n in motions}
    if labels is None or not values:
        return render_line_integrals(_prepared(mu, ijk_to_lps, refine), geometry, pose)
    moving = np.isin(labels, list(values))
    background = np.where(moving, np.float32(mu_soft), mu).astype(np.float32)
    total = render_line_integrals(_prepared(background, ijk_to_lps, refine), geometry, pose)
    del background
    boxes = ndimage.find_objects(np.where(moving, labels, 0).astype(np.int32))
    for value, box in enumerate(boxes, start=1):
        if box is None:
            continue
        sl = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, n)) for s, n in zip(box, labels.shape,
                                                                                  strict=True))
        sub = np.where(labels[sl] == value, mu[sl] - np.float32(mu_soft), np.float32(0.0))
        shift = np.eye(4)
        shift[:3, 3] = [s.start for s in sl]
        level = _prepared(sub, ijk_to_lps @ shift, refine)
        level.ijk_to_lps = motions[values[value]].matrix @ level.ijk_to_lps
        _add_rendered_window(total, level, geometry, pose)
    return total


def detector_window(intr: CarmIntrinsics, u_start: int, v_start: int, cols: int, rows: int) -> CarmIntrinsics:
    """Intrinsics of the sub-image [v_start:v_start+rows, u_start:u_start+cols] of the detector (same rays).

    Built without validation on purpose: the principal point may lie outside a small window.
    """
    window = object.__new__(CarmIntrinsics)
    u0, v0 = intr.principal_point_px
    for name, value in (("sdd_mm", intr.sdd_mm), ("pixel_spacing_mm", tuple(intr.pixel_spacing_mm)),
                        ("size_px", (int(cols), int(rows))), ("principal_point_px", (u0 - u_start, v0 - v_start)),
                        ("sources", {})):
        object.__setattr__(window, name, value)
    return window


def _add_rendered_window(total: np.ndarray, level: MuLevel, geometry: CarmGeometry, pose: CarmPose) -> None:
    """total += DRR of ``level``, rendered only over the detector window its grid box projects into."""
    n = np.array(level.mu_per_mm.shape, float)
    corners = np.array([[a, b, c] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                        for c in (-0.5, n[2] - 0.5)])
    uv = project(geometry.projection_matrix(pose), corners @ level.ijk_to_lps[:3, :3].T + level.ijk_to_lps[:3, 3])
    rows, cols = total.shape
    u_lo, v_lo = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
    u_hi, v_hi = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, (cols, rows))
    if u_hi <= u_lo or v_hi <= v_lo:
        return
    window = detector_window(geometry.intrinsics, u_lo, v_lo, u_hi - u_lo, v_hi - v_lo)
    total[v_lo:v_hi, u_lo:u_hi] += render_line_integrals(level, geometry, pose, intrinsics=window)


def label_centers(labels: np.ndarray, ijk_to_lps: np.ndarray) -> dict[str, np.ndarray]:
    """Centre of mass (LPS mm) of every CarmReg-labelled vertebra present."""
    out = {}
    for value, box in enumerate(ndimage.find_objects(np.asarray(labels).astype(np.int32, copy=False)), start=1):
        if box is None or value not in CARMREG_VERTEBRAE:
            continue
        ijk = np.argwhere(labels[box] == value).mean(axis=0) + [s.start for s in box]
        out[CARMREG_VERTEBRAE[value]] = ijk_to_lps[:3, :3] @ ijk + ijk_to_lps[:3, 3]
    return out
