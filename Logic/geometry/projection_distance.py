"""Projection distance error (method paper Eq. 16), measured on the detector in mm.

``PDE_i = | (u, v)_projected,i - (u, v)_xray,i |`` with the pixel difference scaled by the pixel spacing
(du, dv) so that it is in detector millimetres; ``mPDE = mean_i PDE_i``. Vectorised over poses.
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry, project


def pde_mm(P: np.ndarray, points_lps_mm: np.ndarray, uv_px: np.ndarray,
           pixel_spacing_mm: tuple[float, float]) -> np.ndarray:
    """Per-point PDE in detector mm: (n,) for P (3, 4) or (m, n) for a batch (m, 3, 4)."""
    diff = (project(P, points_lps_mm) - np.asarray(uv_px, float)) * np.asarray(pixel_spacing_mm, float)
    return np.linalg.norm(diff, axis=-1)


def mpde_mm(geometry: CarmGeometry, poses: np.ndarray, points_lps_mm: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """mPDE in detector mm for pose vectors (6,) -> scalar or (m, 6) -> (m,)."""
    P = geometry.projection_matrix(np.asarray(poses, float))
    return pde_mm(P, points_lps_mm, uv_px, geometry.intrinsics.pixel_spacing_mm).mean(axis=-1)
