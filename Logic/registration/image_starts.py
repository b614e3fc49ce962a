"""Where the search on the image alone starts (no clicks): the best peaks of the spatial map, swept over the C-arm's
rotation in the image plane (beyond the paper).

The DRR database (``database``) holds poses without rotation. An X-ray taken with the C-arm turned about its beam
by a few degrees (pose rx; ``geometry.camera``) lays a long spine at an angle across every DRR of the grid, so the
map's value at the true (ty, tz) can be low and its best peaks elsewhere: on the appearance benchmark's second CT
(report case 5, rx -3.7 deg) the map at the true (ty, tz) was 0.05 against 0.23 at its best peak, the nearest
peak to the truth was the 7th, and with only the best 3 refined the right polarity never saw an aligned spine (its
refinements reached GC 0.38, where the true pose has 0.54) and lost to the wrong one (0.46).

So the coarse X-ray is turned in the image plane by each angle a of ``IN_PLANE_DEG`` (about the image centre:
``scipy.ndimage.rotate``, linear) and scored against every DRR by gradient correlation (the refinement's metric)
on one field for every turn, the pixels exposed whichever the turn (the field shrunk by 2 pixels, so that a turned
pixel interpolates exposed pixels only, turned by each a, nearest, and intersected; a field too small to keep a
pixel that way is scored without a turn)::

    S(ty, tz) = max_a  GC(turn_a(X), DRR(ty, tz)),       a*(ty, tz) = its argmax

One field makes the DRRs' half of GC the same for every turn (``metrics.gc_against_each``): the seven turns cost
about one GC map over the database (0.3 s for the chest CT's 7,650 DRRs here, against 4.7-6.4 s turn by turn).

The X-ray turned by a matching DRR(ty, tz) is the pose (ty, tz, rx = -a): the C-arm turns about its moved isocentre,
which lies on the principal ray, so the anatomy at the principal point stays put (``test_image_starts``). The starts
are the ``count`` best peaks of S (``spatial_peaks``, as grid cells), each with rx = -a* and no other rotation, at
the database's depth. The angles span the C-arm's in-plane rotation CarmReg expects (+- 10 deg, as the coarse
refinement's rx bound of 12 deg allows) in steps of 3 deg, within which the map holds its peak.
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.registration.database import DrrDatabase
from carmreg.logic.similarity.metrics import gc_against_each

IN_PLANE_DEG = (-9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0)


def spatial_peaks(score_map: np.ndarray, ty_mm: np.ndarray, tz_mm: np.ndarray, count: int,
                  min_separation_mm: float = 12.0) -> list[tuple[float, float]]:
    """The ``count`` best local maxima (ty, tz) of a spatial similarity map, at least ``min_separation_mm`` apart."""
    return [(float(ty_mm[iy]), float(tz_mm[iz]))
            for iy, iz in _peak_cells(score_map, ty_mm, tz_mm, count, min_separation_mm)]


def _peak_cells(score_map: np.ndarray, ty_mm: np.ndarray, tz_mm: np.ndarray, count: int,
                min_separation_mm: float = 12.0) -> list[tuple[int, int]]:
    """``spatial_peaks`` as grid cells (iy, iz) of ``score_map``."""
    from scipy import ndimage

    finite = np.where(np.isfinite(score_map), score_map, -np.inf)
    peaks = np.argwhere(finite == ndimage.maximum_filter(finite, size=3, mode="nearest"))
    peaks = sorted(peaks.tolist(), key=lambda ij: -finite[ij[0], ij[1]])
    out: list[tuple[int, int]] = []
    for iy, iz in peaks:
        if all(np.hypot(ty_mm[iy] - ty_mm[jy], tz_mm[iz] - tz_mm[jz]) >= min_separation_mm for jy, jz in out):
            out.append((iy, iz))
        if len(out) == count:
            break
    return out


def turned_maps(db: DrrDatabase, xray_coarse: np.ndarray, mask_coarse: np.ndarray, angles_deg=IN_PLANE_DEG
                ) -> tuple[np.ndarray, np.ndarray]:
    """(S, a*) of the module docstring, both (ny, nz): the best GC over the in-plane turns and the turn (degrees)
    that gave it. ``xray_coarse``/``mask_coarse``: the X-ray and its field on the database's detector."""
    from scipy import ndimage

    ny, nz, rows, cols = db.drrs.shape
    field = np.asarray(mask_coarse, bool)
    inner = ndimage.binary_erosion(field, iterations=2).astype(np.uint8)  # a turned pixel interpolates its
    common = field.copy()                                                  # neighbours: all of them exposed
    for a in angles_deg:
        if a:
            common &= ndimage.rotate(inner, a, reshape=False, order=0) > 0
    turned = np.stack([ndimage.rotate(xray_coarse, a, reshape=False, order=1) if a else xray_coarse
                       for a in angles_deg])
    drrs = db.drrs.reshape(ny * nz, rows, cols)
    scores = gc_against_each(turned, drrs, common)  # (ny nz, k)
    if not scores.any():  # a field too small to survive the turns: the map without a turn, on the whole field
        angles_deg, scores = (0.0,), gc_against_each(xray_coarse[None], drrs, field)
    best = scores.argmax(axis=1)
    return (scores[np.arange(len(scores)), best].reshape(ny, nz),
            np.asarray(angles_deg, float)[best].reshape(ny, nz))


def image_starts(db: DrrDatabase, xray_coarse: np.ndarray, mask_coarse: np.ndarray, count: int) -> list[np.ndarray]:
    """(6,) start poses (tx, ty, tz, rx, ry, rz) at the ``count`` best peaks of the turned maps (module
    docstring): the database's depth tx, rx = -a*, ry = rz = 0."""
    best, angle = turned_maps(db, xray_coarse, mask_coarse)
    return [np.array([db.tx_mm, float(db.ty_mm[iy]), float(db.tz_mm[iz]), 0.0 - angle[iy, iz], 0.0, 0.0])
            for iy, iz in _peak_cells(best, db.ty_mm, db.tz_mm, count)]  # 0.0 - a: never -0.0
