"""One labelling of the X-ray clicks, registered: the unit of the method (``fit_labelling``).

A labelling pairs each click (spine order) with a CT centroid. It is registered the way the pipeline registers
named clicks: depth search (Algorithm 3) from the spatial stage's (ty, tz), anchored fine search (Algorithm 4),
then a wide coarse image refinement (``image_refine`` at 4 mm: gradient correlation with a landmark term). Its
score is that refinement's objective (lower is better)::

    f = (1 - GC) + w_lm * mean_i (PDE_i / s_click)^2 + w_rot * sum_k (theta_k / 10 deg)^2

so a labelling wins by image similarity AND landmark fit. ``refit_from`` gives a labelling another start (a
rival labelling's refined pose: one level away along the spine, with that rival's rotations), keeping the better
of the two refinements, so that a labelling never loses a contest to its optimiser stopping in a local optimum.

The pipeline adopts the chosen labelling's fit (its depth, fine and coarse image refinement) instead of
computing them again. Frames and units: poses are the 6 C-arm parameters (mm, degrees; ``geometry.camera``),
points LPS mm, clicks (column, row) px, PDE detector mm.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.image.turn import ORIENTATIONS, orient_uv, turned_intrinsics
from carmreg.logic.registration.depth import DepthResult, depth_search, recenter_pose
from carmreg.logic.registration.early_stop import rejoins
from carmreg.logic.registration.fine import FineParameters, FineResult, fine_search
from carmreg.logic.registration.image_refine import RefineParameters, RefineResult, intensity_refine
from carmreg.logic.registration.labellings import order_along_spine
from carmreg.logic.registration.refinement_memo import RefinementMemo

if TYPE_CHECKING:  # labelling_order builds on this module
    from carmreg.logic.registration.labelling_order import LabellingOrders


def coarse_refine_parameters() -> RefineParameters:
    """The wide coarse refinement (4 mm mu, ~4 mm detector pixels) that scores a labelling and seeds the fine one."""
    return RefineParameters(mu_spacing_mm=4.0, detector_pixel_mm=4.0, popsize=16, max_evaluations=800,
                            sigma=(20.0, 4.0, 4.0, 4.0, 5.0, 5.0), bounds=(80.0, 20.0, 20.0, 12.0, 15.0, 15.0),
                            landmark_weight=0.003, rotation_weight=0.002)


@dataclass
class FitContext:
    """What every labelling's fit shares."""

    mu: MuLevel                             # mu level of ``refine`` (its mu_spacing_mm)
    geometry: CarmGeometry
    xray_line_integral: np.ndarray          # (rows, cols) attenuation-like X-ray
    mask: np.ndarray                        # (rows, cols) exposed field
    start_ty_mm: float                      # the spatial stage's answer
    start_tz_mm: float
    fine: FineParameters                    # anchored landmark search (Algorithm 4)
    refine: RefineParameters                # the wide coarse image refinement that scores a labelling
    magnification_range: tuple = (1.05, 3.0)  # the depth search's C-arm range (Algorithm 3)
    depth_far_mm: float = 400.0
    depth_step_mm: float = 10.0
    should_stop: object = None
    on_labelling: object = None             # optional progress hook, on_labelling(labels) before each fit
    xray_equalised: np.ndarray | None = None  # (rows, cols) the X-ray's rank image (``agreement``; None: not used)
    refinements: RefinementMemo | None = None  # the registration's refinements run so far (None: none recalled)
    labelling_orders: LabellingOrders | None = None  # unnamed clicks' labellings' order, one per registration
    #                                         (None: computed each time; ``labelling_order.unnamed_order``)


