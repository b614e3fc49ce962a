"""Which vertebra is which: name the X-ray clicks, or check the surgeon's names, by registering every plausible
labelling and letting the image decide (beyond the paper; wrong-level surgery starts with a misnamed vertebra).

Hypotheses
----------
The clicks are put in spine order (``order_along_spine``). A *labelling* gives the k-th click in that order a CT
level name; clicks are taken to sit on consecutive vertebrae unless the surgeon named them.

- unnamed clicks: every run of n consecutive CT-labelled levels (T1-T3, T2-T4, ..., the ends included);
- named clicks (all or some): the labelling the names imply (unnamed clicks between named ones follow spine
  order) and that labelling shifted by +-1 ... +-``max_shift`` levels;
- no clicks: ``identify_from_image`` (coarse intensity stage, multi-start).

Scoring
-------
Each labelling is registered the way the pipeline does: depth search (Algorithm 3) from the spatial stage's
(ty, tz), anchored fine search (Algorithm 4), then a wide coarse image refinement (``intensity_refine`` at 4 mm:
gradient correlation with a landmark term). Its score is that refinement's objective (lower is better)::

    f = (1 - GC) + w_lm * mean_i (PDE_i / s_click)^2 + w_rot * sum_k (theta_k / 10 deg)^2

so a labelling wins by image similarity AND landmark fit. Registering every labelling would cost ~1 s each,
so they are taken in order of plausibility: unnamed clicks start with the ``candidates`` labellings whose click
spacing implies a source depth nearest the nominal C-arm's (intervertebral distances grow from head to
sacrum, so far-off labellings need an implausible magnification); named clicks start with the names and their
neighbours one level up and down. Then, until it holds, both neighbours of the best registered labelling are
registered too: the winner has always beaten the look-alike labellings next to it. Short refinements did NOT
rank labellings reliably (the right one often ranked last after 160 evaluations and first after 800).

Decision
--------
``margin`` = f(best other labelling) - f(reference), where the reference is the winner (unnamed clicks, no clicks)
or the surgeon's names (named clicks):

- margin >= ``margin``: **confident**;
- |margin| < ``margin``: **ambiguous** - the image cannot tell the levels apart (look-alike thoracic levels, few
  levels in view, transitional anatomy): check another view or name one distinctive level;
- margin <= -``margin`` (named clicks only): **contradicted** - the image fits another labelling better;
- no clicks: **proposed** instead of confident. The image alone has no clicks to anchor it: on 54 realistic
  simulated cases it named the levels right in 48, and 4 of the 6 misses had a clear margin (one was 4 levels
  off with the C-arm turned 15 deg about the beam). A proposal is a starting point, never a confirmation.

Every level a hypothesis names differs from the winner's (a shift renames every click), so the per-level margin
equals the labelling's margin.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.camera import CarmGeometry, project
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.io.landmarks import LEVEL_NAMES, Landmarks2D, Landmarks3D, level_index
from carmreg.logic.registration.depth import depth_search
from carmreg.logic.registration.fine import FineParameters, fine_search
from carmreg.logic.registration.image_refine import RefineParameters, intensity_refine


def coarse_refine_parameters() -> RefineParameters:
    """The wide coarse refinement (4 mm mu, ~4 mm detector pixels) that scores a labelling and seeds the fine one."""
    return RefineParameters(mu_spacing_mm=4.0, detector_pixel_mm=4.0, popsize=16, max_evaluations=800,
                            sigma=(20.0, 4.0, 4.0, 4.0, 5.0, 5.0), bounds=(80.0, 20.0, 20.0, 12.0, 15.0, 15.0),
                            landmark_weight=0.003, rotation_weight=0.002)


@dataclass
class IdentifyParameters:
    candidates: int = 5                     # unnamed clicks: labellings registered first (most plausible)
    max_shift: int = 2                      # named clicks: shifts tried each way
    margin: float = 0.02                    # objective difference between confident and ambiguous
    image_starts: int = 3                   # no clicks: spatial-map peaks refined


@dataclass
class Hypothesis:
    labels: list                            # CT level per click, clicks in spine order ([] without clicks)
    shift: int                              # levels relative to the reference labelling
    pose: np.ndarray                        # (6,) after its refinement
    score: float                            # refinement objective f (lower is better)
    similarity: float                       # GC at ``pose``
    mpde_mm: float                          # clicked mPDE at ``pose`` (detector mm; nan without clicks)
    refined: bool = False                   # registered and scored (False: only its depth search ran)
    fine_pose: np.ndarray | None = None     # landmark pose it started from

    def as_dict(self) -> dict:
        return {"labels": list(self.labels), "shift": self.shift, "score": self.score,
                "similarity": self.similarity, "mpde_mm": self.mpde_mm, "refined": self.refined,
                "pose": [float(x) for x in self.pose]}


@dataclass
class LevelIdentification:
    mode: str                               # named | partly_named | unnamed | image_only
    status: str                             # confident | ambiguous | contradicted | proposed (no clicks)
    margin: float
    order: list                             # indices into ``click_indices``, spine order
    winner: Hypothesis
    runner_up: Hypothesis | None
    given: Hypothesis | None                # the surgeon's names (named modes)
    hypotheses: list = field(default_factory=list)
    message: str = ""
    visible_labels: list = field(default_factory=list)  # image_only: levels in the exposed field at the winner
    click_indices: list = field(default_factory=list)   # the given clicks these labels name (see assigned_labels)

    @property
    def chosen(self) -> Hypothesis:
        """The labelling the registration continues with: the surgeon's names when given, else the winner."""
        return self.given if self.given is not None else self.winner

    def assigned_labels(self) -> list:
        """The name of each identified click (``click_indices``, in the order given) in the chosen labelling."""
        out = [""] * len(self.order)
        for k, i in enumerate(self.order):
            out[i] = self.chosen.labels[k]
        return out

    def as_dict(self) -> dict:
        ru = self.runner_up
        return {"mode": self.mode, "status": self.status, "margin": self.margin, "message": self.message,
                "assigned_labels": self.assigned_labels(), "click_indices": list(self.click_indices),
                "winner_labels": list(self.winner.labels),
                "runner_up_labels": list(ru.labels) if ru is not None else None,
                "visible_labels": list(self.visible_labels),
                "hypotheses": [h.as_dict() for h in self.hypotheses]}


