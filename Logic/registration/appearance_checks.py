"""The X-ray's appearance decided against the CT: polarity, storage and orientation (the spatial stage's first step).

``AppearanceChecks.decide`` is every check, in order, on the state after the database stage; each check below
runs only when the verdict before it left the question open (for the second opinions, or settled it by a small
lead) and the user did not set the polarity:

1. the database's gradient correlation under each storage and polarity (``image.appearance.database_gc``);
2. with clicks, the leading labellings registered under both polarities (``click_polarity``), else the spatial
   map's peaks refined on the image alone under both (``image_polarity``); ``decide_polarity`` takes the verdict;
3. the display's orientation from the database (``orientation_scores``) and, with clicks and a clear polarity,
   at the clicks (``click_orientation``);
4. with clicks, a second opinion without the image's shading (``_polarity_at_clicks_without_shading``; asked of a
   clear verdict by less than ``CHECKED_CLICKS_GC`` too), then the image mirrored left-right and, with unnamed
   clicks, upside down (``_polarity_on_displays``; without the shading too when the second opinion is clear): a
   display so shown is refused; then a clear verdict the second opinion did not confirm has the display judged
   under the other polarity too (``_orientation_under_other_polarity``);
5. without clicks, the image mirrored left-right, and flipped, turned 180 degrees or (square detectors) turned a
   quarter where the database could not rule that out under either polarity (``_orientation_without_clicks``; a
   display so shown is refused), then a second opinion without the image's shading (``_polarity_without_shading``),
   and the displays judged after it when it left a clear verdict unclear;
6. the warnings on the appearance.

``with_winner`` is the levels stage's ``judge_appearance``: the contest's winner judged at the clicks too. When the
polarity stayed unclear at the clicks and the contest's winner, not judged there (or judged there and agreeing
better under the other polarity than under the one those judgements chose), explains the image poorly, the
levels stage runs the contest again under the other polarity (``worth_other_polarity``,
``contest_under_other_polarity``) and takes it only when its winner, judged at the clicks too, confirms that
polarity; it asks this first of the contest's leader before the searches for confidence, which then run only when
the other polarity's contest is not taken (``CarmRegLogic._levels_at_clicks``). Neither that contest nor the
searches for confidence run when no labelling, winning, could make the appearance trusted (``trust_within_reach``).
The appearance in use (``state.appearance``) always comes with the X-ray's attenuation image converted by it
(``_use_appearance``). Every number and rule is the README's rule item 5 and ``image.appearance``'s thresholds;
this module only orders the checks and keeps their evidence in ``appearance.scores``.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
from collections.abc import Callable

import numpy as np

from carmreg.logic.image.appearance import (
    CHECKED_CLICKS_GC,
    CHECKED_REFINED_GC,
    ON_TURNED_AT_CLICKS,
    POLARITIES,
    REFINED_AT_CLICKS,
    REFINED_AT_CLICKS_WITHOUT_SHADING,
    REFINED_AT_DATABASE_POSES,
    REFINED_WITHOUT_SHADING,
    REFUSE_ORIENTATION_AT_CLICKS_GC,
    WITHOUT_SHADING_MM,
    Appearance,
    dark_storage,
    database_gc,
    database_orientation,
    decide_polarity,
    displayed_without_clicks,
    orientation_scores,
    refined_on_at_clicks,
    refined_on_without_clicks,
    stated_storage,
)
from carmreg.logic.image.prepare import attenuation, bin_image_to, bin_mask_to
from carmreg.logic.image.shading import shading_remover
from carmreg.logic.image.turn import QUARTER_TURNED, turned_clicks
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.registration.click_orientation import (
    MIRROR,
    close_call,
    displayed_under_other_polarity,
    orientation_at_clicks,
    rival_orientations,
    stored_against_turned,
)
from carmreg.logic.registration.click_polarity import (
    CLEAR_WITH_WINNER_GC,
    ClickPolarity,
    confirms,
    judged_again_from,
    judged_also,
    one_level_from,
    polarity_at_clicks,
    registered_as_leader,
)
from carmreg.logic.registration.early_stop import cannot_lead
from carmreg.logic.registration.image_polarity import ImagePolarity, polarity_from_image
from carmreg.logic.registration.image_refine import penalty_bound
from carmreg.logic.registration.image_starts import image_starts
from carmreg.logic.registration.labelling_fit import (
    FitContext,
    LabellingFit,
    oriented_context,
    plan_labelling,
    state_context,
    unshaded_context,
)
from carmreg.logic.registration.levels import LevelIdentification, explains_the_image, plan_contest
from carmreg.logic.registration.preflight import MIN_CLICKS
from carmreg.logic.registration.spatial import spatial_search
from carmreg.logic.registration.state import RegistrationState

UPSIDE_DOWN = ("flipped-up-down", "turned-180")
"""The displays that keep the image's shape and show the spine upside down: unnamed clicks cannot tell them."""
WITHOUT_CLICKS_TURNS = (MIRROR, *UPSIDE_DOWN)
"""The displays ``_orientation_without_clicks`` refines on any detector: those that keep the image's shape; the mirror
always, the others when not ruled out."""


def _rivals_under_either_polarity(state: RegistrationState) -> list[str]:
    """The displays the database could not rule out (``rival_orientations``) under the polarity in use, then those it
    could not rule out under the other polarity, each in the database's order, each once. Under the polarity in use
    the database can rule the right display out and keep it under the other (tune case 502's half turn under bone
    bright, 0.27 against 0.31 as stored; bone dark 0.64 against 0.36); under the other polarity it rarely rules
    any display out (stop 61)."""
    a = state.appearance
    other = _database_orientation(state, not a.bone_dark)
    return list(dict.fromkeys(rival_orientations(a.orientation_scores) + rival_orientations(other)))


def _shown_without_clicks(pixel_spacing_mm: tuple) -> tuple[str, ...]:
    """The displays ``_orientation_without_clicks`` may judge: ``WITHOUT_CLICKS_TURNS`` on any detector, and the
    quarter turns (``turn.QUARTER_TURNED``) too on a square one with square pixels, where the turned image lies on
    the same pixel grid as the database's DRRs (the database scores a quarter turn only when the image is square:
    ``orientation_scores``)."""
    square = bool(np.isclose(pixel_spacing_mm[0], pixel_spacing_mm[1], rtol=1e-6))
    return WITHOUT_CLICKS_TURNS + (QUARTER_TURNED if square else ())


def _upside_down_rivals(state: RegistrationState) -> list[str]:
    """With unnamed clicks, the upside-down displays judged at the clicks when the polarity is unclear there: the
    display the database refuses the image for (``Appearance.orientation``, its verdict) when that is the flip or the
    half turn, none when it is another; else the flip and the half turn among ``_rivals_under_either_polarity``.
    None with named clicks. Unnamed clicks run along the spine either way up, so as stored they fit an upside-down
    display about as well as an upright one; named clicks on such a display run bottom to top and are refused before
    (``preflight``), and a quarter turn puts the clicks across the image, refused there too. A display the database
    refuses is the one judged: judged on the other upside-down display too, report case 307's flipped TIFF (the
    database's flip 0.56 against 0.36 as stored) was taken as turned 180 degrees at the clicks (stop 62)."""
    a = state.appearance
    if state.xray_landmarks.named:
        return []
    if a.orientation != "as-stored":
        return [a.orientation] if a.orientation in UPSIDE_DOWN else []
    return [o for o in _rivals_under_either_polarity(state) if o in UPSIDE_DOWN]


