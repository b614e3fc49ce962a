"""The X-ray's orientation judged where the clicks put the CT (beyond the paper; ``image.appearance`` orientation).

A C-arm display can be mirrored left-right or turned, which no header records. The database's verdict
(``appearance.orientation_scores``) compares each orientation of the image with DRRs at poses without rotation and
at one depth; on a CT whose DRRs carry features of their own those scores are noise (the appearance benchmark's
second CT: the stored orientation of correctly displayed images led by less than ``CLEAR_ORIENTATION_GC`` in most
cases, so their level answers could never be confident).

With clicks, the CT can be put where they say first. The labellings the polarity check registered
(``click_polarity``, under the polarity used; the best of them scores the stored orientation) are registered
again on each rival orientation o of the image - the
image, its exposed field, the clicks and the detector's principal point and pixel spacing all turned with it
(``turn.orient_uv``) - exactly as the level check registers a labelling (``plan_labelling``,
``fit_labelling``). Names the user gave stay with their clicks (they are anatomy); unnamed clicks get each
labelling's names head to sacrum along the turned image, as any labelling of unnamed clicks is made (so a display
turned upside down is judged with its levels the right way up)::

    g(o) = max over the judged labellings L of the GC of L registered on o(image) with o(clicks)

Every orientation gets the same labellings: judged with the stored orientation's best labelling alone, a mirrored
display was once called clearly as stored (0.487 against 0.353, with a labelling two levels off; the mirror with
the right labelling reaches 0.68). And when the judged labellings are all wrong, the verdict is a close call
whichever way it goes (seen, stop 32: report case 99, T9-T11 clicked, judged on T6-T8 and T8-T10: its mirrored
display clear as stored by 0.066, its correctly displayed images refused by 0.107). So a close call - the stored
orientation and its best rival within ``CLOSE_ORIENTATION_AT_CLICKS_GC`` either way (``close_call``) - is judged
again with the labellings one level up and down from each judged one added, registered as stored and on every
rival (``appearance_checks._neighbours_as_stored``).

A display shown as acquired matches the CT as stored; a mirrored one matches it mirrored. The rivals judged are
the orientations the database could not rule out (within ``CLEAR_ORIENTATION_GC`` of the stored one, or ahead of
it) and always the left-right mirror, the display setting most often wrong: even a clear database verdict is
checked against it (the database once called a mirrored display clearly as stored, lead 0.064; only its unclear
polarity kept that answer from being trusted). ``Appearance.set_orientation_at_clicks`` decides from g. Frames
and units as in ``labelling_fit``; pixel (u, v) = (column, row), 0-based centres.

A rival keeps the clicks fitted when its best registration's click mPDE is within the level rule's landmark limit
against the stored orientation's best (``fitted_limit_mm``), except that a stored registration that does not show
the spine - its GC under ``MIN_CLICKS_GC``, where the landmark term alone placed it - sets no reference, only the
rule's cap (stop 62: report case 295's intensifier PNG turned 180 degrees, unnamed clicks, stored best GC 0.108 at
0.83 mm; the half turn 0.832 at 1.92 mm, over 1.5 x 0.83 + 0.5 = 1.75 mm, and so not taken). Replayed on every
judgement recorded since stop 17 (469 polarity verdicts on a turned display, 3,915 orientation checks at the
clicks): no other decision changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carmreg.logic.image.appearance import (
    CLEAR_ORIENTATION_GC,
    CLOSE_ORIENTATION_AT_CLICKS_GC,
    MIN_CLICKS_GC,
    displayed_rival,
)
from carmreg.logic.registration.click_polarity import ClickPolarity
from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit, fit_labelling, turned_labelling
from carmreg.logic.registration.level_confidence import ConfidenceRule, landmark_limit_mm

MIRROR = "mirrored-left-right"
ALWAYS_CHECKED = (MIRROR,)


@dataclass
class ClickOrientation:
    """The orientation evidence at the clicks' poses."""

    labels: list            # the labellings registered in every orientation (the polarity check's)
    scores: dict            # {orientation: best GC of those labellings registered on it; nan: none refined}
    mpde_mm: dict           # {orientation: the clicks' mPDE of that best one (of the best landmark fit if none)}
    fitted: dict            # {orientation: mPDE within the level rule's limit against the stored one's}

    def as_dict(self) -> dict:
        return {"labels": list(self.labels), "scores": dict(self.scores), "mpde_mm": dict(self.mpde_mm),
                "fitted": dict(self.fitted)}


def rival_orientations(database_scores: dict) -> list[str]:
    """The orientations to judge at the clicks: those the database could not rule out, and the mirror."""
    stored = database_scores["as-stored"]
    close = [o for o, g in database_scores.items() if o != "as-stored" and g > stored - CLEAR_ORIENTATION_GC]
    return sorted(set(close) | {o for o in ALWAYS_CHECKED if o in database_scores},
                  key=lambda o: -database_scores[o])