@dataclass
class IdentifyContext:
    """What every hypothesis fit shares."""

    level: MuLevel                          # mu level of ``refine`` (its mu_spacing_mm)
    geometry: CarmGeometry
    xray_line_integral: np.ndarray
    mask: np.ndarray
    start_ty_mm: float                      # spatial stage's answer
    start_tz_mm: float
    fine: FineParameters                    # anchored landmark search (Algorithm 4)
    refine: RefineParameters                # the wide coarse image refinement that scores a labelling
    should_stop: object = None
    on_labelling: object = None             # optional progress hook, on_labelling(labels) before each fit


# ----------------------------------------------------------------------------------------------- labellings

def order_along_spine(uv_px: np.ndarray) -> np.ndarray:
    """Click indices head to sacrum: sorted along the clicks' principal axis, oriented so that the image row
    grows (rows run toward the patient's feet, CONVENTIONS.md). Ties keep the given order."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    if len(uv) < 2:
        return np.arange(len(uv))
    centred = uv - uv.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    if axis[1] < 0 or (axis[1] == 0 and axis[0] < 0):
        axis = -axis
    return np.argsort(centred @ axis, kind="stable")


def ct_level_names(ct: Landmarks3D) -> list[str]:
    """The CT's labelled levels, head to sacrum."""
    return sorted(ct.labels, key=level_index)


def shifted_labels(labels: list[str], shift: int, available: list[str] | set[str]) -> list[str] | None:
    """``labels`` moved ``shift`` places along the available levels (head to sacrum), or None if off the end."""
    available = set(available)
    names = [n for n in LEVEL_NAMES if n in available]
    if not all(lb in names for lb in labels):
        return None
    moved = [names.index(lb) + shift for lb in labels]
    return [names[i] for i in moved] if all(0 <= i < len(names) for i in moved) else None


def identifiable_clicks(clicks: Landmarks2D, ct_names: list[str]) -> list[int]:
    """Indices of the clicks the levels stage works with: unnamed ones, and named ones with a CT centroid
    (a named click without one is left out, as in pairing by name)."""
    return [i for i, lb in enumerate(clicks.labels) if lb is None or lb in ct_names]


def check_labelling_possible(clicks: Landmarks2D, ct_names: list[str]) -> None:
    """LandmarkError now, before any registration, when no labelling can satisfy the (partly named) clicks."""
    used = identifiable_clicks(clicks, ct_names)
    order = order_along_spine(np.asarray(clicks.uv_px, float)[used])
    candidate_labellings([clicks.labels[used[k]] for k in order], ct_names, 0)