def _cannot_lead_stored(state: RegistrationState, stored: ClickPolarity):
    """``give_up_for(polarity, landmark_pose)`` for a display's registrations (``polarity_at_clicks``): each stops
    once it cannot end ``REFUSE_ORIENTATION_AT_CLICKS_GC`` ahead of the stored image's best under its polarity
    (``ClickPolarity.scores``) with the clicks within the rule's cap (``early_stop.cannot_lead``;
    ``image_refine.penalty_bound`` from its start, the landmark fit's pose), the only way the display can be taken
    (``stored_against_turned``, ``Appearance.set_orientation_at_clicks``). Seen, stop 62: case 425's large
    patient, correctly displayed, its polarity unclear at the clicks: 22 registrations on three displays, 12 of its
    33 s, every one below 0.22 against the stored image's 0.38."""
    p = state.parameters
    n_clicks, cap_mm = len(state.xray_landmarks.uv_px), p.identify.rule.max_landmark_mpde_mm

    def give_up_for(polarity: str, landmark_pose: np.ndarray):
        penalty = penalty_bound(p.refine_coarse, landmark_pose, n_clicks, cap_mm)
        return cannot_lead(stored.scores[polarity], REFUSE_ORIENTATION_AT_CLICKS_GC, penalty)

    return give_up_for


def _within_reach(turned: ClickPolarity, stored: ClickPolarity, in_use: str) -> bool:
    """Whether a display judged with ``_cannot_lead_stored``'s stops may still be taken, or tell the polarity
    (``_leaning``): one of its registrations ran in full and ended ``REFUSE_ORIENTATION_AT_CLICKS_GC`` ahead of the
    stored image's best under its polarity, or, under the polarity not in use (``in_use``), ahead of the stored
    image's best under either (a stopped one counts for neither). It is then judged again in full, as before the
    stops, so that its verdict is that of full registrations; those that ran in full are recalled
    (``refinement_memo``)."""
    return any(f.stopped_at is None and (f.similarity >= stored.scores[polarity] + REFUSE_ORIENTATION_AT_CLICKS_GC
                                         or (polarity != in_use and _ahead_of_stored(f.similarity, stored) > 0))
               for polarity, fits in turned.registered.items() for f in fits)


def _ahead_of_stored(gc: float, stored: ClickPolarity) -> float:
    """How far a display's GC ``gc`` is ahead of the stored image's best under either polarity (``stored``)."""
    return float(gc - max(stored.scores.values()))


def _leaning(again: Appearance, turned: ClickPolarity, stored: ClickPolarity, in_use: str) -> float | None:
    """How far a display's clear polarity verdict (``again``, from ``turned``'s registrations) leads the stored image,
    when it names the polarity not in use and its best registration is ahead of the stored image's best under either
    polarity (``stored``): the display then explains the image better than the stored image does, whatever the
    polarity, so its verdict is the better evidence of the polarity, a property of the pixels' values that no turn of
    the display changes. None otherwise. Seen, stop 63: report case 441's mirrored display (bone dark), unclear at
    the clicks as stored and taken bone bright (bone dark 0.387 off the clicks, bone bright 0.177 on them); on the
    mirror bone dark 0.426 against 0.011, 0.039 ahead of the stored image, under the 0.10 that takes a display."""
    ahead = _ahead_of_stored(turned.scores[again.polarity], stored)
    return ahead if again.clear and again.polarity != in_use and ahead > 0 else None


def _evidence_at_clicks(a: Appearance) -> dict:
    """The polarity evidence at the clicks in ``a.scores`` (as stored, without the shading, on each display judged),
    for a verdict taken instead of ``a`` to keep."""
    return {k: v for k, v in a.scores.items() if k.startswith(("at_clicks", "on_"))}


def _at_clicks_key(orientation: str) -> str:
    """The ``Appearance.scores`` key of the polarity judged at the clicks on ``orientation`` (the mirror's as since
    stop 17)."""
    return "on_mirror" if orientation == MIRROR else f"on_{orientation}"


def _stated(state: RegistrationState) -> tuple[str | None, str]:
    """(storage, by whom) the X-ray's storage is stated: the user's setting, else its file's (``stated_storage``)."""
    return stated_storage(state.xray, state.parameters.storage)


def _without_clicks_key(orientation: str) -> str:
    """The ``Appearance.scores`` key of the image-alone evidence on ``orientation`` (the mirror's as since stop 28)."""
    return "without_clicks_on_mirror" if orientation == MIRROR else f"without_clicks_on_{orientation}"


@contextlib.contextmanager
def _all_or_nothing(state: RegistrationState):
    """The appearance, the polarity evidence at the clicks, the warnings and the X-ray as converted as they were
    should the block raise (a cancel): a check judged again with the levels' winner never leaves them half updated (a
    re-run could then trust an orientation never checked at the clicks). Yields what it keeps, so that the block can
    also undo itself (``_restore``)."""
    kept = (copy.deepcopy(state.appearance), state.click_polarity, list(state.warnings), state.xray_line_integral)
    try:
        yield kept
    except BaseException:
        _restore(state, kept)
        raise


def _restore(state: RegistrationState, kept: tuple) -> None:
    """Put back what ``_all_or_nothing`` kept."""
    state.appearance, state.click_polarity, state.warnings[:], state.xray_line_integral = kept


def _settled(state: RegistrationState, checked_gc: float) -> bool:
    """Whether the polarity verdict in use needs no second opinion without the shading: clear, and either by a lead
    of ``checked_gc`` or more or on a file that states its polarity."""
    a = state.appearance
    return a.clear and (a.clarity_gc >= checked_gc or state.xray.polarity_stated)


def _database_orientation(state: RegistrationState, bone_dark: bool) -> dict:
    """The database's orientation scores of the X-ray read as ``bone_dark`` (``appearance.orientation_scores``)."""
    return orientation_scores(state.xray.pixels, state.mask, state.database.drrs, state.coarse_factor, bone_dark)


def _other_appearance(state: RegistrationState) -> Appearance:
    """The appearance in use under the other polarity (``Appearance.other_polarity``, never clear), with the database's
    orientation verdict measured under that polarity; a bone-dark image converted as the polarity check at the clicks
    converted it."""
    a = state.appearance
    return a.other_polarity(state.click_polarity.dark_storage, _database_orientation(state, not a.bone_dark),
                            _stated(state))


def _judged(winner: LabellingFit, labellings: list) -> bool:
    """Whether the contest's ``winner`` is one of the ``labellings`` (lists of level names) a check judged."""
    return any(winner.names(lb) for lb in labellings)


def _contest_record(polarity: str, winner: LabellingFit, status: str | None) -> dict:
    """A levels contest in ``scores["contest_under_other_polarity"]``: the polarity it ran under, its winner (or its
    leader before its searches for confidence), the winner's GC and its status (None: not decided yet)."""
    return {"polarity": polarity, "winner": list(winner.labels), "gc": float(winner.similarity), "status": status}


