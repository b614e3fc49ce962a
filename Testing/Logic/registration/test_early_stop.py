"""Stopping hopeless labelling refinements (``early_stop``): the allowance table, a stopped search being the full
one cut short, and the levels contest giving the verdict full refinements give; refits stopped once back at
their labelling's pose (``rejoins``)."""

import numpy as np
import pytest

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.camera import project
from carmreg.logic.registration.early_stop import (
    REJOIN_DISTANCE,
    REJOIN_GAIN,
    REJOIN_SPREAD,
    SAFETY,
    SLACK,
    STILL_TO_COME,
    allowance,
    cannot_lead,
    give_up_above,
    lower_bound,
    rejoins,
)
from carmreg.logic.registration.fine import FineParameters, FineResult
from carmreg.logic.registration.image_refine import (
    RefineParameters,
    RefineResult,
    _objective,
    intensity_refine,
    penalty_bound,
    refine_grid,
)
from carmreg.logic.registration.labelling_fit import (
    FitContext,
    LabellingFit,
    coarse_refine_parameters,
    refit_from,
)
from carmreg.logic.registration.levels import _rival_score, _settle
from carmreg.logic.similarity.metrics import prepare


def test_the_allowance_is_twice_the_largest_improvement_seen_after_that_many_evaluations_plus_the_slack():
    assert allowance(0) == allowance(319) == np.inf  # nothing stops before 320 evaluations
    assert allowance(320) == allowance(479) == pytest.approx(SAFETY * STILL_TO_COME[320] + SLACK)
    assert allowance(480) == pytest.approx(2 * 0.1076 + 0.05)
    assert allowance(800) == allowance(640) == pytest.approx(2 * 0.0406 + 0.05)
    give_up = give_up_above(0.30)
    assert not give_up(304, 5.0)  # far behind, but too early to tell
    assert give_up(640, 0.30 + allowance(640) + 1e-9) and not give_up(640, 0.30 + allowance(640) - 1e-9)
    assert lower_bound(0.9, None) == 0.9 and lower_bound(0.9, 480) == pytest.approx(0.9 - allowance(480))


def test_a_stopped_refinement_is_the_full_one_cut_short(tiny_db_inputs):
    level, geometry, intrinsics, _, _ = tiny_db_inputs
    truth = np.array([0.0, 2.0, -3.0, 0.0, 4.0, 0.0])
    image = render_line_integrals(level, geometry, truth)
    mask = np.ones(image.shape, bool)
    params = coarse_refine_parameters()
    start = truth + np.array([10.0, 3.0, 2.0, 2.0, -3.0, 2.0])
    full = intensity_refine(level, geometry, start, image, mask, np.zeros((0, 3)), np.zeros((0, 2)), params)
    cut = intensity_refine(level, geometry, start, image, mask, np.zeros((0, 3)), np.zeros((0, 2)), params,
                           give_up=lambda evaluations, best: evaluations >= 480)
    assert full.stopped_at is None and full.evaluations > 600
    assert cut.stopped_at == 480 and cut.evaluations == 481
    assert cut.convergence == full.convergence[:len(cut.convergence)]  # the same search, generation by generation
    assert cut.objective_end == cut.convergence[-1][1] >= full.objective_end


def _scored_fit(score: float, stopped_at: int | None) -> LabellingFit:
    """A labelling 'registered' with the given score, stopped after ``stopped_at`` evaluations or (None) in full; its
    landmark pose the tiny CT's centre."""
    fit = LabellingFit(["A"], 0, np.zeros((0, 3)), np.zeros((0, 2)), fine=FineResult(np.zeros(6), 0.0, 0.0, 0))
    fit.refine = RefineResult(np.zeros(6), 0.0, 0.0, float("nan"), 1, objective_end=score, stopped_at=stopped_at)
    return fit


def test_a_stopped_labelling_is_completed_only_when_it_could_still_end_ahead_of_the_reference_s_rival(
        tiny_db_inputs):
    level, geometry, _, _, _ = tiny_db_inputs
    image = render_line_integrals(level, geometry, np.zeros(6))
    ctx = FitContext(level, geometry, image, np.ones(image.shape, bool), 0.0, 0.0, FineParameters(),
                     coarse_refine_parameters())
    leader, rival = _scored_fit(0.2, None), _scored_fit(0.5, None)
    behind = _scored_fit(0.5 + allowance(640) + 0.01, 640)   # cannot end ahead of the rival: left as it is
    close = _scored_fit(0.5 + allowance(640) - 0.01, 640)    # could: registered in full
    fits = [leader, rival, behind, close]
    assert _rival_score(fits, None) == 0.5 and _rival_score(fits, 1) == 0.2  # names given: the best other
    _settle(ctx, fits, None)
    assert behind.stopped_at == 640 and behind.starts == 0
    assert close.stopped_at is None and close.starts == 1 and close.refine.evaluations > 640
    named = [_scored_fit(0.6, None), _scored_fit(0.2, None), _scored_fit(0.2 + allowance(480) - 0.01, 480)]
    _settle(ctx, named, 0)  # the names (0.6) are the reference, their rival the best other (0.2)
    assert named[2].stopped_at is None


def test_a_refit_has_rejoined_only_when_contracted_onto_the_labelling_s_pose_without_bettering_its_score():
    steps = np.array([20.0, 4.0, 4.0, 4.0, 5.0, 5.0])
    pose = np.array([10.0, 2.0, -3.0, 1.0, 0.0, 2.0])
    settled = rejoins(pose, 0.40, steps)
    near, tight = pose + 0.9 * REJOIN_DISTANCE * steps, 0.9 * REJOIN_SPREAD * steps
    assert settled(0.41, near, tight) and settled(0.40 - 0.9 * REJOIN_GAIN, near, tight)
    assert not settled(0.40 - 1.1 * REJOIN_GAIN, near, tight)       # it found better: let it finish
    wide = tight.copy()
    wide[4] = 1.1 * REJOIN_SPREAD * steps[4]
    assert not settled(0.41, near, wide)                             # one coordinate still searching
    away = near.copy()
    away[0] = pose[0] + 1.1 * REJOIN_DISTANCE * steps[0]
    assert not settled(0.41, away, tight)                            # contracted elsewhere: another basin