@dataclass
class LabellingFit:
    """A labelling and, once registered, its fit. ``score`` is inf until ``refine`` ran."""

    labels: list                            # CT level per click, clicks in spine order ([] without clicks)
    shift: int                              # levels relative to the reference labelling
    points_lps_mm: np.ndarray               # (n, 3) the labels' CT centroids
    uv_px: np.ndarray                       # (n, 2) the clicks, spine order
    depth: DepthResult | None = None
    fine: FineResult | None = None
    refine: RefineResult | None = None      # the best of its image refinements
    starts: int = 0                         # image refinements run (starts)
    runs: list = field(default_factory=list)  # objective of each start
    curves: list = field(default_factory=list)  # per start: [(evaluations, best objective)] after each generation
    rejoined: list = field(default_factory=list)  # evaluations after which each refit stopped back at its pose

    @property
    def refined(self) -> bool:
        return self.refine is not None

    @property
    def pose(self) -> np.ndarray:
        """(6,) the refined pose, else the landmark pose, else the depth search's."""
        if self.refine is not None:
            return np.asarray(self.refine.pose, float)
        if self.fine is not None:
            return np.asarray(self.fine.pose, float)
        d = self.depth
        return np.array([d.tx_mm, d.ty_mm, d.tz_mm, 0.0, 0.0, 0.0]) if d is not None else np.zeros(6)

    @property
    def stopped_at(self) -> int | None:
        """Evaluations after which its kept refinement was stopped as hopeless (``early_stop``); None: in full."""
        return self.refine.stopped_at if self.refine is not None else None

    @property
    def score(self) -> float:
        return float(self.refine.objective_end) if self.refine is not None else float("inf")

    @property
    def similarity(self) -> float:
        return float(self.refine.similarity_end) if self.refine is not None else float("nan")

    @property
    def agreement(self) -> float:
        """The image agreement the confidence rule judges (``agreement``): the better of ``similarity`` and the GC
        on the equalised X-ray at the same pose, when that was measured."""
        equalised = self.refine.equalised_similarity if self.refine is not None else float("nan")
        return float(max(self.similarity, equalised)) if np.isfinite(equalised) else self.similarity

    @property
    def mpde_mm(self) -> float:
        return float(self.refine.mpde_mm) if self.refine is not None else float("nan")

    def names(self, labels) -> bool:
        """Whether this is the labelling ``labels`` (level names, clicks in spine order; any sequence)."""
        return list(self.labels) == list(labels)

    def copy(self, **changes) -> LabellingFit:
        """A copy whose later starts do not touch this one's record (``runs``, ``curves``, ``rejoined``), with
        ``changes``."""
        return dataclasses.replace(self, runs=list(self.runs), curves=list(self.curves), rejoined=list(self.rejoined),
                                   **changes)

    def as_dict(self) -> dict:
        """For result.json; ``start_curves``: each start's best objective after each CMA-ES generation, from which
        one can read whether a labelling was still improving when its search ended (a fair contest)."""
        return {"labels": list(self.labels), "shift": self.shift, "score": self.score,
                "similarity": self.similarity, "agreement": self.agreement, "mpde_mm": self.mpde_mm,
                "refined": self.refined,
                "starts": self.starts, "start_scores": [float(x) for x in self.runs],
                "stopped_at_evaluations": self.stopped_at,
                "rejoined_at_evaluations": list(self.rejoined),
                "start_curves": [{"evaluations": [e for e, _ in curve], "objective": [round(f, 6) for _, f in curve]}
                                 for curve in self.curves],
                "pose": [float(x) for x in self.pose]}


def plan_labelling(ctx: FitContext, labels: list, shift: int, points_lps_mm: np.ndarray, uv_px: np.ndarray
                   ) -> LabellingFit:
    """A labelling before its image registration: only its depth search (Algorithm 3), whose source depth says
    how plausible the magnification implied by the click spacing is."""
    depth = depth_search(ctx.geometry, ctx.start_ty_mm, ctx.start_tz_mm, points_lps_mm, uv_px, ctx.depth_far_mm,
                         ctx.depth_step_mm, magnification_range=ctx.magnification_range)
    return LabellingFit(list(labels), shift, np.asarray(points_lps_mm, float), np.asarray(uv_px, float), depth)


def oriented_geometry(geometry: CarmGeometry, name: str) -> CarmGeometry:
    """The C-arm geometry of the image turned by ``turn.ORIENTATIONS[name]`` (``turn.turned_intrinsics``: its
    size, pixel spacing and principal point turned with it, its radial distortion the same; the source and the
    detector plane unchanged)."""
    return geometry.with_intrinsics(turned_intrinsics(geometry.intrinsics, name))


def oriented_context(ctx: FitContext, name: str) -> FitContext:
    """``ctx`` on orientation ``name`` of its X-ray (``ORIENTATIONS``): the attenuation image, the field and the
    geometry turned together."""
    orient = ORIENTATIONS[name]
    return dataclasses.replace(ctx, geometry=oriented_geometry(ctx.geometry, name),
                               xray_line_integral=np.ascontiguousarray(orient(ctx.xray_line_integral)),
                               mask=np.ascontiguousarray(orient(ctx.mask)))


