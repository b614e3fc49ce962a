"""Stage 4 (beyond the paper): hybrid 6-DOF refinement on image similarity with a landmark regulariser.

Three nearly collinear centroids fix the in-plane pose and the magnification, but hardly the rotations out of
the image plane; the whole image does. Starting at the landmark pose, CMA-ES maximises the gradient correlation
(GC, ``similarity.gc``) between the X-ray and DRRs of a medium mu level (default 3 mm) on a binned detector
(default ~2 mm pixels), inside the exposed field, while a small landmark term keeps the clicked centroids
where the surgeon put them::

    f(p) = (1 - GC(p)) + w_lm * mean_i (PDE_i(p) / s_click)^2 + w_rot * sum_k (theta_k / 10 deg)^2

with PDE in detector mm and ``s_click`` the expected clicking error (detector mm); without clicks the landmark
term is 0. Whole populations are rendered in one batch, and only over the exposed field (the metrics never
look outside it, so the scores are the same as from full DRRs). Bounded to +- ``bounds`` about the start, seeded
(repeatable).

The pipeline runs it twice: a wide coarse pass (``level_identify.coarse_refine_parameters``: 4 mm, large steps,
800 evaluations; it also scores each level labelling) and this module's default, a local pass at 3 mm on
~2 mm pixels. On 8 realistic simulated cases the median projection distance of the levels not clicked fell
from 2.5 mm (one local pass) to 1.4 mm (coarse + local, landmark weights 0.003 and 0.002).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.drr.cpu import render_line_integrals, row_spans
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
from carmreg.logic.geometry.projection_distance import pde_mm
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.image.prepare import bin_image_to, bin_mask_to, coarse_factor
from carmreg.logic.image.shading import shading_remover
from carmreg.logic.registration.cma_search import cma_strategy
from carmreg.logic.similarity.metrics import prepare


@dataclass
class RefineParameters:
    enabled: bool = True
    metric: str = "gc"
    mu_spacing_mm: float = 3.0
    detector_pixel_mm: float = 2.0
    popsize: int = 12
    max_evaluations: int = 360
    sigma: tuple = (4.0, 1.0, 1.0, 1.0, 1.5, 1.5)       # mm, deg
    bounds: tuple = (40.0, 10.0, 10.0, 6.0, 10.0, 10.0)  # +- about the start pose
    landmark_weight: float = 0.002
    click_sd_mm: float = 1.5
    rotation_weight: float = 0.002
    seed: int = 1
    without_shading_mm: float = 0.0   # > 0: GC of the X-ray and each DRR without their shading above this scale
    #                                   (``image.shading``; detector mm); 0: the images as they are


@dataclass
class RefineResult:
    pose: np.ndarray
    similarity_start: float
    similarity_end: float
    mpde_mm: float                      # clicked mPDE at ``pose`` (nan without clicks)
    evaluations: int
    convergence: list = field(default_factory=list)
    seconds: float = 0.0
    objective_end: float = float("nan")
    stopped_at: int | None = None       # evaluations after which ``give_up`` stopped it (None: ran in full)
    rejoined_at: int | None = None      # evaluations after which ``rejoined`` stopped it (None: it did not)
    equalised_similarity: float = float("nan")  # GC at ``pose`` on the equalised X-ray (``agreement``; nan: not
    #                                             measured)
    resume: object = field(default=None, repr=False, compare=False)  # stopped early: () -> the same search run to
    #                                             its end from where it stopped (``intensity_refine``); else None


@dataclass(frozen=True)
class RefineGrid:
    """Where a refinement compares DRRs with an image: the binned detector and that image and its exposed field
    binned onto it. Pixels (column, row), images indexed image[row, column]."""

    detector: CarmIntrinsics   # the binned detector (``CarmIntrinsics.binned``)
    image: np.ndarray          # (rows, cols) the image binned (``bin_image_to``)
    mask: np.ndarray           # (rows, cols) bool, the exposed field binned (``bin_mask_to``)
    spans: np.ndarray          # (rows, 2) the columns traced per row (``row_spans``: the field, grown one pixel)

    def line_integrals(self, level: MuLevel, geometry: CarmGeometry, poses: np.ndarray) -> np.ndarray:
        """DRR line integrals (n, rows, cols) of ``poses`` (n, 6) on this grid, traced over the field only (the
        metrics never look outside it, so the scores are the same as from full DRRs)."""
        return render_line_integrals(level, geometry, poses, self.detector, self.spans)


def refine_grid(intrinsics: CarmIntrinsics, params: RefineParameters, image: np.ndarray, mask: np.ndarray
                ) -> RefineGrid:
    """The grid of a refinement with ``params`` on the detector ``intrinsics``: binned by the factor that brings
    the pixel nearest ``params.detector_pixel_mm``; ``image`` and ``mask`` at full detector resolution."""
    factor = coarse_factor(intrinsics.pixel_spacing_mm, params.detector_pixel_mm)
    small = intrinsics.binned(factor)
    cols, rows = small.size_px
    binned_mask = bin_mask_to(mask, factor, (rows, cols))
    return RefineGrid(small, bin_image_to(image, factor, (rows, cols)), binned_mask, row_spans(binned_mask))


def _objective(level, geometry, grid: RefineGrid, poses, scores, points_lps_mm, uv_px, p: RefineParameters):
    """(f, similarity, clicked mPDE) of each pose; ``scores`` = ``metrics.prepare`` against the X-ray."""
    score = scores(grid.line_integrals(level, geometry, poses))
    rotation = np.sum((poses[:, 3:] / 10.0) ** 2, axis=1)
    if len(points_lps_mm) == 0:
        return (1.0 - score) + p.rotation_weight * rotation, score, np.full(len(poses), np.nan)
    P = geometry.projection_matrix(poses)
    pde = pde_mm(P, points_lps_mm, uv_px, geometry.intrinsics.pixel_spacing_mm)
    landmark = np.mean((pde / p.click_sd_mm) ** 2, axis=-1)
    return (1.0 - score) + p.landmark_weight * landmark + p.rotation_weight * rotation, score, pde.mean(axis=-1)


def penalty_bound(p: RefineParameters, start_pose: np.ndarray, n_clicks: int, max_mpde_mm: float) -> float:
    """The most the landmark and rotation terms of ``_objective`` can add at any pose a refinement with ``p`` from
    ``start_pose`` reaches (each rotation within ``start +- p.bounds``) where the clicks' mPDE is at most
    ``max_mpde_mm``::

        w_lm n (M / s_click)^2 + w_rot sum_k ((|theta_k| + b_k) / 10 deg)^2

    (the mean of n squared distances whose mean is at most M is at most n M^2, all of it on one click; ``theta`` the
    start's rotations, ``b`` their bounds). So at such a pose ``1 - similarity >= f - penalty_bound``."""
    rotations = np.abs(np.asarray(start_pose, float)[3:]) + np.asarray(p.bounds, float)[3:]
    landmark = p.landmark_weight * n_clicks * (max_mpde_mm / p.click_sd_mm) ** 2 if n_clicks else 0.0
    return float(landmark + p.rotation_weight * np.sum((rotations / 10.0) ** 2))


def grid_scores(p: RefineParameters, grid: RefineGrid):
    """``metrics.prepare`` (``p.metric``) against the grid's image, both sides without their shading when
    ``p.without_shading_mm`` asks (``image.shading``; the DRRs' shading in float32, deterministic and twice as fast).
    The scores in float64: rankings repeat bit for bit."""
    fixed, fmask, pixel_mm = grid.image, grid.mask, grid.detector.pixel_spacing_mm[0]
    if p.without_shading_mm <= 0:
        return prepare(p.metric, fixed, fmask, dtype=np.float64)
    remove = shading_remover(fmask, p.without_shading_mm / pixel_mm)
    inner = prepare(p.metric, remove(fixed), fmask, dtype=np.float64)
    return lambda drrs: inner(remove(np.asarray(drrs, np.float32)))


def intensity_refine(level: MuLevel, geometry: CarmGeometry, start_pose: np.ndarray, xray_line_integral: np.ndarray,
                     mask: np.ndarray, points_lps_mm: np.ndarray, uv_px: np.ndarray,
                     params: RefineParameters | None = None, should_stop=None, give_up=None, rejoined=None
                     ) -> RefineResult:
    """Refine ``start_pose`` on image similarity + landmarks; see module docstring. ``give_up(evaluations,
    best_objective) -> bool``, asked after each generation, stops the search early when True (``early_stop``;
    ``stopped_at`` records when). ``rejoined(best_objective, mean_pose, stds) -> bool``, asked after each
    generation with the search distribution's mean and standard deviations (pose units), stops it when True (a
    refit back where its labelling already is: ``early_stop.rejoins``; ``rejoined_at`` records when). A search so
    stopped can be run on to its end (``RefineResult.resume``; ``refinement_memo`` does, when the same refinement is
    asked for without stopping rules)."""
    p = params or RefineParameters()
    t0 = time.perf_counter()
    intr = geometry.intrinsics
    grid = refine_grid(intr, p, xray_line_integral, mask)
    x0 = np.asarray(start_pose, float).copy()
    es = cma_strategy(x0, p.sigma, p.bounds, p.popsize, p.max_evaluations, p.seed, tolx=1e-3)
    scores = grid_scores(p, grid)

    def objective(poses):
        return _objective(level, geometry, grid, poses, scores, points_lps_mm, uv_px, p)

    f0, s0, _ = objective(x0[None])
    best = [float(f0[0]), float(s0[0]), x0]
    convergence, spent, final = [], [time.perf_counter() - t0], []

    def search(give_up, rejoined) -> RefineResult:
        """Generations until the strategy stops or a stopping rule ends it; the result as it then stands."""
        t = time.perf_counter()
        stopped_at = rejoined_at = None
        while not es.stop():
            if should_stop is not None:
                should_stop()
            population = es.ask()
            f, s, _ = objective(population)
            es.tell(f)
            i = int(np.argmin(f))
            if f[i] < best[0]:
                best[:] = [float(f[i]), float(s[i]), population[i].copy()]
            convergence.append((es.countevals, best[0], best[1]))
            if give_up is not None and give_up(es.countevals, best[0]):
                stopped_at = int(es.countevals)
                break
            if rejoined is not None and rejoined(best[0], es.mean, es.stds):
                rejoined_at = int(es.countevals)
                break
        spent[0] += time.perf_counter() - t
        pose = np.array(best[2], float)
        mpde = float(pde_mm(geometry.projection_matrix(pose), points_lps_mm, uv_px, intr.pixel_spacing_mm).mean()) \
            if len(points_lps_mm) else float("nan")
        ended = stopped_at is not None or rejoined_at is not None
        return RefineResult(pose, float(s0[0]), best[1], mpde, es.countevals + 1, list(convergence), spent[0],
                            best[0], stopped_at, rejoined_at, resume=resume if ended else None)

    def resume() -> RefineResult:
        """The search run on from where a stopping rule ended it, without stopping rules, to its end: what a run
        without them returns, bit for bit (the same strategy state, random stream and best so far); asked again,
        the same result."""
        if not final:
            final.append(search(None, None))
        return final[0]

    return search(give_up, rejoined)
