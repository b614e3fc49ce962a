"""Stopping a labelling's coarse refinement once it can no longer matter (the levels contest's time).

Every plausible labelling of the clicks is registered by an 800-evaluation image refinement (``labelling_fit``),
most of a run's time. Many of them end far behind and were far behind long before their end. A
refinement's best objective ``obj(e)`` after ``e`` evaluations only falls, and it fell by at most ``STILL_TO_COME[e]``
after ``e`` on the appearance benchmark's tune half (stop 17's 140 recorded refinements of 20 runs,
``Testing/Benchmarks/results_refinement_curves_s17.json``; every start, the winners' included). A refinement is
stopped at the first generation where::

    obj(e) - allowance(e) > bar,      allowance(e) = SAFETY * STILL_TO_COME[e'] + SLACK

``e'`` the largest tabulated count <= e (the table only falls with e), ``bar`` the score of the reference's best
rival among the labellings registered in full so far (``levels._rival_score``: the reference is the surgeon's
names, else the best labelling; the rival is what the confidence rule compares it with, and its score only falls
as the contest goes on). Its final objective is then taken to be at least ``lower_bound = obj(e) -
allowance(e)``: it would have ended behind that rival, where it changes nothing.

The verdict must be the one full refinements give, so the contest never stops the surgeon's names nor the first
two registrations (no rival yet), nor any refitted leader, and ``levels._settle`` completes (in full: the same
seeded search run on from where it stopped, ``labelling_fit.complete``) every stopped labelling whose lower bound
does not clear the final rival. Then no stopped labelling can be the winner or the rival, and the margin and
checks are those of full refinements as long as no refinement improves by more than its allowance: twice the
largest improvement seen, plus ``SLACK``. Measured on the appearance benchmark's report half (README, stop 18):
the same verdicts, margins and checks in 240 of 240 runs, 4.4 % of the coarse evaluations saved.

A turned display's registrations
--------------------------------
With clicks and an unclear polarity, the polarity is judged again on the mirrored and upside-down displays
(``appearance_checks._polarity_on_display``); a display is taken only when its best registration leads the stored
image's best under the same polarity by ``REFUSE_ORIENTATION_AT_CLICKS_GC`` with the clicks within the rule's cap.
Each of its registrations stops once it cannot (``cannot_lead``: the bar in GC made a bar in objective with the
most its landmark and rotation terms can add there, ``image_refine.penalty_bound``). A display one of whose full
registrations does lead is judged again without stops, its stopped searches run on to their end
(``RefineResult.resume`` through ``refinement_memo``), so it is taken on full registrations only.

Refits back where they started
------------------------------
The levels contest then gives each of its leading two more starts (``levels``: from the other's pose, from its own
tilted about L, a fresh search from its own): each is asked for a better pose its labelling has not found, and the
better refinement is kept. Most find none and contract back onto the labelling's registered pose. A refit is
stopped once its search distribution has contracted there (``rejoins``)::

    stds_k <= REJOIN_SPREAD * s_k,   |mean_k - pose_k| <= REJOIN_DISTANCE * s_k   (every pose parameter k),
    best >= score - REJOIN_GAIN

with ``s`` the refinement's first steps (mm, degrees), ``pose`` and ``score`` the labelling's registration, ``mean``
and ``stds`` the CMA-ES distribution's, ``best`` the refit's best objective so far: what is left of it could only
polish the pose the labelling already has. A refit that has found better by more than ``REJOIN_GAIN`` runs to its
end, as does one contracting elsewhere; a labelling's first registration is never stopped so. What a stop forfeits
is the polish the rest of the search would have added. Chosen on the appearance benchmark's tune half 192-202
(stop 41: every refit run in full with its search recorded, 1440 refits of 180 clicked runs; spread and distance
0.1-0.3, gain 0-0.01 tried): the setting that saves most (33 % of the refits' evaluations, 906 refits stopped)
among those that forfeit at most 0.003 of a score; wider ones forfeit up to 0.008
(``Testing/Benchmarks/rejoin_traces.py --load Testing/Benchmarks/results_rejoin_traces_s41.json``).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

STILL_TO_COME = {320: 0.4151, 480: 0.1076, 640: 0.0406}
"""Largest improvement of a coarse refinement's best objective after e evaluations (tune half, stop 17; after 160
and 240 evaluations it was 2.66 and 1.51, beyond any objective's range, so no refinement stops before 320)."""
SAFETY = 2.0
SLACK = 0.05
_COUNTS = sorted(STILL_TO_COME)


