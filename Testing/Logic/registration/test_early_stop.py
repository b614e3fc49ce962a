"""Stopping hopeless labelling refinements (``early_stop``): the allowance table, a stopped search being the full
one cut short, and the levels contest giving the verdict full refinements give."""

import numpy as np
import pytest

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.registration.early_stop import SAFETY, SLACK, STILL_TO_COME, allowance, give_up_above, lower_bound
from carmreg.logic.registration.fine import FineParameters, FineResult
from carmreg.logic.registration.image_refine import RefineResult, intensity_refine
from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit, coarse_refine_parameters
from carmreg.logic.registration.levels import _rival_score, _settle


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