def implied_labels(names_in_order: list, ct_names: list[str]) -> list[str]:
    """The full labelling implied by partly named clicks in spine order (unnamed clicks are consecutive levels
    between and around the named ones); LandmarkError when the names contradict the spine order."""
    starts = set()
    for k, name in enumerate(names_in_order):
        if name is None:
            continue
        if name not in ct_names:
            raise LandmarkError(f"the X-ray click named {name} has no CT centroid; label {name} in the CT or leave "
                                "the click unnamed")
        starts.add(ct_names.index(name) - k)
    if len(starts) != 1:
        raise LandmarkError("the named X-ray clicks do not fit consecutive vertebrae in spine order (top of the "
                            "image = head): check the names, or click every vertebra between them")
    s = starts.pop()
    if s < 0 or s + len(names_in_order) > len(ct_names):
        raise LandmarkError("with these names some unnamed clicks fall beyond the CT's labelled levels "
                            f"({ct_names[0]}-{ct_names[-1]}): label more levels in the CT or fewer clicks")
    return ct_names[s:s + len(names_in_order)]


def candidate_labellings(names_in_order: list, ct_names: list[str], max_shift: int
                         ) -> tuple[list[tuple[int, list[str]]], int | None, str]:
    """(shift, labels) for every hypothesis, the index of the surgeon's labelling (or None) and the mode."""
    n = len(names_in_order)
    named = [lb for lb in names_in_order if lb is not None]
    if not named:
        runs = [(s, ct_names[s:s + n]) for s in range(len(ct_names) - n + 1)]
        if not runs:
            raise LandmarkError(f"{n} clicks but only {len(ct_names)} CT-labelled levels: label at least as many "
                                "vertebrae in the CT as you click on the X-ray")
        return runs, None, "unnamed"
    if len(named) == n:
        given, mode = list(names_in_order), "named"
    else:
        given, mode = implied_labels(names_in_order, ct_names), "partly_named"
    out = []
    for shift in range(-max_shift, max_shift + 1):
        labels = given if shift == 0 else shifted_labels(given, shift, ct_names)
        if labels is not None:
            out.append((shift, labels))
    return out, [s for s, _ in out].index(0), mode


# ----------------------------------------------------------------------------------------------- fitting

def unregistered(ctx: IdentifyContext, points_lps_mm: np.ndarray, uv_px: np.ndarray, labels: list, shift: int
                 ) -> Hypothesis:
    """A labelling before its registration: the depth search's pose (Algorithm 3; its source depth says how
    plausible the magnification implied by the click spacing is); scores unknown."""
    depth = depth_search(ctx.geometry, ctx.start_ty_mm, ctx.start_tz_mm, points_lps_mm, uv_px)
    pose = np.array([depth.tx_mm, depth.ty_mm, depth.tz_mm, 0.0, 0.0, 0.0])
    return Hypothesis(list(labels), shift, pose, float("inf"), float("nan"), float("nan"), False, None)


def register_labelling(ctx: IdentifyContext, points_lps_mm: np.ndarray, uv_px: np.ndarray, h: Hypothesis
                       ) -> Hypothesis:
    """The labelling ``h`` (from ``unregistered``) registered: anchored fine search from its depth pose, then
    the wide image refinement, which scores it (module docstring)."""
    landmark = fine_search(ctx.geometry, h.pose, points_lps_mm, uv_px, ctx.fine, should_stop=ctx.should_stop)
    r = intensity_refine(ctx.level, ctx.geometry, landmark.pose, ctx.xray_line_integral, ctx.mask, points_lps_mm,
                         uv_px, ctx.refine, should_stop=ctx.should_stop)
    return Hypothesis(list(h.labels), h.shift, r.pose, r.objective_end, r.similarity_end, r.mpde_mm, True,
                      landmark.pose)


def _decide(hypotheses: list[Hypothesis], given: Hypothesis | None, margin: float
            ) -> tuple[str, float, Hypothesis, Hypothesis | None]:
    """(status, margin, winner, runner-up) over the fully refined hypotheses (module docstring)."""
    ranked = sorted((h for h in hypotheses if h.refined), key=lambda h: h.score)
    winner = ranked[0]
    reference = given if given is not None else winner
    others = [h for h in ranked if h is not reference]
    if not others:
        return "confident", float("inf"), winner, None
    d = others[0].score - reference.score
    runner_up = others[0] if reference is winner else winner
    status = "confident" if d >= margin else ("ambiguous" if d > -margin else "contradicted")
    return status, float(d), winner, runner_up