def turned_labelling(ctx: FitContext, fit: LabellingFit, name: str, size_px: tuple[int, int],
                     names_follow_clicks: bool) -> LabellingFit:
    """``fit``'s labelling planned (``plan_labelling``) on orientation ``name`` of the image (``ctx``: an
    ``oriented_context``; ``size_px`` = (columns, rows) of the image as stored), its clicks turned with it
    (``turn.orient_uv``). Names the user gave stay with their clicks (they are anatomy); unnamed clicks get the
    labelling's names head to sacrum along the turned image, as any labelling of unnamed clicks is made."""
    uv = orient_uv(fit.uv_px, name, size_px)
    if not names_follow_clicks:
        uv = uv[order_along_spine(uv)]
    return plan_labelling(ctx, fit.labels, fit.shift, fit.points_lps_mm, uv)


def fit_labelling(ctx: FitContext, fit: LabellingFit, landmark_gate_mm: float = np.inf, give_up=None
                  ) -> LabellingFit:
    """Register ``fit`` (from ``plan_labelling``) in full: anchored fine search from its depth pose (unless
    ``fit.fine`` is already there: ``landmark_fit``), then the wide image refinement that scores it (module
    docstring). Returns the same object, filled. A labelling whose
    landmark fit leaves the clicks' mPDE above ``landmark_gate_mm`` is not refined (``refined`` stays False):
    the fine search minimises that mPDE, and the image refinement only trades it for image agreement.
    ``give_up``: stops the image refinement early (``early_stop``; ``complete`` runs it in full later)."""
    if ctx.on_labelling is not None:
        ctx.on_labelling(list(fit.labels))
    if fit.fine is None:
        fit.fine = landmark_fit(ctx, fit)
    if fit.fine.mpde_mm > landmark_gate_mm:
        return fit
    return _refine_from(ctx, fit, fit.fine.pose, give_up)


def complete(ctx: FitContext, fit: LabellingFit) -> LabellingFit:
    """A labelling whose kept refinement was stopped early (``stopped_at``), refined in full: the same seeded search
    from the same pose, run to its end, replaces it (the stopped start stays in the record: ``runs``, ``curves``).
    With a ``refinement_memo`` the stopped search is run on from where it stopped, not again from its start."""
    fit.refine = None
    return fit_labelling(ctx, fit)


def landmark_fit(ctx: FitContext, fit: LabellingFit, start_pose: np.ndarray | None = None, pinned: tuple = ()
                 ) -> FineResult:
    """The anchored landmark fit (Algorithm 4) of a planned labelling, from its depth pose (or ``start_pose``, with
    the pose parameters ``pinned`` held there: ``fine_search``). It depends on the clicks, the labels, the geometry
    and ``ctx.fine`` only, not on the image: registrations of one labelling on two conversions of the image (the
    polarities) share it."""
    start = fit.pose if start_pose is None else start_pose
    return fine_search(ctx.geometry, start, fit.points_lps_mm, fit.uv_px, ctx.fine, ctx.should_stop, pinned)


def refit_from(ctx: FitContext, fit: LabellingFit, start_pose: np.ndarray, stop_rejoined: bool = False,
               give_up=None) -> LabellingFit:
    """Another start of the image refinement for a labelling; the better refinement is kept. ``stop_rejoined``:
    stopped once it has settled back where the registered labelling already is (``early_stop.rejoins``);
    ``give_up``: stopped once hopeless (``early_stop.give_up_above``; a refit stopped so is not kept, it ends behind
    the refinement the labelling has)."""
    if ctx.on_labelling is not None:
        ctx.on_labelling(list(fit.labels))
    settled = rejoins(fit.pose, fit.score, ctx.refine.sigma) if stop_rejoined and fit.refined else None
    return _refine_from(ctx, fit, np.asarray(start_pose, float), give_up=give_up, rejoined=settled)