def allowance(evaluations: int) -> float:
    """How much a refinement stopped after ``evaluations`` may still have improved (module docstring); inf before
    the first tabulated count."""
    k = bisect.bisect_right(_COUNTS, evaluations) - 1
    return float("inf") if k < 0 else SAFETY * STILL_TO_COME[_COUNTS[k]] + SLACK


@dataclass(frozen=True)
class GiveUpAbove:
    """``give_up(evaluations, best_objective) -> bool`` for ``image_refine.intensity_refine``: True once the
    refinement cannot come within its allowance of ``bar`` (inf: never). A value (hashable, equal when ``bar`` is):
    a refinement's stopping rule is part of what it is (``refinement_memo``)."""

    bar: float

    def __call__(self, evaluations: int, best: float) -> bool:
        return best - allowance(evaluations) > self.bar


def give_up_above(bar: float) -> GiveUpAbove:
    """The ``GiveUpAbove`` of ``bar``."""
    return GiveUpAbove(float(bar))


def cannot_lead(reference_gc: float, margin: float, penalty: float) -> GiveUpAbove:
    """A refinement that matters only if it ends with a similarity of at least ``reference_gc + margin`` at a pose
    where its landmark and rotation terms add at most ``penalty`` (``image_refine.penalty_bound``): there
    ``similarity = 1 - f + terms <= 1 - f + penalty``, and ``f`` ends at least ``best - allowance(e)``, so it is
    stopped once::

        best - allowance(e) > 1 - (reference_gc + margin) + penalty

    (``GiveUpAbove`` of that bar). Used where a turned display must lead the stored image by the refusal margin
    (``appearance_checks._polarity_on_display``)."""
    return give_up_above(1.0 - (reference_gc + margin) + penalty)


def lower_bound(score: float, stopped_at: int | None) -> float:
    """The least final objective a refinement stopped after ``stopped_at`` evaluations at ``score`` could have
    reached (``score`` itself when it ran in full: ``stopped_at`` None)."""
    return score if stopped_at is None else score - allowance(stopped_at)


REJOIN_SPREAD = 0.2
"""A refit has contracted once every coordinate's standard deviation is at most this fraction of its first step
(``RefineParameters.sigma``)."""
REJOIN_DISTANCE = 0.1
"""... and has come back once its mean lies within this fraction of the first steps of the labelling's pose."""
REJOIN_GAIN = 0.01
"""... without having bettered the labelling's score by more than this."""


@dataclass(frozen=True)
class Rejoins:
    """``rejoined(best_objective, mean_pose, stds) -> bool`` for ``image_refine.intensity_refine`` (``rejoins``); a
    value, as ``GiveUpAbove`` is. ``pose`` and ``steps`` as tuples of floats (pose order)."""

    pose: tuple
    score: float
    steps: tuple
    spread: float
    distance: float
    gain: float

    def __call__(self, best: float, mean: np.ndarray, stds: np.ndarray) -> bool:
        steps = np.asarray(self.steps, float)
        return bool(best >= self.score - self.gain and np.all(np.asarray(stds) <= self.spread * steps)
                    and np.all(np.abs(np.asarray(mean) - np.asarray(self.pose, float)) <= self.distance * steps))


def rejoins(pose, score: float, first_steps, spread: float = REJOIN_SPREAD, distance: float = REJOIN_DISTANCE,
            gain: float = REJOIN_GAIN) -> Rejoins:
    """``rejoined(best_objective, mean_pose, stds) -> bool`` for ``image_refine.intensity_refine``: True once a refit
    of a labelling registered at ``pose`` with ``score`` (another start: ``labelling_fit.refit_from``) has
    settled back in that registration's basin, where the rest of its search could only polish that pose::

        stds_k <= spread * s_k   and   |mean_k - pose_k| <= distance * s_k   for every k,   best >= score - gain

    ``s`` the refinement's first steps (``first_steps``; mm and degrees, pose order); ``spread``, ``distance``,
    ``gain`` the product's ``REJOIN_*`` unless a benchmark tries others (``rejoin_traces.py``). A refit is asked for
    the pose it might find elsewhere (a tilt, a rival's pose, a fresh search); one that has contracted onto the pose
    the labelling already has ends there (module docstring, stop 41's figures)."""
    return Rejoins(tuple(float(x) for x in np.ravel(pose)), float(score),
                   tuple(float(x) for x in np.ravel(first_steps)), float(spread), float(distance), float(gain))
