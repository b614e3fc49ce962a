"""The X-ray's polarity judged where the clicks put the CT (beyond the paper; ``image.appearance`` polarity).

The database's verdict (``appearance.database_gc``) compares the image with DRRs at poses without rotation
and at one depth. On a CT whose DRRs carry strong features of their own (a narrow, truncated reconstruction) a
correlation of the *wrong* sign at a wrong pose can beat the right sign at the nearest grid pose: measured on the
appearance benchmark's second CT, where the database said the opposite of the truth on every image-intensifier
variant while the DRR at the true pose correlated with the right sign (GC -0.42 bone dark, +0.49 bone bright).

With clicks, the CT can be put where they say first. The leading labellings of the contest (``ContestPlan.first``,
the most plausible first: unnamed clicks those the image agrees with most at their landmark pose,
``labelling_order``; named clicks: the names and one level up and down, so that a labelling one level off has
its true neighbour judged too) are registered under both polarities p, exactly as the levels stage registers a
labelling (``fit_labelling``: depth search, anchored landmark fit, wide image refinement with the landmark term)::

    score(p) = max_L GC_refined(L, p)
    fits(p)  = mPDE(L*, p) <= landmark_limit_mm(mPDE(L*, other polarity))   (L* the labelling of score(p))

that is, the clicks fit the winning registration within the confidence rule's cap and not clearly worse than the
same labelling registered under the other polarity (``level_confidence.landmark_limit_mm``): a wrong polarity
can buy GC by pulling the CT off the clicks (seen on a large patient where bone barely shows: 0.34 at 3.9 mm
against 0.21 at 0.5 mm for the right one, same labelling).

The image of the wrong polarity is the negative of the right one up to the storage map, so its refinement finds
no pose where the clicks and the image both agree. ``appearance.verdict_at_clicks`` says when the scores are clear;
unnamed clicks start with ``UNNAMED_LEADERS`` labellings and add the next most plausible one until the scores
are clear or ``MAX_UNNAMED_LEADERS`` were judged (the leading labellings can all be wrong ones: then the right
polarity has no aligned spine to show either, and the verdict stays unclear). When it is still unclear, the
labellings one level up and down from the leading registration (the highest GC under either polarity) are judged
too, once (``_neighbours_of_leader``): a labelling one level off shows much of the spine aligned, and its
neighbour is the likeliest right one (seen on a mirrored display judged on its mirror: T8-T10 led at GC 0.69 with
the clicks 4.3 mm off; T7-T9, the truth, then reached 0.91 at 1.4 mm; and on report case 143's intensifier
images, L4-S1 clicked unnamed, judged on L3-L5, L1-L3 and L2-L4 at GC 0.21-0.22 under either polarity with the
leader's clicks fitted, where L4-S1 reaches 0.69 under the right one). Until stop 35 only a leader off the clicks
had its neighbours judged. Not the other polarity's leader too: its neighbours can show the wrong polarity's
best registration keeping the clicks by chance (tried: tune case 88's intensifier image, T7-T9 clicked, then
took bone bright at GC 0.12 over bone dark's 0.60 off the clicks, and lost its confident right answer).

When the leader has no neighbour left to judge (both judged already, or beyond the CT) and neither polarity's best
registration keeps the clicks (``fits``, whatever its GC: a fit below ``FITTED_MIN_GC`` still counts here), unnamed
clicks have the next most plausible labelling judged instead, once (``_next_plausible``; stop 36): report case 149's
large patient, L4-S1 clicked, was judged on L3-L5, L2-L4 and L1-L3, neither polarity's best keeping the clicks, and
the leader L1-L3's other neighbour lies beyond the CT, so L4-S1 was never registered (wrong polarity, ambiguous).
Only then: tried first whenever the neighbours were exhausted, the extra labelling gave the wrong polarity a
registration that keeps the clicks - report case 101's large patient, bone bright, took bone dark *clearly* on L1-L3
(GC 0.51 with the clicks 3.8 mm off, within the landmark limit; named confidently wrong before the 0.35 check bound
of ``appearance_checks``), and tune case 102's flat panel (stated bone dark) lost its confident right answer to a
bone-bright T4-T6 at GC 0.16.

When the verdict stays unclear and the levels contest then finds a winner that was not among the leaders, the
pipeline registers that labelling too, under both polarities (``judged_also``), and takes the verdict only when
the image confirms the polarity in use by ``CLEAR_WITH_WINNER_GC`` (``confirms``; ``appearance_checks.with_winner``).
When the winner was among them but the contest found it a better pose than its registration here (``found_better``:
the contest's searches of its leaders, ``levels``), it is judged again from that pose under every polarity
(``judged_again_from``), with the same test: seen, report case 263's intensifier JPEG, L1-L3 clicked on an image
whose true pose is turned about every axis, judged at GC 0.17 bone dark and 0.07 bone bright (unclear); the contest's
wider turns found L1-L3 at GC 0.79 bone dark.
A labelling's landmark fit depends on the clicks only and is shared by its polarities.

The chosen polarity's registrations are the levels stage's own (same image, same mu level, same refinement), so
it reuses them (``identify_levels(registered=...)``): the check costs the other polarity's refinements only.
Frames and units as in ``labelling_fit``.
"""

