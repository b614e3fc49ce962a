"""An uncalibrated image intensifier's pincushion, estimated from the image (beyond the paper).

An image intensifier stretches its image toward the rim (``geometry.distortion``: the outward shift ``s`` of an
image point 100 mm from the principal point, ``CarmIntrinsics.distortion_mm``). Without a calibration
(``--distortion-mm``) the pinhole pose absorbs part of it with a larger magnification, and the levels far from
the clicks land 1-2 mm off the true pose. Fitting ``s`` as a 7th parameter of one image refinement does not find
it (stop 23: -0.65 to +2.0 mm against true 2.5-4.6; the search trades ``s`` for magnification). Its profile does:
the local image refinement (``image_refine.intensity_refine``, the clicks taken to their ideal points through
``s``) run from the same start with ``s`` fixed at each of ``GRID_MM``; with f(s) its final objective (image
agreement, landmark and rotation terms)::

    f(s) ~ a s^2 + b s + c      (least squares over the grid)
    s* = -b / (2 a)             when a > 0, clipped to the grid's span; else no s* (the grid's best stands)

and the refinement at ``s*`` is run too. The refinement with the lowest objective of all is kept with its ``s``
(0 among them: an image the pincushion does not help keeps the pinhole), among those that keep the clicks fitted
(``acceptable``) when any does. A detector whose corners cannot take 6 mm in the model samples up to what they
take (``grid_for``). Seeded refinements from one start, so the profile is repeatable.

Chosen on 18 tune-half intensifier runs of the appearance benchmark (named clicks, 2.5-4.6 mm drawn): the median
distance of the levels not clicked from the true pose's projection 2.16 mm at 0, 0.94 mm so. Measured on report
halves 156-167 and 144-155 (README, stop 37): 1.61 -> 0.86 mm and 1.50 -> 1.02 mm (0.55 mm with the true ``s``
given). The estimate runs low (the profile is flat: a pinhole pose at a larger magnification scores nearly as
well), and on the independent cases, whose pincushion is weak, a shift won by a hair of objective now and then
moves the pose by the refinement's own noise (README). No margin of objective is asked of a shift: on the tune half
(72 intensifier runs, cases 132-166) every margin tried, absolute or against the refinement's seed-to-seed spread,
kept the levels further off (median 1.13 mm without one, 1.20-1.43 with one; stop 38,
``Testing/Benchmarks/pincushion_gain.py``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry
from carmreg.logic.registration.image_refine import RefineResult

GRID_MM = (0.0, 3.0, 6.0)
"""The shifts at 100 mm (mm) the profile is sampled at: 0 (a pinhole) to beyond an intensifier's usual 2-5 mm
(stop 37, tune half: 0-2-4-6 and 0-3-6 gave the same levels, 1.04 and 0.94 mm; the fewer refinements kept)."""
SAME_MM = 0.25
"""A vertex this close to a sampled shift is that shift (its refinement is not run again)."""


@dataclass
class PincushionEstimate:
    """The profile's samples and the refinement kept (module docstring)."""

    shift_mm: float                 # the kept refinement's shift at 100 mm (0: the pinhole kept)
    objectives: dict                # {shift mm: final objective of the refinement with it fixed}
    vertex_mm: float | None         # the fitted parabola's minimum (None: the profile is not convex)
    refine: RefineResult            # the kept refinement

    def note(self) -> str:
        """The estimate in words, for the warnings (it replaces ``UNCORRECTED_INTENSIFIER``)."""
        start = "the X-ray's field is round, as an image intensifier's, and no distortion calibration was given: "
        calibration = ("a calibration is more exact: --distortion-mm, or the window's C-arm geometry, Pincushion; "
                       "a pinhole camera: --distortion-mm 0, or untick 'Estimate an intensifier's pincushion'")
        if not self.shift_mm:
            return f"{start}no pincushion was found on the image ({calibration})"
        return (f"{start}its pincushion was estimated from the image, {self.shift_mm:.1f} mm at 100 mm from the "
                f"centre ({calibration})")

    def as_dict(self) -> dict:
        return {"shift_at_100_mm": self.shift_mm, "vertex_mm": self.vertex_mm,
                "objectives": {f"{s:g}": float(f) for s, f in sorted(self.objectives.items())}}