def _message(mode: str, status: str, chosen: Hypothesis, other: Hypothesis | None) -> str:
    names = ", ".join(chosen.labels) if chosen.labels else "the levels in view"
    alt = ", ".join(other.labels) if other is not None and other.labels else "a neighbouring labelling"
    if status == "confident":
        what = "agree with the image" if mode in ("named", "partly_named") else "identified by the image"
        return f"level names {names}: {what}"
    if status == "proposed":
        return (f"levels {names} PROPOSED from the image alone, without clicks (wrong in 6 of 54 simulated "
                "cases): confirm by clicking the centres of at least 3 vertebrae, named or not")
    if status == "ambiguous":
        return (f"level names AMBIGUOUS: the image fits {alt} about as well as {names}; check another view or "
                "name one distinctive level (last rib, thoracolumbar or lumbosacral junction)")
    return (f"level names CONTRADICTED: the image fits {alt} better than the names given ({names}); check the "
            "level names (another view, or name a distinctive level) before trusting this overlay")


def identify_levels(ctx: IdentifyContext, ct: Landmarks3D, clicks: Landmarks2D,
                    params: IdentifyParameters | None = None) -> LevelIdentification:
    """Name (or check the names of) the clicks: register the plausible labellings, decide (module docstring).
    Named clicks without a CT centroid are left out (as in pairing by name); ``click_indices`` says which
    clicks were identified."""
    p = params or IdentifyParameters()
    ct_names = ct_level_names(ct)
    used = identifiable_clicks(clicks, ct_names)
    order = order_along_spine(np.asarray(clicks.uv_px, float)[used])
    uv = np.asarray(clicks.uv_px, float)[used][order]
    names = [clicks.labels[used[k]] for k in order]
    ct_map = ct.as_dict()
    labellings, given_index, mode = candidate_labellings(names, ct_names, p.max_shift)
    hypotheses = [unregistered(ctx, np.array([ct_map[lb] for lb in labels]), uv, labels, shift)
                  for shift, labels in labellings]

    def refine(i: int) -> None:
        h = hypotheses[i]
        if not h.refined:
            if ctx.on_labelling is not None:
                ctx.on_labelling(list(h.labels))
            hypotheses[i] = register_labelling(ctx, np.array([ct_map[lb] for lb in h.labels]), uv, h)

    if given_index is None:  # the most plausible magnifications first (source depth nearest the nominal)
        first = np.argsort([abs(h.pose[0]) for h in hypotheses], kind="stable")[:p.candidates].tolist()
    else:
        first = [i for i in (given_index - 1, given_index, given_index + 1) if 0 <= i < len(hypotheses)]
    for i in first:
        refine(i)
    while True:  # the winner is always compared with both its neighbours, one level up and one down
        best = min((i for i, h in enumerate(hypotheses) if h.refined), key=lambda i: hypotheses[i].score)
        todo = [j for j in (best - 1, best + 1) if 0 <= j < len(hypotheses) and not hypotheses[j].refined]
        if not todo:
            break
        for j in todo:
            refine(j)
    given = hypotheses[given_index] if given_index is not None else None
    status, margin, winner, runner_up = _decide(hypotheses, given, p.margin)
    chosen = given if given is not None else winner
    message = _message(mode, status, chosen, runner_up)
    return LevelIdentification(mode, status, margin, order.tolist(), winner, runner_up, given, hypotheses, message,
                               click_indices=used)


# ----------------------------------------------------------------------------------------------- no clicks

def spatial_peaks(score_map: np.ndarray, ty_mm: np.ndarray, tz_mm: np.ndarray, count: int,
                  min_separation_mm: float = 12.0) -> list[tuple[float, float]]:
    """The ``count`` best local maxima (ty, tz) of a spatial similarity map, at least ``min_separation_mm`` apart."""
    from scipy import ndimage

    finite = np.where(np.isfinite(score_map), score_map, -np.inf)
    peaks = np.argwhere(finite == ndimage.maximum_filter(finite, size=3, mode="nearest"))
    peaks = sorted(peaks.tolist(), key=lambda ij: -finite[ij[0], ij[1]])
    out: list[tuple[float, float]] = []
    for iy, iz in peaks:
        ty, tz = float(ty_mm[iy]), float(tz_mm[iz])
        if all(np.hypot(ty - a, tz - b) >= min_separation_mm for a, b in out):
            out.append((ty, tz))
        if len(out) == count:
            break
    return out


