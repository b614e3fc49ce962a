"""Refinements asked again with the same inputs are recalled, not run again (``refinement_memo``): the labelling then
holds what a fresh run would have given it, and any input that differs - the image's content, the start pose, the
seed, a stopping rule's value - runs the refinement afresh."""

import dataclasses

import numpy as np
import pytest

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.registration import labelling_fit
from carmreg.logic.registration.early_stop import give_up_above, rejoins
from carmreg.logic.registration.fine import FineParameters
from carmreg.logic.registration.labelling_fit import (
    FitContext,
    LabellingFit,
    coarse_refine_parameters,
    refit_from,
    restart,
)
from carmreg.logic.registration.refinement_memo import RefinementMemo

TRUTH = np.array([0.0, 2.0, -3.0, 0.0, 4.0, 0.0])
START = TRUTH + np.array([10.0, 3.0, 2.0, 2.0, -3.0, 2.0])


@pytest.fixture
def counted(monkeypatch):
    """The number of image refinements actually run (``intensity_refine`` called), as a one-item list."""
    calls = [0]
    real = labelling_fit.intensity_refine

    def counting(*args, **kwargs):
        calls[0] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(labelling_fit, "intensity_refine", counting)
    return calls


def _context(tiny_db_inputs, memo):
    level, geometry, _, _, _ = tiny_db_inputs
    image = render_line_integrals(level, geometry, TRUTH)
    p = coarse_refine_parameters()
    p.max_evaluations = 160   # short: the test is about what runs, not how well
    return FitContext(level, geometry, image, np.ones(image.shape, bool), 0.0, 0.0, FineParameters(), p,
                      refinements=memo)


def _fit():
    return LabellingFit([], 0, np.zeros((0, 3)), np.zeros((0, 2)))


def test_the_same_refinement_asked_again_is_recalled_and_is_what_a_fresh_run_gives(tiny_db_inputs, counted):
    memo = RefinementMemo()
    ctx = _context(tiny_db_inputs, memo)
    first = refit_from(ctx, _fit(), START)
    again = refit_from(ctx, _fit(), START.copy())
    assert counted[0] == 1 and (memo.run, memo.recalled) == (1, 1)
    fresh = refit_from(_context(tiny_db_inputs, None), _fit(), START)   # no memo: run anew
    assert counted[0] == 2
    for fit in (again, fresh):
        assert np.array_equal(fit.refine.pose, first.refine.pose)
        assert fit.refine.objective_end == first.refine.objective_end
        assert fit.refine.convergence == first.refine.convergence and fit.runs == first.runs
    assert again.refine is not first.refine
    first.refine.equalised_similarity = 0.5     # annotated in place (``agreement``): not the recalled one's
    assert np.isnan(refit_from(ctx, _fit(), START).refine.equalised_similarity)


def test_an_image_or_mu_level_of_the_same_content_is_the_same_input_another_is_not(tiny_db_inputs, counted):
    memo = RefinementMemo()
    ctx = _context(tiny_db_inputs, memo)
    refit_from(ctx, _fit(), START)
    mirrored = ctx.xray_line_integral[:, ::-1]
    for image in (mirrored.copy(), mirrored.copy()):   # made anew, as the mirrored image is each time it is asked
        refit_from(dataclasses.replace(ctx, xray_line_integral=image), _fit(), START)
    assert counted[0] == 2 and memo.recalled == 1
    level = ctx.mu
    for mu in (level.mu_per_mm.copy(), level.mu_per_mm * np.float32(1.01)):  # a copy (a copied state's), another CT
        refit_from(dataclasses.replace(ctx, mu=dataclasses.replace(level, mu_per_mm=mu)), _fit(), START)
    assert counted[0] == 3 and memo.recalled == 2


def test_another_start_seed_or_stopping_rule_runs_afresh(tiny_db_inputs, counted):
    memo = RefinementMemo()
    ctx = _context(tiny_db_inputs, memo)
    fit = refit_from(ctx, _fit(), START)
    refit_from(ctx, _fit(), START + 1.0)                     # another start
    restart(ctx, _fit(), False)                               # another seed (from the nominal pose)
    restart(ctx, _fit(), False)                               # ... asked again
    assert counted[0] == 3
    for bar in (0.3, 0.4, 0.3):
        refit_from(ctx, _fit(), START, give_up=give_up_above(bar))
    assert counted[0] == 5                                    # 0.3 once, 0.4 once
    refit_from(ctx, fit.copy(), START - 1.0, stop_rejoined=True)   # rejoining the labelling at its pose and score
    refit_from(ctx, fit.copy(), START - 1.0, stop_rejoined=True)
    moved = fit.copy(refine=None)
    refit_from(ctx, moved, START + 2.0)
    refit_from(ctx, moved, START - 1.0, stop_rejoined=True)        # another pose to rejoin: another rule
    assert counted[0] == 8
    refit_from(ctx, _fit(), START, give_up=lambda evaluations, best: False)  # not a value: never recalled
    refit_from(ctx, _fit(), START, give_up=lambda evaluations, best: False)
    assert counted[0] == 10 and memo.run == 10 and memo.recalled == 3


def test_stopping_rules_are_values():
    assert give_up_above(0.3) == give_up_above(0.3) and hash(give_up_above(0.3)) == hash(give_up_above(0.3))
    assert give_up_above(0.3) != give_up_above(0.31)
    pose, steps = np.array([1.0, 2.0, 3.0, 0.0, 0.5, 0.0]), np.array([20.0, 4.0, 4.0, 4.0, 5.0, 5.0])
    assert rejoins(pose, 0.4, steps) == rejoins(pose.copy(), 0.4, tuple(steps))
    assert rejoins(pose, 0.4, steps) != rejoins(pose + 1e-9, 0.4, steps)


def test_a_refinement_its_rules_never_stopped_answers_the_same_one_asked_without_them(tiny_db_inputs, counted):
    """A refinement whose stopping rules never ended it ran as it would have without them: asked again without
    rules it is recalled. One a rule stopped, asked for without rules, is run on from where it stopped
    (``RefineResult.resume``): the same search to its end, bit for bit what a fresh run without rules gives."""
    memo = RefinementMemo()
    ctx = _context(tiny_db_inputs, memo)
    ruled = refit_from(ctx, _fit(), START, give_up=give_up_above(0.3))  # 160 evaluations: nothing stops before 320
    assert ruled.stopped_at is None
    plain = refit_from(ctx, _fit(), START)
    assert counted[0] == 1 and memo.recalled == 1 and np.array_equal(plain.refine.pose, ruled.refine.pose)
    longer = dataclasses.replace(ctx, refine=dataclasses.replace(ctx.refine, max_evaluations=400))
    stopped = refit_from(longer, _fit(), START, give_up=give_up_above(-5.0))  # hopeless from the first allowance
    assert stopped.stopped_at == 320 and stopped.refine.evaluations == 321
    full = refit_from(longer, _fit(), START)
    assert counted[0] == 2 and memo.resumed == 1 and full.stopped_at is None
    fresh = refit_from(dataclasses.replace(longer, refinements=None), _fit(), START)
    assert counted[0] == 3 and full.refine.evaluations == fresh.refine.evaluations > 321
    assert np.array_equal(full.refine.pose, fresh.refine.pose) and full.refine.convergence == fresh.refine.convergence
    assert (full.refine.objective_end, full.refine.similarity_end) == \
        (fresh.refine.objective_end, fresh.refine.similarity_end)
    assert memo.as_dict() == {"run": 2, "recalled": 1, "resumed": 1}
    assert refit_from(longer, _fit(), START).refine.convergence == fresh.refine.convergence  # now recalled