def nominal_depth_start(ctx: FitContext, fit: LabellingFit) -> np.ndarray:
    """(6,) the clicks' landmark fit with the source at the nominal depth: the anchored fine search (Algorithm 4)
    from the labelling's landmark pose moved to tx = 0 and re-centred on the clicks (``depth.recenter_pose``), tx
    held there (``landmark_fit(pinned=(0,))``). The depth search reads the magnification from the clicks' spacing,
    which a view tilted against the spine's curvature foreshortens: three upper thoracic clicks under a view turned
    9 deg put the source 130 mm too far (chest scene 317), beyond the image refinement's reach (+-80 mm). At the
    nominal depth (the anatomy at the isocentre, where the radiographer centres it) the clicks ask for the tilt
    instead, and the image refinement from there found the true pose."""
    start = fit.pose if fit.fine is None else np.asarray(fit.fine.pose, float)
    start = recenter_pose(ctx.geometry, np.array([0.0, *start[1:]]), fit.points_lps_mm, fit.uv_px)
    return landmark_fit(ctx, fit, start, pinned=(0,)).pose


def refit_at_nominal_depth(ctx: FitContext, fit: LabellingFit) -> LabellingFit:
    """A registered labelling refined once more from ``nominal_depth_start``; the better refinement is kept
    (``refit_from``, stopped once it settles back at the labelling's pose)."""
    return refit_from(ctx, fit, nominal_depth_start(ctx, fit), stop_rejoined=True)


def restart(ctx: FitContext, fit: LabellingFit, stop_rejoined: bool = False) -> LabellingFit:
    """A fresh image refinement of a registered labelling from its own refined pose: the refinement's full step
    sizes and the next seed (another random stream), so it can leave the basin its earlier search settled in; the
    better refinement is kept (``stop_rejoined`` as for ``refit_from``)."""
    fresh = dataclasses.replace(ctx, refine=dataclasses.replace(ctx.refine, seed=ctx.refine.seed + 1))
    return refit_from(fresh, fit, fit.pose.copy(), stop_rejoined)


def state_context(state, line_integral: np.ndarray, ty_mm: float, tz_mm: float, should_stop,
                  on_labelling=None) -> FitContext:
    """What every labelling's registration on ``line_integral`` shares, from a ``RegistrationState``: its pyramid's
    mu level of the coarse refinement, geometry, field and parameters; the spatial stage's (ty, tz) mm."""
    p = state.parameters
    return FitContext(state.pyramid.level(p.refine_coarse.mu_spacing_mm), state.geometry, line_integral,
                      state.mask, ty_mm, tz_mm, p.fine, p.refine_coarse, p.magnification_range,
                      p.depth_far_mm, p.depth_step_mm, should_stop, on_labelling, refinements=state.refinements,
                      labelling_orders=state.labelling_orders)


def unshaded_context(ctx: FitContext, without_shading_mm: float) -> FitContext:
    """``ctx`` whose image refinements compare the X-ray and each DRR without their shading above
    ``without_shading_mm`` (``RefineParameters.without_shading_mm``, ``image.shading``)."""
    return dataclasses.replace(ctx, refine=dataclasses.replace(ctx.refine, without_shading_mm=without_shading_mm))


def unlabelled_fit(ctx: FitContext, start_pose: np.ndarray, shift: int = 0) -> LabellingFit:
    """One image refinement without clicks (no landmark term) from ``start_pose``: a hypothesis of the image alone."""
    return refit_from(ctx, LabellingFit([], shift, np.zeros((0, 3)), np.zeros((0, 2))), start_pose)


def _refine_from(ctx: FitContext, fit: LabellingFit, start_pose: np.ndarray, give_up=None, rejoined=None
                 ) -> LabellingFit:
    """One image refinement of ``fit`` from ``start_pose`` (recalled from ``ctx.refinements`` when the same one ran
    before: ``refinement_memo``), recorded as a start and kept when it betters the labelling's."""
    inputs = (ctx.mu, ctx.geometry, start_pose, ctx.xray_line_integral, ctx.mask, fit.points_lps_mm, fit.uv_px,
              ctx.refine)
    stops = {"give_up": give_up, "rejoined": rejoined}

    def run() -> RefineResult:
        return intensity_refine(*inputs, should_stop=ctx.should_stop, **stops)

    memo = ctx.refinements
    r = run() if memo is None else memo.result(memo.key(*inputs, **stops), run)
    fit.starts += 1
    if r.rejoined_at is not None:
        fit.rejoined.append(r.rejoined_at)
    fit.runs.append(float(r.objective_end))
    fit.curves.append([(int(evaluations), float(best)) for evaluations, best, _ in r.convergence])
    if fit.refine is None or r.objective_end < fit.refine.objective_end:
        fit.refine = r
    return fit