from __future__ import annotations

from dataclasses import dataclass

from carmreg.logic.image.appearance import verdict_at_clicks
from carmreg.logic.registration.fine import FineResult
from carmreg.logic.registration.labelling_fit import (
    FitContext,
    LabellingFit,
    fit_labelling,
    landmark_fit,
    refit_from,
)
from carmreg.logic.registration.level_confidence import ConfidenceRule, landmark_limit_mm
from carmreg.logic.registration.levels import ContestPlan

CLEAR_WITH_WINNER_GC = 0.30  # the lead a verdict needs when it rests on the levels contest's winner too
# (``judged_also``), for the polarity and for the stored orientation alike: that labelling won on the image as
# stored and converted as the polarity in use, so the evidence leans toward both. Chosen on the appearance
# benchmark's tune half: right answers led by 0.60-0.87 (polarity) and 0.36-0.60 (orientation); a mirrored
# display's wrong polarity by 0.12, and mirrored displays judged at the clicks trailed their mirror by 0.25-0.31
UNNAMED_LEADERS = 2   # unnamed clicks: the most plausible labellings judged first under both polarities
MAX_UNNAMED_LEADERS = 3  # ... and at most (appearance benchmark: 64 of 78 unnamed runs were clear after 2, 3 more
#                          after 3, 2 more after 4-5 at ~2 s each; 9 never)


@dataclass
class ClickPolarity:
    """The polarity evidence at the clicks' poses."""

    scores: dict            # {polarity: max refined GC over the judged labellings}
    fits: dict              # {polarity: the clicks fit that best registration (module docstring)}
    registered: dict        # {polarity: [LabellingFit, registered under that polarity]}
    labels: list            # the labellings judged, as level names
    dark_storage: str       # how the bone-dark image was converted ("linear-intensity" | "log-display")

    def prefers_other(self, labels: list, polarity: str) -> bool:
        """Whether the judged labelling ``labels`` (level names) reached a higher GC under another polarity than
        under ``polarity`` (False: not judged under both)."""
        fits = {p: self._registered(p, labels) for p in self.registered}
        gc = {p: f.similarity if f is not None else float("nan") for p, f in fits.items()}
        mine = gc.get(polarity, float("nan"))
        return any(value > mine for p, value in gc.items() if p != polarity)

    def found_better(self, winner: LabellingFit, polarity: str) -> bool:
        """Whether the levels contest's ``winner`` (registered on the image as ``polarity``) is a judged labelling
        whose registration there scores better than its registration under ``polarity`` here."""
        judged = self._registered(polarity, winner.labels)
        return judged is not None and winner.score < judged.score

    def _registered(self, polarity: str, labels: list) -> LabellingFit | None:
        """The judged labelling ``labels`` as registered under ``polarity`` (None: not judged there)."""
        return next((f for f in self.registered.get(polarity, []) if f.names(labels)), None)

    def as_dict(self) -> dict:
        record = {"scores": dict(self.scores), "fits": dict(self.fits), "labellings": [list(lb) for lb in self.labels],
                  "dark_storage": self.dark_storage,
                  "similarity": {p: [f.similarity for f in fits] for p, fits in self.registered.items()},
                  "mpde_mm": {p: [f.mpde_mm for f in fits] for p, fits in self.registered.items()}}
        if self.stopped:
            record["stopped_at_evaluations"] = {p: [f.stopped_at for f in fits] for p, fits in self.registered.items()}
        return record

    @property
    def stopped(self) -> bool:
        """Whether any registration was stopped early (``early_stop``; its scores are then where it stopped)."""
        return any(f.stopped_at is not None for fits in self.registered.values() for f in fits)


