"""Stage 3: 6-DOF CMA-ES on the mean projection distance error (method paper Algorithm 4), anchored.

Objective for a pose vector p = (tx, ty, tz, rx, ry, rz) (mm, degrees)::

    f(p) = mPDE(p) + w_rot * sum_k (theta_k / 1 deg)^2

mPDE in detector mm over the labelled pairs (Eq. 16). Three nearly collinear centroids do not determine
the rotations out of the image plane: an unconstrained fit reaches mPDE ~ 0 with a rotation tens of degrees off
and sends the other levels far away. CarmReg keeps the search anchored the way the paper does and more:
CMA-ES starts at the coarse pose with the paper's small steps (sigma 10 mm along source->detector, 3 elsewhere),
the search is bounded (``bounds``, relative to the coarse pose), and a Gaussian prior (``w_rot``) pulls the
rotations toward the nominal AP view the surgeon asked the radiographer for.
Population 50, at most 2000 evaluations, seeded: the same inputs give the same pose bit for bit.
Whole populations are evaluated at once (vectorised projection).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry
from carmreg.logic.geometry.projection_distance import mpde_mm
from carmreg.logic.registration.cma_search import cma_strategy


@dataclass
class FineParameters:
    popsize: int = 50
    max_evaluations: int = 2000
    sigma: tuple = (10.0, 3.0, 3.0, 3.0, 3.0, 3.0)    # initial step per parameter (mm, deg)
    bounds: tuple = (80.0, 30.0, 30.0, 15.0, 15.0, 15.0)  # +- around the coarse pose (mm, deg)
    rotation_weight_mm_per_deg2: float = 0.02
    seed: int = 1


@dataclass
class FineResult:
    pose: np.ndarray              # (6,)
    mpde_mm: float                # at the pose, without the prior
    objective: float
    evaluations: int
    convergence: list = field(default_factory=list)   # [(evaluations, mPDE mm at the best pose, best objective)]
    trajectory: list = field(default_factory=list)    # [(evaluations, mean pose (6,))]
    seconds: float = 0.0


def objective(geometry: CarmGeometry, poses: np.ndarray, points_lps_mm: np.ndarray, uv_px: np.ndarray,
              rotation_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """(objective, mPDE) for poses (m, 6)."""
    m = mpde_mm(geometry, poses, points_lps_mm, uv_px)
    return m + rotation_weight * np.sum(poses[:, 3:] ** 2, axis=1), m


def fine_search(geometry: CarmGeometry, start_pose: np.ndarray, points_lps_mm: np.ndarray, uv_px: np.ndarray,
                params: FineParameters | None = None, should_stop=None, pinned: tuple = ()) -> FineResult:
    """Run CMA-ES from ``start_pose``; ``should_stop()`` is polled each generation (cancel). ``pinned``: indices
    of pose parameters held at their start value (searched over the others only; e.g. ``(0,)`` fits the clicks
    with the source at a given depth tx)."""
    params = params or FineParameters()
    t0 = time.perf_counter()
    x0 = np.asarray(start_pose, float).copy()
    x0[3:] = np.clip(x0[3:], -params.bounds[3], params.bounds[3])
    free = np.array([k for k in range(6) if k not in pinned])
    es = cma_strategy(x0[free], np.asarray(params.sigma, float)[free], np.asarray(params.bounds, float)[free],
                      params.popsize, params.max_evaluations, params.seed, tolx=1e-4)

    def poses(searched: np.ndarray) -> np.ndarray:  # (m, len(free)) -> (m, 6), the pinned parameters as at x0
        out = np.repeat(x0[None], len(searched), axis=0)
        out[:, free] = searched
        return out

    best = (np.inf, np.inf, x0)
    result = FineResult(x0, np.inf, np.inf, 0)
    while not es.stop():
        if should_stop is not None:
            should_stop()
        population = poses(es.ask())
        f, m = objective(geometry, population, points_lps_mm, uv_px, params.rotation_weight_mm_per_deg2)
        es.tell(f)
        i = int(np.argmin(f))
        if f[i] < best[0]:
            best = (float(f[i]), float(m[i]), population[i].copy())
        result.convergence.append((es.countevals, best[1], best[0]))
        result.trajectory.append((es.countevals, poses(es.mean[None])[0]))
    result.objective, result.mpde_mm, result.pose = best
    result.evaluations = es.countevals
    result.seconds = time.perf_counter() - t0
    return result