def central_level(geometry: CarmGeometry, pose: np.ndarray, ct: Landmarks3D) -> str:
    """The CT level whose projection is nearest the principal point at ``pose``."""
    uv = project(geometry.projection_matrix(pose), ct.points_lps_mm)
    centre = np.asarray(geometry.intrinsics.principal_point_px, float)
    return ct.labels[int(np.argmin(np.linalg.norm(uv - centre, axis=1)))]


def visible_levels(geometry: CarmGeometry, pose: np.ndarray, ct: Landmarks3D, mask: np.ndarray) -> list[str]:
    """CT levels, head to sacrum, whose projection at ``pose`` falls inside the exposed field ``mask``."""
    uv = project(geometry.projection_matrix(pose), ct.points_lps_mm)
    rows, cols = mask.shape
    out = []
    for label, (u, v) in zip(ct.labels, uv, strict=True):
        iu, iv = int(round(u)), int(round(v))
        if 0 <= iu < cols and 0 <= iv < rows and mask[iv, iu]:
            out.append(label)
    return sorted(out, key=level_index)


def _level_step(ct: Landmarks3D, label: str, step: int) -> np.ndarray | None:
    """LPS mm vector from ``label``'s centroid to the one ``step`` levels caudal, or None off the end."""
    names = ct_level_names(ct)
    j = names.index(label) + step
    if not 0 <= j < len(names):
        return None
    m = ct.as_dict()
    return m[names[j]] - m[label]


def identify_from_image(ctx: IdentifyContext, ct: Landmarks3D, score_map: np.ndarray, ty_mm: np.ndarray,
                        tz_mm: np.ndarray, tx_mm: float, params: IdentifyParameters | None = None
                        ) -> LevelIdentification:
    """No clicks: refine from the best peaks of the spatial map on the image alone, then challenge the winner
    with its pose moved one level up and down along the spine (the look-alike neighbours); decide as above.
    A pose translation (tx, ty, tz) moves the isocentre by (P, L, S) = (tx, ty, tz) mm (camera.py)."""
    p = params or IdentifyParameters()
    empty_points, empty_uv = np.zeros((0, 3)), np.zeros((0, 2))  # no clicks: no landmark term

    def fit(start: np.ndarray, shift: int) -> Hypothesis:
        if ctx.on_labelling is not None:
            ctx.on_labelling([])
        r = intensity_refine(ctx.level, ctx.geometry, start, ctx.xray_line_integral, ctx.mask, empty_points,
                             empty_uv, ctx.refine, should_stop=ctx.should_stop)
        return Hypothesis([], shift, r.pose, r.objective_end, r.similarity_end, float("nan"), True, start)

    starts = [np.array([tx_mm, ty, tz, 0.0, 0.0, 0.0]) for ty, tz in
              spatial_peaks(score_map, ty_mm, tz_mm, p.image_starts)]
    hypotheses = [fit(s, 0) for s in starts]
    challenged: set[str] = set()
    while True:  # challenge the best with its pose one level up and down, until the best has been challenged
        best = min(hypotheses, key=lambda h: h.score)
        centre = central_level(ctx.geometry, best.pose, ct)
        if centre in challenged or len(challenged) >= 3:
            break
        challenged.add(centre)
        for step in (-1, 1):
            delta = _level_step(ct, centre, step)
            if delta is not None:
                start = best.pose.copy()
                start[:3] += (delta[1], delta[0], delta[2])
                hypotheses.append(fit(start, step))
    for h in hypotheses:
        h.labels = [central_level(ctx.geometry, h.pose, ct)]
    distinct = {}
    for h in sorted(hypotheses, key=lambda h: h.score):
        distinct.setdefault(h.labels[0], h)
    ranked = list(distinct.values())
    winner = ranked[0]
    runner_up = ranked[1] if len(ranked) > 1 else None
    margin = float(runner_up.score - winner.score) if runner_up is not None else float("inf")
    status = "proposed" if margin >= p.margin else "ambiguous"
    visible = visible_levels(ctx.geometry, winner.pose, ct, ctx.mask)
    chosen = replace(winner, labels=visible)
    message = _message("image_only", status, chosen, runner_up)
    return LevelIdentification("image_only", status, margin, [], winner, runner_up, None, hypotheses, message,
                               visible)