def polarity_at_clicks(contexts: dict, plan: ContestPlan, dark_storage: str, rule: ConfidenceRule,
                       progress=None, give_up_for=None) -> ClickPolarity:
    """Register the leading labellings under each polarity until the scores are clear (module docstring).
    ``contexts``: {polarity: FitContext} whose images are the X-ray converted with that polarity (bone dark with
    ``dark_storage``), without a per-labelling hook (``progress`` reports instead); ``rule``: the level confidence
    rule, whose landmark limits say when the clicks fit; ``progress(done, total)`` is called before each
    registration; ``give_up_for(polarity, landmark_pose) -> give_up | None``: how each image refinement may stop
    early (``early_stop``; None: every one in full)."""
    leaders = list(plan.first) if plan.given_index is not None else list(plan.first[:MAX_UNNAMED_LEADERS])
    count = len(leaders) if plan.given_index is not None else min(UNNAMED_LEADERS, len(leaders))
    registered = {polarity: [] for polarity in contexts}
    landmark_fits = {}  # a labelling's landmark fit depends on the clicks only: one for both polarities
    widened = False  # the leaders widened once: the leader's neighbours, else the next most plausible
    while True:
        for polarity, ctx in contexts.items():
            for i in leaders[len(registered[polarity]):count]:
                if progress is not None:
                    progress(sum(len(f) for f in registered.values()), count * len(contexts))
                if i not in landmark_fits:
                    landmark_fits[i] = landmark_fit(ctx, plan.fits[i])
                give_up = give_up_for(polarity, landmark_fits[i].pose) if give_up_for is not None else None
                registered[polarity].append(registered_as_leader(ctx, plan.fits[i], landmark_fits[i], give_up))
        evidence = _evidence(registered, [plan.fits[i].labels for i in leaders[:count]], dark_storage, rule)
        if verdict_at_clicks(evidence.scores, evidence.fits)[2]:
            return evidence
        if count < len(leaders):
            count += 1
            continue
        more = [] if widened else _neighbours_of_leader(evidence, plan, leaders)
        if not more and not widened and not any(evidence.fits.values()):
            more = _next_plausible(plan, leaders)
        if not more:
            return evidence
        leaders, count, widened = leaders + more, len(leaders) + len(more), True


def _neighbours_of_leader(evidence: ClickPolarity, plan: ContestPlan, judged: list) -> list:
    """The plan's indices of the labellings one level up and down from the leading registration (the highest GC
    under either polarity) not judged yet (module docstring)."""
    polarity = max(evidence.scores, key=evidence.scores.get)
    leader = max(evidence.registered[polarity], key=lambda f: f.similarity)
    return [i for i in one_level_from(plan, {leader.shift}) if i not in judged]


def _next_plausible(plan: ContestPlan, judged: list) -> list:
    """The plan's index of the most plausible labelling not judged yet (``ContestPlan.first`` beyond the leaders),
    as a list of one or none (module docstring). Named clicks have none left: their leaders are all of ``first``."""
    return [i for i in plan.first if i not in judged][:1]


