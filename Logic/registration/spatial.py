"""Stage 1b: 2-DOF spatial search of the DRR database (method paper Algorithm 2).

Every database DRR (poses (tx0, ty, tz, 0, 0, 0)) is compared with the coarse X-ray (binned to the same
detector, attenuation-like, exposed field only) by each metric of ``similarity.METRICS``. Each metric's
similarity map S[iy, iz] gives its own best (ty, tz); the chosen metric's best is the stage's answer.
When CT-X-ray landmark pairs are known, the mPDE of each metric's answer is reported (the paper's
"minimum mPDE" check), but it never steers the answer: the intensity stage stays independent of the clicks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.registration.database import DrrDatabase
from carmreg.logic.similarity.metrics import METRICS, similarity


@dataclass
class SpatialResult:
    metric: str
    ty_mm: float
    tz_mm: float
    maps: dict = field(default_factory=dict)          # metric -> (ny, nz) similarity
    best_by_metric: dict = field(default_factory=dict)  # metric -> (ty_mm, tz_mm)
    seconds_by_metric: dict = field(default_factory=dict)
    seconds: float = 0.0


def spatial_search(db: DrrDatabase, xray_coarse: np.ndarray, mask_coarse: np.ndarray, metric: str = "gc",
                   metrics: tuple[str, ...] = METRICS, known: dict | None = None) -> SpatialResult:
    """Score all DRRs with ``metric`` and each of ``metrics``; the best (ty, tz) of ``metric`` and every map.
    ``known``: {metric: (n,) scores} already computed for this very X-ray (not computed again)."""
    start = time.perf_counter()
    ny, nz, rows, cols = db.drrs.shape
    if xray_coarse.shape != (rows, cols):
        raise ValueError(f"coarse X-ray {xray_coarse.shape} does not match database DRRs {(rows, cols)}")
    flat = db.drrs.reshape(ny * nz, rows, cols)
    result = SpatialResult(metric, 0.0, 0.0)
    for name in dict.fromkeys((metric, *metrics)):
        t0 = time.perf_counter()
        scores = (known[name] if known and name in known else similarity(name, xray_coarse, flat, mask_coarse)
                  ).reshape(ny, nz)
        result.seconds_by_metric[name] = time.perf_counter() - t0
        iy, iz = np.unravel_index(int(np.argmax(scores)), scores.shape)
        result.maps[name] = scores
        result.best_by_metric[name] = (float(db.ty_mm[iy]), float(db.tz_mm[iz]))
    result.ty_mm, result.tz_mm = result.best_by_metric[metric]
    result.seconds = time.perf_counter() - start
    return result