def _three_bars():
    """A 24^3 CT (4 mm voxels) of three bone bars along the three axes and a denser block, on a 24 x 24 px
    detector: small, and unlike a single bar, every pose parameter shows in its DRR (mu level, geometry)."""
    from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
    from carmreg.logic.geometry.volume import MuPyramid, Volume

    hu = np.full((24, 24, 24), -1000, np.int16)
    hu[8:12, 8:12, 2:22] = 1000
    hu[4:20, 14:17, 6:9] = 1000
    hu[14:17, 2:20, 15:18] = 1000
    hu[5:8, 5:8, 17:20] = 1500
    volume = Volume(hu, np.diag([4.0, 4.0, 4.0, 1.0]), "three bars")
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (4.0, 4.0), (24, 24)), tuple(volume.center_lps_mm()), 600.0)
    return MuPyramid(volume).level(None), geometry


def test_a_refit_from_a_tilted_pose_stops_once_back_at_the_registered_pose_and_the_better_refinement_is_kept():
    level, geometry = _three_bars()
    truth = np.array([0.0, 2.0, -3.0, 0.0, 4.0, 0.0])
    image = render_line_integrals(level, geometry, truth)
    ctx = FitContext(level, geometry, image, np.ones(image.shape, bool), 0.0, 0.0, FineParameters(),
                     coarse_refine_parameters())
    fit = LabellingFit([], 0, np.zeros((0, 3)), np.zeros((0, 2)))
    refit_from(ctx, fit, truth + np.array([10.0, 3.0, 2.0, 2.0, -3.0, 2.0]), stop_rejoined=True)
    assert fit.rejoined == [] and fit.refine.evaluations > 800  # its first registration: nothing to rejoin
    registered = fit.refine
    tilt = np.array([0.0, 0.0, 0.0, 0.0, 6.0, 0.0])
    full = refit_from(ctx, fit.copy(), fit.pose + tilt)          # the same refit, run to its end
    cut = refit_from(ctx, fit.copy(), fit.pose + tilt, stop_rejoined=True)
    assert full.rejoined == [] and len(cut.rejoined) == 1 and cut.rejoined[0] <= 700 < full.curves[-1][-1][0]
    assert cut.curves[-1] == full.curves[-1][:len(cut.curves[-1])]  # the same search, cut short
    assert cut.runs[-1] >= full.runs[-1] and cut.runs[-1] >= registered.objective_end - REJOIN_GAIN
    assert cut.refine is registered and cut.stopped_at is None    # still the registration, not "hopeless"
    elsewhere = refit_from(ctx, fit.copy(), fit.pose - tilt, stop_rejoined=True)  # settles in another basin
    assert elsewhere.rejoined == [] and elsewhere.curves[-1][-1][0] > 800 and elsewhere.runs[-1] > 0.01


def test_a_refinement_that_must_lead_by_a_margin_stops_once_its_similarity_cannot_get_there(tiny_db_inputs):
    """``cannot_lead`` and ``image_refine.penalty_bound``: at any pose inside a refinement's box where the clicks'
    mPDE is within the cap, ``1 - similarity >= f - penalty_bound``, so a refinement whose ``f`` cannot end below
    ``1 - (reference + margin) + penalty`` cannot end that far ahead of the reference."""
    level, geometry, _, _, _ = tiny_db_inputs
    p = RefineParameters(mu_spacing_mm=4.0, detector_pixel_mm=4.0)
    start = np.array([5.0, 2.0, -3.0, 4.0, -6.0, 2.0])
    bound = penalty_bound(p, start, 3, 4.0)
    rotations = (np.abs(start[3:]) + np.asarray(p.bounds[3:])) / 10.0
    assert bound == pytest.approx(p.landmark_weight * 3 * (4.0 / p.click_sd_mm) ** 2
                                  + p.rotation_weight * np.sum(rotations ** 2))
    assert penalty_bound(p, start, 0, 4.0) == pytest.approx(p.rotation_weight * np.sum(rotations ** 2))
    image = render_line_integrals(level, geometry, start)
    grid = refine_grid(geometry.intrinsics, p, image, np.ones(image.shape, bool))
    scores = prepare("gc", grid.image, grid.mask, dtype=np.float64)
    ijk = np.array([[8.0, 8.0, 5.0], [8.0, 8.0, 8.0], [8.0, 8.0, 11.0]])
    points = ijk @ level.ijk_to_lps[:3, :3].T + level.ijk_to_lps[:3, 3]
    uv = project(geometry.projection_matrix(start), points)
    rng = np.random.default_rng(3)
    poses = start + rng.uniform(-1.0, 1.0, (64, 6)) * np.asarray(p.bounds) * np.array([0.05, 0.1, 0.1, 1, 1, 1])
    f, similarity, mpde = _objective(level, geometry, grid, poses, scores, points, uv, p)
    inside = mpde <= 4.0
    assert inside.sum() >= 10 and np.all((1.0 - similarity - (f - bound))[inside] >= -1e-12)
    give_up = cannot_lead(0.40, 0.10, bound)
    assert give_up.bar == pytest.approx(1.0 - 0.50 + bound)
    assert give_up(480, give_up.bar + allowance(480) + 1e-9) and not give_up(480, give_up.bar + allowance(480) - 1e-9)