class AppearanceChecks:
    """The appearance checks of one ``CarmRegLogic`` (module docstring): ``report(stage, fraction, message)`` its
    progress hook (which raises ``CancelledError`` on a cancel), ``should_stop()`` its cancel check inside a
    registration."""

    def __init__(self, report, should_stop):
        self._report = report
        self._should_stop = should_stop

    def _context(self, state: RegistrationState, line_integral: np.ndarray) -> FitContext:
        """A labelling's registration on ``line_integral`` from the nominal pose, without a progress hook."""
        return state_context(state, line_integral, 0.0, 0.0, self._should_stop)

    def decide(self, state: RegistrationState) -> dict:
        """Every check of the module docstring, in order, on ``state`` after the database stage: sets
        ``state.appearance`` (with its evidence), ``click_polarity`` or ``image_polarity``, the X-ray's attenuation
        image converted with the verdict and the appearance warnings; returns ``appearance.as_dict()`` (result.json
        ``appearance``)."""
        p, xray = state.parameters, state.xray
        rows, cols = state.database.drrs.shape[2:]
        drrs = state.database.drrs.reshape(-1, rows, cols)
        scores, gc_by_storage = database_gc(xray.pixels, state.mask, drrs, state.coarse_factor)
        refined, refined_by = None, REFINED_AT_DATABASE_POSES
        state.click_polarity = self._polarity_at_clicks(state, gc_by_storage)
        fits = None
        if state.click_polarity is not None:
            refined, refined_by, fits = state.click_polarity.scores, REFINED_AT_CLICKS, state.click_polarity.fits
        elif p.polarity == "auto":
            state.image_polarity = self.polarity_from_image(state, gc_by_storage)
            refined = state.image_polarity.scores
        state.appearance = a = decide_polarity(scores, refined, p.polarity, xray.bone_dark,
                                               xray.sources.get("bone_dark", ""), header_explicit=xray.polarity_stated,
                                               refined_by=refined_by, fits=fits)
        if state.click_polarity is not None:
            a.scores["at_clicks"] = state.click_polarity.as_dict()
        if state.image_polarity is not None:
            a.scores["without_clicks"] = state.image_polarity.as_dict()
        a.set_storage(gc_by_storage, *_stated(state))
        a.set_orientation(_database_orientation(state, a.bone_dark))
        self._use_appearance(state, a, gc_by_storage)
        self._orientation_at_clicks(state, "spatial")
        unshaded = self._polarity_at_clicks_without_shading(state, gc_by_storage)
        self._polarity_on_displays(state, gc_by_storage, unshaded)
        self._orientation_under_other_polarity(state, gc_by_storage, unshaded)
        judged = self._orientation_without_clicks(state, gc_by_storage)
        self._polarity_without_shading(state, gc_by_storage)
        if not judged:
            self._orientation_without_clicks(state, gc_by_storage)  # a clear verdict the second opinion left unclear
        self._appearance_warnings(state)
        return state.appearance.as_dict()

    def _polarity_at_clicks_without_shading(self, state: RegistrationState, gc_by_storage: dict
                                            ) -> ClickPolarity | None:
        """With clicks, a polarity unclear at them, or clear by less than ``CHECKED_CLICKS_GC`` (the file not stating
        a polarity), on an image taken as stored (the user did not set it): the second opinion. The leading
        labellings registered again under both polarities exactly as by ``polarity_at_clicks``, but the X-ray and
        every DRR of the refinements compared without their shading above ``WITHOUT_SHADING_MM``
        (``image.shading``): on a large patient the shading outweighs the faint bone (seen: a bone-bright large
        patient of the second CT, taken bone dark at the clicks by an unclear 0.032, bone bright there by a clear
        0.36; report case 155's, bone dark at the clicks by a clear 0.133, 0.318 against 0.184 with the clicks
        fitted, bone bright without the shading by 0.48). When its verdict is clear (``verdict_at_clicks``) and
        names the other polarity, that polarity is used, never clear (``Appearance.as_second_opinion``): the levels
        stage registers on the image as stored converted with it, and only the contest's winner judged at the
        clicks too (``with_winner``) can make it clear. Otherwise the appearance stays as it was. Either way
        ``scores["at_clicks_without_shading"]`` records it. It runs before the check on the mirror
        (``_polarity_on_displays``), which judges the mirror without the shading too when this verdict is clear and
        the polarity is then unclear (a clear first verdict this one confirms stays clear: no mirror check).
        Returns the evidence without the shading when its verdict is clear, else None."""
        a, cp, p = state.appearance, state.click_polarity, state.parameters
        if cp is None or _settled(state, CHECKED_CLICKS_GC) or p.polarity in POLARITIES or a.orientation != "as-stored":
            return None
        unshaded = self._leaders_judged_again(state, lambda ctx: unshaded_context(ctx, WITHOUT_SHADING_MM),
                                              state.xray_landmarks, "at the clicks without the image's shading")
        a.scores["at_clicks_without_shading"] = unshaded.as_dict()
        again = self._polarity_again(state, unshaded.scores, REFINED_AT_CLICKS_WITHOUT_SHADING, unshaded.fits)
        if not again.clear:
            return None
        if again.polarity == a.polarity:
            return unshaded
        again.as_second_opinion(a)
        again.scores.update({k: v for k, v in a.scores.items() if k.startswith("at_clicks")})  # this one's among them
        self._database_verdicts(state, again, gc_by_storage)
        self._use_appearance(state, again, gc_by_storage)
        return unshaded

    def _polarity_on_displays(self, state: RegistrationState, gc_by_storage: dict,
                              unshaded: ClickPolarity | None = None) -> None:
        """With clicks, and a polarity the image left unclear at them (the user did not set it): the polarity judged
        again on the image mirrored left-right, then (unnamed clicks) flipped up-down and turned 180 degrees: the
        one the database refuses the image for, else those it could not rule out under either polarity
        (``_upside_down_rivals``), each with the clicks turned with it, exactly as at the clicks
        (``_polarity_on_display``); the first display so taken ends it. A
        mirrored display shows no aligned spine as stored under either polarity, and neither does an upside-down one
        with unnamed clicks (the clicks fit either way up, the CT only head up): the verdict as stored stays unclear,
        sometimes for the wrong polarity (stop 62, tune half 288-298 and cases 502-508, unnamed clicks: 6 of 20
        flipped or half-turned displays unclear, 2 of them wrong, where the image turned back tells it clearly).
        When no display is taken but one or more gave a clear verdict for the polarity not in use from a registration
        ahead of the stored image's best under either polarity (``_leaning``), the one furthest ahead lends its
        polarity, never clear (``Appearance.leaned_on_display``); the display itself is not taken."""
        a, cp, p = state.appearance, state.click_polarity, state.parameters
        if cp is None or a.clear or p.polarity in POLARITIES:
            return
        leanings = []
        for o in [MIRROR, *_upside_down_rivals(state)]:
            shown, leaning = self._polarity_on_display(state, gc_by_storage, unshaded, o)
            if shown:
                return
            if leaning is not None:
                leanings.append(leaning)
        if leanings:
            ahead, again, o = max(leanings, key=lambda lean: lean[0])
            again.leaned_on_display(a, o, ahead)
            again.scores.update(_evidence_at_clicks(a))
            self._use_appearance(state, again, gc_by_storage)

    def _polarity_on_display(self, state: RegistrationState, gc_by_storage: dict, unshaded: ClickPolarity | None,
                             orientation: str) -> tuple[bool, tuple | None]:
        """The polarity judged at the clicks on ``orientation`` of the image, the clicks turned with it. Taken only
        when that verdict is clear and the display then leads the stored image under that polarity by
        ``REFUSE_ORIENTATION_AT_CLICKS_GC`` with the clicks fitted (``stored_against_turned``,
        ``Appearance.set_orientation_at_clicks``): the display is so shown, the image refused, no level answer
        confident; returns (whether it was, the display's ``_leaning`` as (lead, verdict, orientation) or None).
        Otherwise the appearance stays as it was, with the display's evidence recorded (``scores["on_mirror"]``,
        ``scores["on_<orientation>"]``). ``unshaded``: the second opinion's
        evidence at the clicks when its verdict is clear (``_polarity_at_clicks_without_shading``); the display is
        then judged without the shading too and compared with it: judged with the shading, a large patient's
        shading can fit the mirror better than the faint bone fits as stored (seen: report case 125, bone bright,
        names one level off: unclear at the clicks, bone bright without the shading by 0.39, then taken bone dark
        and mirrored on the mirror by 0.27). The display's registrations stop once they cannot lead the stored image
        by that margin (``_cannot_lead_stored``); a display one of whose registrations still does, or may lend its
        polarity, is judged again in full (``_within_reach``), so a display is taken, or lends, on full registrations
        only."""
        a, p, xray = state.appearance, state.parameters, state.xray
        stored = state.click_polarity if unshaded is None else unshaded
        where = f"on the image {orientation.replace('-', ' ')}" + ("" if unshaded is None else ", without its shading")
        clicks = turned_clicks(state.xray_landmarks, orientation, xray.size_px)
        change = functools.partial(self._on_display, orientation=orientation, without_shading=unshaded is not None)
        turned = self._leaders_judged_again(state, change, clicks, where, _cannot_lead_stored(state, stored))
        if _within_reach(turned, stored, a.polarity):
            turned = self._leaders_judged_again(state, change, clicks, where)
        a.scores[_at_clicks_key(orientation)] = turned.as_dict()
        again = self._polarity_again(state, turned.scores,
                                     refined_on_at_clicks(orientation, WITHOUT_SHADING_MM if unshaded else 0.0),
                                     turned.fits)
        if not again.clear:
            return False, None
        again.scores.update(_evidence_at_clicks(a))
        self._database_verdicts(state, again, gc_by_storage)
        again.set_orientation_at_clicks(stored_against_turned(stored, turned, orientation, again.polarity,
                                                              p.identify.rule).as_dict())
        if again.orientation != orientation:
            ahead = _leaning(again, turned, stored, a.polarity)
            return False, None if ahead is None else (ahead, again, orientation)
        self._use_appearance(state, again, gc_by_storage)
        return True, None

    def _orientation_under_other_polarity(self, state: RegistrationState, gc_by_storage: dict,
                                          unshaded: ClickPolarity | None) -> None:
        """With clicks, a polarity taken from the image clearly at them but by less than ``CHECKED_CLICKS_GC`` and
        not confirmed by a clear second opinion (``unshaded`` None; the file not stating a polarity, the user not
        setting it), on a display judged as stored at the clicks: the orientation judged at the clicks under the other
        polarity too (``click_orientation.orientation_at_clicks`` on the polarity check's registrations under it, the
        mirror and every orientation that polarity's database scores do not rule out). With g_taken the stored
        image's GC under the polarity taken and g'(o) orientation o's under the other, when the best rival o keeps
        the clicks fitted and

            g'(o) - g_taken >= REFUSE_ORIENTATION_AT_CLICKS_GC      (``displayed_under_other_polarity``)

        the image is the other polarity displayed o (``Appearance.displayed_otherwise``): refused, no level answer
        confident (``image.appearance``'s module docstring, stop 54). Otherwise the appearance stays. Either way
        ``scores["other_polarity_at_clicks"]`` records the evidence. No threshold of its own."""
        a, cp, p, xray = state.appearance, state.click_polarity, state.parameters, state.xray
        if (cp is None or unshaded is not None or not a.clear or _settled(state, CHECKED_CLICKS_GC)
                or p.polarity in POLARITIES or a.orientation != "as-stored" or a.orientation_at_clicks is None):
            return
        other = _other_appearance(state)
        base = self._context(state, self._polarity_image(state, other.polarity, cp.dark_storage))
        contexts = {o: oriented_context(base, o) for o in rival_orientations(other.orientation_scores)}
        self._report("spatial", 0.97, f"judging the display's orientation at the clicks as {other.polarity} too")
        evidence = orientation_at_clicks(contexts, list(cp.registered[other.polarity]), xray.size_px,
                                         p.identify.rule, names_follow_clicks=state.xray_landmarks.named,
                                         memo=state.turned_fits.setdefault((other.polarity, other.storage), {}))
        a.scores["other_polarity_at_clicks"] = other.scores["other_polarity_at_clicks"] = record = evidence.as_dict()
        taken = float(a.orientation_at_clicks["scores"]["as-stored"])
        shown = displayed_under_other_polarity(evidence, taken)
        if shown is not None:
            other.displayed_otherwise(a, record, shown, taken)
            self._use_appearance(state, other, gc_by_storage)

    @staticmethod
    def _on_display(ctx: FitContext, orientation: str, without_shading: bool) -> FitContext:
        """``ctx`` on ``orientation`` of the image, compared without its shading above ``WITHOUT_SHADING_MM`` when
        ``without_shading``."""
        turned = oriented_context(ctx, orientation)
        return unshaded_context(turned, WITHOUT_SHADING_MM) if without_shading else turned

    def _leaders_judged_again(self, state: RegistrationState, change, clicks: Landmarks2D, where: str,
                              give_up_for=None) -> ClickPolarity:
        """The leading labellings of ``clicks`` registered under both polarities exactly as by ``polarity_at_clicks``,
        on the contexts the first check used (``_polarity_contexts``, its bone-dark storage) each passed through
        ``change(ctx) -> FitContext`` (the image mirrored, or compared without its shading); ``where`` words the
        progress; ``give_up_for`` as ``polarity_at_clicks``'s."""
        cp, p = state.click_polarity, state.parameters
        contexts = {polarity: change(ctx) for polarity, ctx in self._polarity_contexts(state, cp.dark_storage).items()}
        plan = plan_contest(contexts["bone-dark"], state.ct_landmarks, clicks, p.identify)

        def progress(done: int, total: int) -> None:
            self._report("spatial", 0.9, f"telling bone-dark from bone-bright {where} ({done + 1} of {total})")

        return polarity_at_clicks(contexts, plan, cp.dark_storage, p.identify.rule, progress, give_up_for)

    def _orientation_without_clicks(self, state: RegistrationState, gc_by_storage: dict) -> bool:
        """Without clicks, a polarity the image left unclear and an orientation not clearly as stored (the user did
        not set the polarity): each polarity refined again on the rival displays of the image as on the image as
        stored (``_displays_judged``). The rival that leads the stored image most, by at least
        ``REFUSE_ORIENTATION_AT_CLICKS_GC``, under its own leading polarity (``image.appearance.
        displayed_without_clicks``) is the display: its verdict is taken (clear at ``CLEAR_REFINED_GC``) and the image
        refused (``Appearance.set_orientation_without_clicks``). Otherwise the appearance stays as it was, with the
        evidence recorded (``scores["without_clicks_on_mirror"]``, ``scores["without_clicks_on_<o>"]``). The levels
        stage keeps the image as stored (a refused image names no level). Not once the second opinion's evidence
        without the shading is in use (its scores are not comparable with the rivals refined on the plain image).
        Returns whether the rivals were judged.
        ``decide`` asks again after the second opinion (``_polarity_without_shading``) when that left a clear verdict
        unclear (stop 61: tune case 296's mirrored display, bone dark, taken bone bright by 0.222 over the 0.22
        threshold, the second opinion leaning so by 0.026; the mirror was never judged)."""
        a, p, stored = state.appearance, state.parameters, state.image_polarity
        if (stored is None or stored.without_shading_mm > 0 or a.clear or p.polarity in POLARITIES
                or (a.orientation == "as-stored" and a.orientation_clear)):
            return False
        judged, shown = self._displays_judged(state, gc_by_storage, stored)
        if shown is None:
            return True
        best, gc = shown
        again = self._polarity_again(state, judged[best].scores, refined_on_without_clicks(best))
        again.scores.update({k: v for k, v in a.scores.items() if k.startswith("without_clicks")})
        self._database_verdicts(state, again, gc_by_storage)
        again.set_orientation_without_clicks(best, gc)
        self._use_appearance(state, again, gc_by_storage)
        return True

    def _displays_judged(self, state: RegistrationState, gc_by_storage: dict, stored: ImagePolarity
                         ) -> tuple[dict, tuple | None]:
        """({display: its ``ImagePolarity``}, ``displayed_without_clicks`` of them against ``stored``): each polarity
        refined on each rival display (``polarity_from_image``), recorded in the appearance's scores as judged. The
        rivals: the mirror always, and the image flipped up-down, turned 180 degrees and, on a square detector,
        turned a quarter (mirrored or not; ``_shown_without_clicks``) where the database could not rule that out
        under either polarity (``_rivals_under_either_polarity``; the polarity is unclear here, and a display the
        database rules out under the polarity in use can lead clearly under the other: stop 61, tune case 502's
        intensifier PNG turned 180 degrees, taken bone bright, unclear). They are judged in that order,
        and once the display so far has a clear verdict the rest are not (stop 61, tune half 288-298: judging every
        rival cost 133 judgements where 39 named the same displays and polarities; without the clear verdict,
        report cases 297 and 299 named the first rival leading by the margin, a flip at a polarity gap of 0.030 and
        a half turn at 0.114, where judging on found the display)."""
        a, displays = state.appearance, _shown_without_clicks(state.geometry.intrinsics.pixel_spacing_mm)
        judged, shown = {}, None
        for o in [o for o in _rivals_under_either_polarity(state) if o in displays]:
            judged[o] = self.polarity_from_image(state, gc_by_storage, o)
            a.scores[_without_clicks_key(o)] = judged[o].as_dict()
            shown = displayed_without_clicks(stored.scores, {o: j.scores for o, j in judged.items()})
            if shown is not None and self._polarity_again(state, judged[shown[0]].scores,
                                                          refined_on_without_clicks(shown[0])).clear:
                break
        return judged, shown

    def _polarity_without_shading(self, state: RegistrationState, gc_by_storage: dict) -> None:
        """Without clicks, a polarity still unclear, or the image's clear verdict by less than
        ``CHECKED_REFINED_GC`` (the file not stating a polarity), on an image taken as stored (the user did not set
        it): the second opinion. Each polarity judged again exactly as by ``polarity_from_image``, but the X-ray, the
        database and every DRR of the refinements compared without their shading above ``WITHOUT_SHADING_MM``
        (``image.shading``): on a large patient the shading outweighs the faint bone, and on a tilted view the
        plain map's peaks miss the true pose (``Testing/Benchmarks/large_patient_shading.py``). When it leads with
        the other polarity, that polarity is used, never clear (``Appearance.as_second_opinion``: no level answer is
        proposed on it), and the levels stage compares the images the same way, reusing its refinements
        (``_levels``). When it leads with the same polarity but not clearly (by less than ``CLEAR_REFINED_GC``), a
        clear first verdict is no longer clear (``Appearance.not_confirmed_by``); otherwise the appearance stays as it
        was. Either way ``scores["without_clicks_without_shading"]`` records it."""
        a, p = state.appearance, state.parameters
        if (state.image_polarity is None or _settled(state, CHECKED_REFINED_GC) or p.polarity in POLARITIES
                or a.orientation != "as-stored"):
            return
        unshaded = self.polarity_from_image(state, gc_by_storage, without_shading_mm=WITHOUT_SHADING_MM)
        a.scores["without_clicks_without_shading"] = unshaded.as_dict()
        again = self._polarity_again(state, unshaded.scores, REFINED_WITHOUT_SHADING)
        if again.polarity == a.polarity:
            if a.clear and not again.clear:
                a.not_confirmed_by(again)
            return
        again.as_second_opinion(a)
        again.scores.update({k: v for k, v in a.scores.items() if k.startswith("without_clicks")})
        self._database_verdicts(state, again, gc_by_storage)
        state.image_polarity = unshaded
        self._use_appearance(state, again, gc_by_storage)

    @staticmethod
    def _polarity_again(state: RegistrationState, refined: dict, refined_by: str, fits: dict | None = None):
        """``decide_polarity`` again, on the database's scores and ``refined`` (measured ``refined_by``; ``fits`` at
        the clicks), with the user's choice and the file's header as the first verdict had them."""
        xray = state.xray
        return decide_polarity(state.appearance.scores["database"], refined, state.parameters.polarity,
                               xray.bone_dark, xray.sources.get("bone_dark", ""), header_explicit=xray.polarity_stated,
                               refined_by=refined_by, fits=fits)

    @staticmethod
    def _database_verdicts(state: RegistrationState, again, gc_by_storage: dict) -> None:
        """The storage and the database's orientation verdict of a polarity verdict taken ``again`` (the orientation
        scores of the appearance in use when the polarity is the same, else measured under the new one)."""
        a = state.appearance
        again.set_storage(gc_by_storage, *_stated(state))
        again.set_orientation(a.orientation_scores if again.polarity == a.polarity
                              else _database_orientation(state, again.bone_dark))

    @classmethod
    def _use_appearance(cls, state: RegistrationState, a, gc_by_storage: dict) -> None:
        """Take ``a`` as the X-ray's appearance: the spatial stage's GC map when already computed (``_known_gc``)
        and the X-ray's attenuation image converted with ``a``'s polarity and storage."""
        state.appearance = a
        state.known_gc = cls._known_gc(state, gc_by_storage)
        state.xray_line_integral = attenuation(state.xray.pixels, state.mask, a.bone_dark, a.storage)

    @staticmethod
    def _appearance_warnings(state: RegistrationState) -> None:
        """The warnings on the X-ray's appearance, replacing earlier ones (the levels stage may judge it again)."""
        a = state.appearance
        state.warnings[:] = [w for w in state.warnings if not w.startswith(("X-ray polarity:", "X-ray orientation:"))]
        if not a.clear:
            state.warnings.append(f"X-ray polarity: {a.note}")
        if a.orientation == "as-stored" and not a.orientation_clear:
            state.warnings.append("X-ray orientation: the image matches the CT mirrored or turned about as well as "
                                  "as stored; check that the display is not mirrored or rotated")

    def with_winner(self, state: RegistrationState, winner: LabellingFit) -> bool:
        """The levels stage's ``judge_appearance``: whether the appearance is trusted once the contest's winner is
        judged at the clicks too. A trusted appearance has its orientation judged again with the winner
        (``_orientation_with_winner``). Otherwise, only for an image taken as stored, or refused by the orientation
        check at the clicks on the stored image's leaders alone (``_refused_at_clicks``; any other refusal stays),
        whose judged labellings did not include the winner: it is registered under both polarities as the leaders were
        (``click_polarity.judged_also``). Whenever the winner's registration there - judged among the leaders, or just
        registered so - is worse than the pose the contest found for it (``ClickPolarity.found_better``), the
        orientation clear (only the polarity in question), it is refitted under both from that pose
        (``judged_again_from``; a winner judged among the leaders only then, since stop 47; one registered afresh
        too since stop 51 - seen, case 281's scene drawn on the chest CT, T6-T8 clicked unnamed on a view turned about
        10 degrees, judged on T2-T7, all wrong: T6-T8 won at GC 0.82 from its neighbour's pose, registered afresh it
        reached 0.18, and the right answer stayed ambiguous). When the image confirms the polarity in use by
        ``CLEAR_WITH_WINNER_GC`` (``click_polarity.confirms``) and ``decide_polarity`` agrees (a header conflict
        stays one), that verdict is taken and the orientation judged again at the clicks with the winner, the stored
        one clear only by the same lead: the winner was chosen on the image as stored and as converted, so the
        evidence leans toward both. Otherwise nothing changes. All or nothing: a cancel on the way leaves the
        appearance as it was."""
        a, cp, p = state.appearance, state.click_polarity, state.parameters
        a.scores.pop("at_clicks_with_winner", None)
        if a.trusted:
            return self._orientation_with_winner(state, winner)
        if not self._judged_anew(state, a, winner):
            return a.trusted
        judged = _judged(winner, cp.labels)
        if judged and not cp.found_better(winner, a.polarity):
            return a.trusted
        contexts = self._polarity_contexts(state, cp.dark_storage)
        names = ", ".join(winner.labels)
        extended = cp
        if not judged:
            planned = plan_labelling(contexts["bone-dark"], winner.labels, winner.shift, winner.points_lps_mm,
                                     winner.uv_px)
            self._report("levels", 0.99, f"judging the X-ray's appearance with {names} too")
            extended = judged_also(contexts, cp, planned, p.identify.rule)
        if a.orientation_clear and extended.found_better(winner, a.polarity):  # a judged winner always, here
            self._report("levels", 0.99, f"judging the X-ray's appearance again at the pose found for {names}")
            extended = judged_again_from(contexts, extended, winner, p.identify.rule)
        again = self._polarity_again(state, extended.scores, REFINED_AT_CLICKS, extended.fits)
        if not (again.clear and again.polarity == a.polarity and confirms(extended, a.polarity)):
            a.scores["at_clicks_with_winner"] = extended.as_dict()
            return a.trusted
        with _all_or_nothing(state):
            a.take_polarity_verdict(again, f"the levels' winner {', '.join(winner.labels)}", CLEAR_WITH_WINNER_GC)
            a.scores["at_clicks"] = extended.as_dict()
            state.click_polarity = extended
            a.set_orientation(a.orientation_scores)  # the database's verdict, which the clicks' may not overrule
            self._orientation_at_clicks(state, "levels", clear_gc=CLEAR_WITH_WINNER_GC)
            self._appearance_warnings(state)
        return a.trusted

    @staticmethod
    def worth_other_polarity(state: RegistrationState, winner: LabellingFit) -> bool:
        """Whether the levels contest at the clicks should run again under the other polarity
        (``contest_under_other_polarity``): the polarity was left unclear at the clicks, on an image taken as stored
        whose file does not state a polarity, the user did not set it, the contest's ``winner`` was not among the
        labellings the polarity was judged on, and it explains the image poorly (``levels.explains_the_image``: under
        the confidence rule's floor, or its clicks beyond the cap). The polarity at the clicks is judged on the most
        plausible labellings (``labelling_order``; by click spacing until stop 65); when all of them are wrong
        neither polarity shows an aligned spine there, and the verdict can name the wrong one (seen: report case 205,
        chest, T10-T12 clicked, the 10th most plausible of 11 by click spacing: taken bone bright, unclear, on three
        bone-dark images; the contest on the inverted image then won with T1-T3 at GC 0.22-0.27, ambiguous, where
        under bone dark T10-T12 wins at GC 0.81). A winner the polarity was judged on left it unclear itself: the
        image cannot tell, and a second contest only costs time (seen: large patients stored bone bright, 5-25 s more
        a run, never taken) - unless the polarity was taken from that very evidence (``REFINED_AT_CLICKS``) although
        at the winner the other polarity agreed better with the image (``ClickPolarity.prefers_other``: the polarity
        was taken where the clicks fitted, on other labellings). Seen, stop 46: fresh report case 271's flat-panel
        DICOM without a sign, stored bone bright, unnamed clicks on T8-T10: judged on T3-T8, bone dark was taken (its
        registration kept the clicks at GC 0.11, bone bright's did not, at 0.29); T6-T8 then won, GC 0.29 bone bright
        against -0.07 bone dark. Never for a polarity a display lent (``Appearance.lent_by_display``): the other
        polarity is the stored image's unclear verdict, which trailed clearly on a display that explained the image
        better (stop 64: report case 441's mirrored display, the second contest 17 s more, not taken)."""
        a, cp, p = state.appearance, state.click_polarity, state.parameters
        if (a is None or cp is None or a.clear or p.polarity in POLARITIES or state.xray.polarity_stated
                or a.orientation != "as-stored" or a.lent_by_display or explains_the_image(winner, p.identify.rule)):
            return False
        if not _judged(winner, cp.labels):
            return True
        return a.decided_by == f"image ({REFINED_AT_CLICKS})" and cp.prefers_other(winner.labels, a.polarity)

    def contest_under_other_polarity(self, state: RegistrationState, first: LabellingFit, first_status: str | None,
                                     labellings: list, contest: Callable[[], LevelIdentification]
                                     ) -> LevelIdentification | None:
        """The levels contest run again (``contest() -> LevelIdentification``) on the X-ray converted as the other
        polarity (``Appearance.other_polarity``, never clear): its answer is returned and its appearance taken only
        when the appearance is then trusted, i.e. its winner, judged at the clicks under both polarities as the
        leaders were, confirmed that polarity by ``CLEAR_WITH_WINNER_GC`` (``with_winner``) and the orientation
        held. Otherwise None, with the appearance, the polarity evidence and the warnings as they were (also on a
        cancel: ``_all_or_nothing``). No threshold of its own: the same rule that trusts a polarity with the winner
        of the first contest. ``first``: the first contest's winner, or its leader before its searches for
        confidence (``first_status`` None: the pipeline asks before them); ``labellings``: the contest's candidates
        (``LabellingFit``). Since stop 59 the contest is not run when none of them, winning, could make the other
        polarity trusted (``trust_within_reach``): it could never be taken. Either way
        ``scores["contest_under_other_polarity"]`` records both contests (``again`` None: not run)."""
        a, xray = state.appearance, state.xray
        other = _other_appearance(state)
        again, taken = None, False
        if self.trust_within_reach(state, labellings, other):
            self._report("levels", 0.5, f"the best labelling explains the X-ray poorly as {a.polarity}: the contest "
                                        f"again as {other.polarity}")
            with _all_or_nothing(state) as kept:
                state.appearance = other
                state.xray_line_integral = attenuation(xray.pixels, state.mask, other.bone_dark, other.storage)
                again = contest()
                taken = state.appearance.trusted
                if not taken:
                    _restore(state, kept)
        state.appearance.scores["contest_under_other_polarity"] = {
            "first": _contest_record(a.polarity, first, first_status),
            "again": None if again is None else _contest_record(other.polarity, again.winner, again.status),
            "taken": bool(taken), "before_first_searched": first_status is None}
        if not taken:
            return None
        state.appearance.note += (f"; found after the levels contest as {a.polarity} ended with "
                                  f"{first.labels[0]}-{first.labels[-1]} explaining the image poorly")
        self._appearance_warnings(state)
        return again

    def _orientation_with_winner(self, state: RegistrationState, winner: LabellingFit) -> bool:
        """A trusted appearance (``Appearance.trusted``) whose orientation check at the clicks did not judge the
        contest's winner: the winner registered on the image as stored as the leaders were, and the orientation
        judged again with it among the judged labellings, as stored and on every rival, by the same rule and leads
        (``_orientation_at_clicks``, ``Appearance.set_orientation_at_clicks``). The leaders, ranked by click spacing,
        can all be wrong, and a mirrored display can then lead as stored on them (seen: report case 99's, 0.425
        against 0.359 on T6-T8 and T8-T10; T9-T11 on the mirror reaches 0.82): no confident answer names a labelling
        whose display was not judged. It runs on a trusted appearance only, so it can take trust away, never give
        it (the winner, chosen on the image as stored, leans toward the stored orientation: ``with_winner`` asks a
        wider lead where it may give trust). All or nothing: a cancel on the way leaves the appearance as it was.
        Whether the appearance is trusted after."""
        a = state.appearance
        judged = a.orientation_at_clicks["labels"] if a.orientation_at_clicks is not None else None
        if judged is None or _judged(winner, judged):
            return a.trusted
        with _all_or_nothing(state):
            self._orientation_at_clicks(state, "levels", winner=winner)
            self._appearance_warnings(state)
        return a.trusted

    @classmethod
    def trust_within_reach(cls, state: RegistrationState, labellings: list, appearance: Appearance | None = None
                           ) -> bool:
        """Whether a levels contest over ``labellings`` (its ``LabellingFit`` candidates) may end with the appearance
        (``appearance``, default the one in use) trusted, so that a verdict other than ambiguous can come out:
        trusted already, or one of them, as the winner, would be judged anew by ``with_winner``
        (``_judged_anew``). When not, the contest's searches that serve only a confident verdict are skipped
        (``levels.finish_contest(confidence_possible=False)``) and the contest under this polarity is not run
        (``contest_under_other_polarity``): neither could change the status. Seen, stop 59: report case 149's large
        patient stored bone bright (second CT, L1-S1: all four labellings of three clicks judged at the clicks, the
        orientation unclear under either polarity), with names one level off: 14 s for a contest under the other
        polarity that could never be taken and 10 s of searches under the first, 41 s a run, ambiguous either way."""
        a = appearance if appearance is not None else state.appearance
        return a is None or a.trusted or any(cls._judged_anew(state, a, f) for f in labellings)

    @classmethod
    def _judged_anew(cls, state: RegistrationState, a: Appearance, winner: LabellingFit) -> bool:
        """Whether ``with_winner`` goes on to judge the untrusted appearance ``a`` with the contest's ``winner`` at the
        clicks: there is a polarity check at the clicks, ``a`` is not untrusted for good
        (``untrusted_for_good``), and the winner was not judged there or the orientation is clear (a judged winner
        is judged again only from a better pose, and only with the orientation clear)."""
        cp = state.click_polarity
        return (cp is not None and not cls.untrusted_for_good(a)
                and (a.orientation_clear or not _judged(winner, cp.labels)))

    @classmethod
    def untrusted_for_good(cls, a: Appearance | None) -> bool:
        """Whether the appearance ``a`` stays untrusted whatever the levels contest finds: not trusted, on a display
        judged mirrored or turned by a check the contest's winner cannot overrule (any but the orientation check at the
        clicks on the stored image's leaders alone, ``_refused_at_clicks``). ``with_winner`` then changes nothing
        (``_judged_anew``), so no level answer can be confident (``trust_within_reach``)."""
        return (a is not None and not a.trusted and a.orientation != "as-stored"
                and not cls._refused_at_clicks(a))

    @staticmethod
    def _refused_at_clicks(a) -> bool:
        """Whether the appearance ``a`` refuses the display only on the orientation check at the clicks
        (``set_orientation_at_clicks``) of the stored image's polarity verdict: not on the database's scores, the
        polarity verdict on a turned or mirrored display (``_polarity_on_displays``) or without clicks. That check
        judged the leading labellings only (and, on a close call, their neighbours), which may all be wrong
        (seen: report case 99's intensifier images, T9-T11 clicked, judged on T6-T8 and T8-T10 at GC 0.32, the
        mirror 0.43 ahead by 0.11; the contest's winner T9-T11 then reached 0.82 as stored; the close call's
        neighbours now settle that case first); the levels' winner judged too (``with_winner``) may overrule it."""
        return (a.orientation_at_clicks is not None and a.orientation != "as-stored"
                and database_orientation(a.orientation_scores) == "as-stored"
                and ON_TURNED_AT_CLICKS not in a.decided_by)

    def _polarity_at_clicks(self, state: RegistrationState, gc_by_storage: dict) -> ClickPolarity | None:
        """The leading labellings registered under both polarities (``click_polarity``); None without enough
        identifiable clicks. A bone-dark image is converted with its storage (``dark_storage``)."""
        p, clicks = state.parameters, state.xray_landmarks
        if len(clicks.labels) < MIN_CLICKS or (clicks.named and not p.level_check):
            return None
        storage = dark_storage(gc_by_storage, _stated(state)[0])
        contexts = self._polarity_contexts(state, storage)
        plan = plan_contest(contexts["bone-dark"], state.ct_landmarks, clicks, p.identify)

        def progress(done: int, total: int) -> None:
            self._report("spatial", 0.1 + 0.8 * done / max(total, 1),
                         f"telling bone-dark from bone-bright at the clicks ({done + 1} of {total})")

        return polarity_at_clicks(contexts, plan, storage, p.identify.rule, progress)

    @staticmethod
    def _known_gc(state: RegistrationState, gc_by_storage: dict) -> np.ndarray | None:
        """The spatial stage's GC map when already computed: the chosen bone-dark conversion's (``database_gc``),
        or the chosen polarity's map of the check without clicks."""
        a, checked = state.appearance, state.image_polarity
        if a.bone_dark:
            return gc_by_storage[a.storage]
        if checked is not None and a.polarity in checked.maps and state.parameters.metric == "gc":
            return checked.maps[a.polarity].reshape(-1)
        return None

    def _polarity_contexts(self, state: RegistrationState, dark_storage: str) -> dict:
        """{polarity: FitContext} on the X-ray converted as that polarity (``_polarity_image``), without a progress
        hook: where the polarity checks (at the clicks, and without clicks) register."""
        return {polarity: self._context(state, self._polarity_image(state, polarity, dark_storage))
                for polarity in POLARITIES}

    @staticmethod
    def _polarity_image(state: RegistrationState, polarity: str, dark_storage: str) -> np.ndarray:
        """The X-ray's attenuation image if it were ``polarity``: bone dark converted with ``dark_storage``,
        bone bright as a log display (the only storage that shows bone bright)."""
        dark = polarity == "bone-dark"
        return attenuation(state.xray.pixels, state.mask, dark, dark_storage if dark else "log-display")

    def _orientation_at_clicks(self, state: RegistrationState, stage: str, clear_gc: float | None = None,
                               winner: LabellingFit | None = None) -> None:
        """With clicks and a clear polarity, the mirror and the orientations the database could not rule out
        judged where the clicks put the CT (``click_orientation``), which then decides; ``winner``: the contest's
        winner judged too (``_orientation_with_winner``). A close call (the stored orientation's lead either way
        under ``CLOSE_ORIENTATION_AT_CLICKS_GC``) is judged again with the judged labellings' neighbours too
        (``_neighbours_as_stored``)."""
        a, cp = state.appearance, state.click_polarity
        if cp is None or not a.clear or a.polarity not in cp.registered:
            return
        base = self._context(state, state.xray_line_integral)
        contexts = {o: oriented_context(base, o) for o in rival_orientations(a.orientation_scores)}
        self._report(stage, 0.95, "judging the display's orientation at the clicks")
        memo = state.turned_fits.setdefault((a.polarity, a.storage), {})  # the image the contexts show

        def judged_on(judged: list):
            return orientation_at_clicks(contexts, judged, state.xray.size_px, state.parameters.identify.rule,
                                         names_follow_clicks=state.xray_landmarks.named, memo=memo)

        judged = list(cp.registered[a.polarity])
        if winner is not None:
            planned = plan_labelling(base, winner.labels, winner.shift, winner.points_lps_mm, winner.uv_px)
            judged.append(self._registered_as_stored(base, planned, memo))
        evidence = judged_on(judged)
        if close_call(evidence.scores):
            more = self._neighbours_as_stored(state, base, judged, memo)
            evidence = judged_on(judged + more) if more else evidence
        a.set_orientation_at_clicks(evidence.as_dict(), clear_gc)

    @staticmethod
    def _neighbours_as_stored(state: RegistrationState, base: FitContext, judged: list, memo: dict) -> list:
        """The labellings one level up and down from each judged one (the plan's, not judged yet), registered on
        the image as stored (``base``) as the leaders were (``registered_as_leader``), each once per image
        (``memo``). The leading labellings, ranked by click spacing, can all be wrong; on a mirrored display the
        stored image then fits them about as well as the mirror does, and the right labelling, a level or two
        away, shows the mirror clearly ahead (seen: report case 99's mirrored display, judged on T6-T8 and T8-T10,
        clear as stored by 0.066; T9-T11 on the mirror reaches 0.82)."""
        plan = plan_contest(base, state.ct_landmarks, state.xray_landmarks, state.parameters.identify)
        done = {(tuple(f.labels), f.shift) for f in judged}
        near = [plan.fits[i] for i in one_level_from(plan, {f.shift for f in judged})]
        return [AppearanceChecks._registered_as_stored(base, f, memo)
                for f in near if (tuple(f.labels), f.shift) not in done]

    @staticmethod
    def _registered_as_stored(base: FitContext, planned: LabellingFit, memo: dict) -> LabellingFit:
        """``planned`` (depth search only) registered on the image as stored (``base``) as the leaders were
        (``registered_as_leader``), once per image (``memo``, keyed by its labels and shift)."""
        key = ("as-stored", tuple(planned.labels), planned.shift)
        if key not in memo:
            memo[key] = registered_as_leader(base, planned)
        return memo[key]

    def polarity_from_image(self, state: RegistrationState, gc_by_storage: dict, orientation: str = "as-stored",
                             without_shading_mm: float = 0.0) -> ImagePolarity:
        """Without clicks: each polarity's spatial-map peaks refined on the image alone (``image_polarity``),
        the starts the levels stage takes under that polarity. A bone-dark image is converted with its storage
        (``dark_storage``). ``orientation``: judged on that orientation of the image (``oriented_context``; the
        database's GC map, which is the stored image's, is then not reused). ``without_shading_mm`` > 0: the
        X-ray, the database and the refinements' DRRs compared without their shading above that scale
        (``image.shading``)."""
        storage = dark_storage(gc_by_storage, _stated(state)[0])
        contexts = self._polarity_contexts(state, storage)
        if orientation != "as-stored":
            contexts = {polarity: oriented_context(ctx, orientation) for polarity, ctx in contexts.items()}
        if without_shading_mm > 0:
            contexts = {polarity: unshaded_context(ctx, without_shading_mm) for polarity, ctx in contexts.items()}
        stored_gc = gc_by_storage[storage] if orientation == "as-stored" else None
        starts, maps = self._image_alone_starts(state, contexts, stored_gc, without_shading_mm)

        where = "" if orientation == "as-stored" else f" on the image {orientation.replace('-', ' ')}"
        if without_shading_mm > 0:
            where += f" without its shading above {without_shading_mm:g} mm"

        def progress(done: int, total: int) -> None:
            self._report("spatial", 0.1 + 0.8 * done / max(total, 1),
                         f"telling bone-dark from bone-bright{where} ({done + 1} of {total})")

        return polarity_from_image(contexts, starts, maps, progress, without_shading_mm)

    @staticmethod
    def _image_alone_starts(state: RegistrationState, contexts: dict, stored_gc: np.ndarray | None,
                            without_shading_mm: float) -> tuple[dict, dict]:
        """({polarity: [(6,) start]}, {polarity: spatial map}) of each context's image on the coarse database
        (``image_starts``, ``spatial_search``). ``stored_gc``: the bone-dark image's map when already computed
        (``database_gc``), else None. ``without_shading_mm`` > 0: the database and the images less their shading,
        and no map (only the plain image's serves the spatial stage)."""
        p, db = state.parameters, state.database
        rows, cols = db.drrs.shape[2:]
        mask_coarse = bin_mask_to(contexts["bone-dark"].mask, state.coarse_factor, (rows, cols))
        remove = None
        if without_shading_mm > 0:
            remove = shading_remover(mask_coarse, without_shading_mm / db.intrinsics.pixel_spacing_mm[0])
            db = dataclasses.replace(db, drrs=remove(db.drrs))
        starts, maps = {}, {}
        for polarity, ctx in contexts.items():
            coarse = bin_image_to(ctx.xray_line_integral, state.coarse_factor, (rows, cols))
            if remove is not None:
                coarse = remove(coarse)
            else:
                known = {"gc": stored_gc} if polarity == "bone-dark" and stored_gc is not None else None
                maps[polarity] = spatial_search(db, coarse, mask_coarse, p.metric, (p.metric,),
                                                known=known).maps[p.metric]
            starts[polarity] = image_starts(db, coarse, mask_coarse, p.identify.image_starts)
        return starts, maps
