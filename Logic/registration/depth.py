"""Stage 2: 1-DOF source-to-detector search on intervertebral distances (method paper Algorithm 3).

With (ty, tz) from stage 1b and no rotation, the C-arm is moved along its source->detector axis from a far
point toward the patient. For each tx the CT centroids are projected and the distances between consecutive
levels (cyclically, i -> i+1 mod N, as in the paper) are compared with those between the clicked X-ray
centroids::

    D(tx) = sum_i | |p_i - p_{i+1}| - |x_i - x_{i+1}| |      (detector mm)

The coarse scan uses ``step_mm`` (paper: 10 mm); the minimum is then refined by a bounded scalar search
(Brent) inside the neighbouring steps. The result fixes the magnification SDD / (source-to-isocentre depth).

Then (``recenter``, beyond the paper) the C-arm is translated parallel to the detector so that the mean
projected centroid meets the mean clicked centroid: a 2x2 Newton step on (ty, tz) with a finite-difference
Jacobian, twice. Distances between levels do not change with that shift, so D(tx) is kept while the
translation error the coarse 2 mm / 4 mm grid left behind goes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry, project


@dataclass
class DepthResult:
    tx_mm: float
    ty_mm: float
    tz_mm: float
    magnification: float
    cost_mm: float
    tx_scan_mm: np.ndarray
    cost_scan_mm: np.ndarray
    seconds: float


def _consecutive_lengths(uv: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """|x_i - x_{i+1 mod N}| in detector mm for (..., N, 2) pixel positions."""
    return np.linalg.norm((uv - np.roll(uv, -1, axis=-2)) * spacing, axis=-1)


def tx_limits(geometry: CarmGeometry, min_magnification: float = 1.05,
              max_magnification: float = 3.0) -> tuple[float, float]:
    """tx range keeping the isocentre magnification SDD / (SOD - tx) within the given C-arm range."""
    sdd, sod = geometry.intrinsics.sdd_mm, geometry.sod_mm
    return sod - sdd / min_magnification, sod - sdd / max_magnification


def depth_search(geometry: CarmGeometry, ty_mm: float, tz_mm: float, points_lps_mm: np.ndarray,
                 uv_px: np.ndarray, far_mm: float = 400.0, step_mm: float = 10.0,
                 recenter: bool = True, magnification_range: tuple = (1.05, 3.0)) -> DepthResult:
    """Scan tx from -far_mm toward the patient in ``step_mm`` steps, then refine; see module docstring."""
    from scipy.optimize import minimize_scalar  # here: 0.13 s to import, which a run without clicks never needs

    start = time.perf_counter()
    spacing = np.asarray(geometry.intrinsics.pixel_spacing_mm, float)
    target = _consecutive_lengths(np.asarray(uv_px, float), spacing)
    lo, hi = tx_limits(geometry, *magnification_range)
    lo = max(lo, -far_mm)
    scan = np.arange(lo, hi + 1e-9, step_mm)

    def cost(tx) -> np.ndarray:
        tx = np.atleast_1d(np.asarray(tx, float))
        poses = np.zeros((len(tx), 6))
        poses[:, 0], poses[:, 1], poses[:, 2] = tx, ty_mm, tz_mm
        uv = project(geometry.projection_matrix(poses), points_lps_mm)
        return np.abs(_consecutive_lengths(uv, spacing) - target).sum(axis=-1)

    costs = cost(scan)
    i = int(np.argmin(costs))
    bracket = (scan[max(i - 1, 0)], scan[min(i + 1, len(scan) - 1)])
    refined = minimize_scalar(lambda t: float(cost(t)[0]), bounds=bracket, method="bounded",
                              options={"xatol": 0.05})
    tx = float(refined.x) if refined.fun <= costs[i] else float(scan[i])
    pose = np.array([tx, ty_mm, tz_mm, 0.0, 0.0, 0.0])
    if recenter:
        pose = recenter_pose(geometry, pose, points_lps_mm, uv_px)
    return DepthResult(tx, float(pose[1]), float(pose[2]), float(geometry.magnification(pose)),
                       float(cost(tx)[0]), scan, costs, time.perf_counter() - start)


def recenter_pose(geometry: CarmGeometry, pose: np.ndarray, points_lps_mm: np.ndarray, uv_px: np.ndarray,
                  iterations: int = 2) -> np.ndarray:
    """Shift (ty, tz) so the mean projected point lands on the mean clicked point (Newton, numeric Jacobian)."""
    pose = np.asarray(pose, float).copy()
    target = np.asarray(uv_px, float).mean(axis=0)

    def mean_uv(p):
        return project(geometry.projection_matrix(p), points_lps_mm).mean(axis=0)

    for _ in range(iterations):
        base = mean_uv(pose)
        jac = np.empty((2, 2))
        for k, axis in enumerate((1, 2)):
            step = pose.copy()
            step[axis] += 1.0
            jac[:, k] = mean_uv(step) - base
        if abs(np.linalg.det(jac)) < 1e-9:
            break
        pose[1:3] += np.linalg.solve(jac, target - base)
    return pose