def one_level_from(plan: ContestPlan, shifts: set) -> list:
    """The plan's indices of the labellings one level up or down from any of ``shifts`` (``LabellingFit.shift``)."""
    return [i for i, f in enumerate(plan.fits) if any(abs(f.shift - s) == 1 for s in shifts)]


def judged_also(contexts: dict, evidence: ClickPolarity, planned: LabellingFit, rule: ConfidenceRule
                ) -> ClickPolarity:
    """``evidence`` with one more labelling registered under every polarity exactly as the leaders were (``planned``:
    ``plan_labelling`` on these contexts): the levels contest's winner when it was not among the leaders (the
    leaders, the most plausible, can all be wrong ones, and then neither polarity shows an aligned
    spine)."""
    registered = {polarity: list(fits) for polarity, fits in evidence.registered.items()}
    fine = landmark_fit(next(iter(contexts.values())), planned)
    for polarity, ctx in contexts.items():
        registered[polarity].append(registered_as_leader(ctx, planned, fine))
    return _evidence(registered, [*evidence.labels, list(planned.labels)], evidence.dark_storage, rule)


def judged_again_from(contexts: dict, evidence: ClickPolarity, winner: LabellingFit, rule: ConfidenceRule
                      ) -> ClickPolarity:
    """``evidence`` with the judged labelling of ``winner`` refitted under every polarity from the pose the levels
    contest found for it (``refit_from``: each polarity keeps its better registration; copies, the evidence given is
    left as it was)."""
    def again(polarity: str, fit: LabellingFit) -> LabellingFit:
        same = fit.names(winner.labels)
        return refit_from(contexts[polarity], fit.copy(), winner.pose.copy()) if same else fit

    registered = {polarity: [again(polarity, f) for f in fits] for polarity, fits in evidence.registered.items()}
    return _evidence(registered, evidence.labels, evidence.dark_storage, rule)


def confirms(evidence: ClickPolarity, polarity: str) -> bool:
    """Whether the evidence with the levels' winner (``judged_also``) confirms ``polarity``: the image's own
    verdict at the clicks (``verdict_at_clicks``: clicks fitted, GC floor) names it, by a lead of at least
    ``CLEAR_WITH_WINNER_GC``. Asked of the image itself, whatever the user or the file said."""
    seen, lead, clear = verdict_at_clicks(evidence.scores, evidence.fits)
    return bool(clear and seen == polarity and lead >= CLEAR_WITH_WINNER_GC)


def _evidence(registered: dict, labels: list, dark_storage: str, rule: ConfidenceRule) -> ClickPolarity:
    """score(p) and fits(p) of the module docstring; ``registered``: {polarity: fits, in the same labelling order}."""
    scores, fits = {}, {}
    for polarity, done in registered.items():
        k = max(range(len(done)), key=lambda i: done[i].similarity)
        rivals = [other[k].mpde_mm for p, other in registered.items() if p != polarity]
        limit = landmark_limit_mm(min(rivals) if rivals else float("nan"), rule)
        scores[polarity], fits[polarity] = done[k].similarity, bool(done[k].mpde_mm <= limit)
    return ClickPolarity(scores, fits, {p: list(f) for p, f in registered.items()}, labels, dark_storage)


def registered_as_leader(ctx: FitContext, planned: LabellingFit, fine: FineResult | None = None, give_up=None
                         ) -> LabellingFit:
    """``planned`` (``plan_labelling`` or a ``ContestPlan``'s, depth search only) registered on ``ctx`` as the
    leaders are (``fit_labelling`` from its landmark fit ``fine``, computed when None; ``give_up`` as there), as a
    new object."""
    fine = landmark_fit(ctx, planned) if fine is None else fine
    return fit_labelling(ctx, LabellingFit(list(planned.labels), planned.shift, planned.points_lps_mm,
                                           planned.uv_px, planned.depth, fine), give_up=give_up)