def profile_vertex(shifts_mm, objectives) -> float | None:
    """The least-squares parabola's minimum over the sampled ``shifts_mm``, clipped to their span; None when the
    parabola is not convex (module docstring)."""
    s, f = np.asarray(shifts_mm, float), np.asarray(objectives, float)
    a, b, _ = np.polyfit(s, f, 2)
    if not a > 0:
        return None
    return float(np.clip(-b / (2.0 * a), s.min(), s.max()))


def grid_for(max_shift_mm: float) -> tuple:
    """``GRID_MM`` scaled down to a detector that accepts at most ``max_shift_mm`` (``CarmIntrinsics.
    max_distortion_mm``: a large detector's corners limit the model; a 12-inch intensifier of 1024 x 0.3 mm takes
    4.2 mm), unchanged where it fits."""
    top = min(GRID_MM[-1], 0.999 * max_shift_mm)
    return tuple(s * top / GRID_MM[-1] for s in GRID_MM)


def estimate_pincushion(refine_at: Callable[[float], RefineResult], grid_mm=GRID_MM,
                        progress: Callable[[int, int], None] | None = None,
                        acceptable: Callable[[RefineResult], bool] | None = None) -> PincushionEstimate:
    """The pincushion's shift at 100 mm from the refinement profile (module docstring). ``refine_at(shift_mm)``
    runs the local refinement with the detector's distortion fixed at that shift; ``progress(done, total)`` is
    called before each; ``acceptable(refinement)``: whether its pose may be kept (the clicks still fitted): the
    lowest objective is taken among those, all of them when none is."""
    runs: dict = {}

    def run(shift: float) -> None:
        if progress is not None:
            progress(len(runs), len(grid_mm) + 1)
        runs[float(shift)] = refine_at(float(shift))

    for shift in grid_mm:
        run(shift)
    vertex = profile_vertex(list(runs), [r.objective_end for r in runs.values()])
    if vertex is not None and min(abs(vertex - s) for s in runs) >= SAME_MM:
        run(vertex)
    kept = [s for s in runs if acceptable is None or acceptable(runs[s])] or list(runs)
    best = min(kept, key=lambda s: runs[s].objective_end)
    return PincushionEstimate(best, {s: r.objective_end for s, r in runs.items()}, vertex, runs[best])


UNCORRECTED_INTENSIFIER = ("the X-ray's field is round, as an image intensifier's, and no distortion calibration was "
                           "given (--distortion-mm; in the window: C-arm geometry, Pincushion): its pincushion is not "
                           "corrected, so levels far from the clicks (or, without clicks, from the image centre) may "
                           "lie 1-2 mm further off than on a flat panel")
"""The warning on a round field with no distortion given, until the estimate replaces it with its note."""
FROM_IMAGE = "estimated from the image (round field, no calibration given): the local refinement's profile"
"""``CarmIntrinsics.sources["distortion_mm"]`` of a shift found here (``NONE_FOUND`` appended when it is 0)."""
NONE_FOUND = ": none found"


def with_shift(geometry: CarmGeometry, shift_mm: float) -> CarmGeometry:
    """``geometry`` whose detector has the pincushion ``shift_mm`` at 100 mm, about its principal point, its
    source ``FROM_IMAGE``."""
    intr = geometry.intrinsics
    source = FROM_IMAGE if shift_mm else FROM_IMAGE + NONE_FOUND
    return geometry.with_intrinsics(dataclasses.replace(intr, distortion_mm=float(shift_mm),
                                                        sources={**intr.sources, "distortion_mm": source}))
