"""The X-ray's polarity judged where the clicks put the CT (beyond the paper; ``image.appearance`` polarity).

The database's verdict (``appearance.polarity_scores``) compares the image with DRRs at poses without rotation
and at one depth. On a CT whose DRRs carry strong features of their own (a narrow, truncated reconstruction) a
correlation of the *wrong* sign at a wrong pose can beat the right sign at the nearest grid pose: measured on the
appearance benchmark's second CT, where the database said the opposite of the truth on every image-intensifier
variant while the DRR at the true pose correlated with the right sign (GC -0.42 bone dark, +0.49 bone bright).

With clicks, the CT can be put where they say first. Each leading labelling L of the contest (``ContestPlan``:
unnamed clicks, the ``UNNAMED_LEADERS`` most plausible; named clicks, the names and one level up and down, so a
labelling one level off still has its true neighbour judged) is registered under both polarities p, exactly as the
levels stage registers a labelling (``fit_labelling``: depth search, anchored landmark fit, wide image refinement
with the landmark term), and::

    score(p) = max_L GC_refined(L, p)

The larger score decides; the gap between them is its clarity (``decide_polarity`` with ``refined=`` these
scores). The image of the wrong polarity is the negative of the right one up to the storage map, so its
refinement finds no pose where the clicks and the image both agree: on the benchmark's tune cases the right
polarity reached GC 0.22-0.79 and the wrong one at most 0.27.

The chosen polarity's registrations are the levels stage's own (same image, same mu level, same refinement), so
it reuses them (``identify_levels(registered=...)``): the check costs the other polarity's refinements only.
Frames and units as in ``labelling_fit``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit, fit_labelling
from carmreg.logic.registration.levels import ContestPlan

UNNAMED_LEADERS = 2   # unnamed clicks: the most plausible labellings judged under both polarities


@dataclass
class ClickPolarity:
    """The polarity evidence at the clicks' poses."""

    scores: dict            # {polarity: max refined GC over the leading labellings}
    fits: dict              # {polarity: [LabellingFit, registered under that polarity]}
    labels: list            # the labellings judged, as level names
    dark_storage: str       # how the bone-dark image was converted ("linear-intensity" | "log-display")

    def as_dict(self) -> dict:
        return {"scores": dict(self.scores), "labellings": [list(lb) for lb in self.labels],
                "dark_storage": self.dark_storage,
                "similarity": {p: [f.similarity for f in fits] for p, fits in self.fits.items()}}


def leading_labellings(plan: ContestPlan) -> list[int]:
    """Indices into ``plan.fits`` judged under both polarities (module docstring)."""
    return list(plan.first) if plan.given_index is not None else list(plan.first[:UNNAMED_LEADERS])


def polarity_at_clicks(contexts: dict, plan: ContestPlan, dark_storage: str, progress=None) -> ClickPolarity:
    """Register the leading labellings under each polarity; ``contexts``: {polarity: FitContext} whose images
    are the X-ray converted with that polarity (bone dark with ``dark_storage``). ``progress(done, total)`` is
    called before each registration."""
    leaders = leading_labellings(plan)
    total = len(leaders) * len(contexts)
    fits, scores = {}, {}
    for polarity, ctx in contexts.items():
        fits[polarity] = []
        for i in leaders:
            if progress is not None:
                progress(sum(len(f) for f in fits.values()), total)
            fits[polarity].append(fit_labelling(_quiet(ctx), _fresh(plan.fits[i])))
        scores[polarity] = max(f.similarity for f in fits[polarity])
    return ClickPolarity(scores, fits, [plan.fits[i].labels for i in leaders], dark_storage)


def _fresh(plan: LabellingFit) -> LabellingFit:
    """The planned labelling (depth search only), as a new object to register."""
    return LabellingFit(list(plan.labels), plan.shift, plan.points_lps_mm, plan.uv_px, plan.depth)


def _quiet(ctx: FitContext) -> FitContext:
    """``ctx`` without its per-labelling progress hook (the caller reports)."""
    out = copy.copy(ctx)
    out.on_labelling = None
    return out