def orientation_at_clicks(contexts: dict, judged: list, size_px: tuple[int, int], rule: ConfidenceRule,
                          names_follow_clicks: bool, memo: dict | None = None) -> ClickOrientation:
    """Register every labelling of ``judged`` (the polarity check's registrations under the polarity used, as
    stored) on each rival orientation; each orientation's score is its best (module docstring). ``contexts``:
    {orientation: FitContext} on that orientation of the X-ray (``oriented_context``); ``size_px``: (columns, rows)
    of the image as stored; ``names_follow_clicks``: the user named the clicks (module docstring); ``rule``: the
    level confidence rule, whose landmark limit says whether a rival's registration keeps the clicks fitted as well
    as the stored one's (``fitted_limit_mm``). A labelling whose clicks cannot be fitted within the rule's cap even
    by the landmarks alone is not refined; an orientation with none refined scores nan (on a correctly displayed
    image, a turn of 90 degrees lays the spine across the detector).

    ``memo``: registrations of an earlier check on the same image (the caller keeps one dict per attenuation
    image), reused and extended: a registration is seeded, so the same labelling on the same orientation gives
    the same fit (the levels stage judges the orientation again with its winner added)."""
    best = max(judged, key=lambda f: f.similarity)
    scores, mpde = {"as-stored": float(best.similarity)}, {"as-stored": float(best.mpde_mm)}
    memo = {} if memo is None else memo
    for name, ctx in contexts.items():
        fits = []
        for f in judged:
            key = (name, tuple(f.labels), f.shift, np.asarray(f.uv_px, float).tobytes(),
                   np.asarray(f.points_lps_mm, float).tobytes(), names_follow_clicks)
            if key not in memo:
                memo[key] = _registered_turned(ctx, f, name, size_px, rule, names_follow_clicks)
            fits.append(memo[key])
        refined = [f for f in fits if f.refined]
        top = max(refined, key=lambda f: f.similarity) if refined else min(fits, key=lambda f: f.fine.mpde_mm)
        scores[name] = float(top.similarity)  # nan: no labelling's clicks could be fitted on it
        mpde[name] = float(top.mpde_mm if top.refined else top.fine.mpde_mm)
    limit = fitted_limit_mm(scores["as-stored"], mpde["as-stored"], rule)
    fitted = {name: bool(name == "as-stored" or (np.isfinite(scores[name]) and m <= limit))
              for name, m in mpde.items()}
    return ClickOrientation([list(f.labels) for f in judged], scores, mpde, fitted)


def fitted_limit_mm(stored_gc: float, stored_mpde_mm: float, rule: ConfidenceRule) -> float:
    """The click mPDE (detector mm) a rival orientation's best registration may have and still keep the clicks
    fitted: the level rule's landmark limit against the stored orientation's best registration (GC ``stored_gc``,
    mPDE ``stored_mpde_mm``), or the rule's cap alone when that registration's GC is under ``MIN_CLICKS_GC`` (it
    does not show the spine; the landmark term alone placed it: module docstring)."""
    reference = stored_mpde_mm if stored_gc >= MIN_CLICKS_GC else float("nan")
    return landmark_limit_mm(reference, rule)


def close_call(scores: dict) -> bool:
    """Whether the stored orientation's GC ``scores["as-stored"]`` and its best rival's (``orientation_at_clicks``;
    nan: not fittable, left out) lie within ``CLOSE_ORIENTATION_AT_CLICKS_GC`` of each other either way: the
    verdict, whichever it is, then rests on the labellings judged (module docstring)."""
    rivals = [g for o, g in scores.items() if o != "as-stored" and g is not None and np.isfinite(g)]
    return bool(rivals) and abs(scores["as-stored"] - max(rivals)) < CLOSE_ORIENTATION_AT_CLICKS_GC


def displayed_under_other_polarity(evidence: ClickOrientation, taken_gc: float) -> str | None:
    """The orientation o the image is displayed in, judged at the clicks under the polarity not taken
    (``evidence``, ``orientation_at_clicks`` under it): its best rival that keeps the clicks fitted when

        g'(o) - taken_gc >= REFUSE_ORIENTATION_AT_CLICKS_GC

    with ``taken_gc`` the stored image's GC at the clicks under the polarity taken (``image.appearance.
    displayed_rival``, the rule the polarity taken judges its own display by); else None
    (``appearance_checks._orientation_under_other_polarity``)."""
    return displayed_rival(evidence.scores, evidence.fitted, taken_gc)


def stored_against_turned(stored: ClickPolarity, turned: ClickPolarity, name: str, polarity: str,
                          rule: ConfidenceRule) -> ClickOrientation:
    """The orientation evidence of a polarity judged on orientation ``name`` of the image as well as stored
    (``appearance_checks._polarity_on_display``): each orientation's score is its best registration under ``polarity``
    (``polarity_at_clicks`` on the stored image, ``stored``, and on the turned one with the clicks turned,
    ``turned``); the turned one keeps the clicks fitted when its own verdict says so (``turned.fits``) and its mPDE
    is within ``fitted_limit_mm`` of the stored one, as ``orientation_at_clicks`` asks of a rival."""
    best = {o: max(cp.registered[polarity], key=lambda f: f.similarity)
            for o, cp in (("as-stored", stored), (name, turned))}
    limit = fitted_limit_mm(best["as-stored"].similarity, best["as-stored"].mpde_mm, rule)
    fitted = {"as-stored": True, name: bool(turned.fits[polarity] and best[name].mpde_mm <= limit)}
    return ClickOrientation([list(lb) for lb in turned.labels], {o: float(f.similarity) for o, f in best.items()},
                            {o: float(f.mpde_mm) for o, f in best.items()}, fitted)


def _registered_turned(ctx: FitContext, fit: LabellingFit, name: str, size_px: tuple[int, int],
                       rule: ConfidenceRule, names_follow_clicks: bool) -> LabellingFit:
    """``fit``'s labelling registered on orientation ``name`` of the image, its clicks turned with it
    (``turned_labelling``)."""
    return fit_labelling(ctx, turned_labelling(ctx, fit, name, size_px, names_follow_clicks),
                         landmark_gate_mm=rule.max_landmark_mpde_mm)

