"""The X-ray's polarity judged without clicks, where the image alone puts the CT (beyond the paper;
``image.appearance`` polarity, ``click_polarity`` for the same with clicks).

The database's verdict (``appearance.database_gc``) compares the image with DRRs at poses without rotation
and at one depth, and can be clearly wrong (the appearance benchmark's second CT: every image-intensifier variant
inverted). Without clicks the image alone must find where the CT lies, exactly as the no-click level answer does
(``levels.identify_from_image``): for each polarity p, the image converted as p (bone dark with ``dark_storage``),
its spatial map's ``count`` best peaks, swept over the C-arm's rotation in the image plane (``image_starts``), each
refined on the image alone (the wide coarse refinement, no landmark term)::

    score(p) = max_s GC_refined(s, p)        (s the peaks of p's spatial map)

These are the no-click answer's own starts (same image, same map, same refinement), so the polarity is judged on
the same search the answer uses, and ``identify_from_image`` reuses the chosen polarity's refinements
(``registered=``): the check costs the other polarity's refinements only. It is only as good as its starts: on
the second CT's intensifier images, before the in-plane sweep, no peak of the right polarity's map lay near the
true pose (report case 5: its three refined to GC 0.35, 0.38, 0.24, the wrong polarity's to 0.46, while the true
pose has 0.54), so without clicks their polarity was inverted (README, appearance benchmark).
Frames and units as in ``labelling_fit``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carmreg.logic.registration.labelling_fit import LabellingFit, unlabelled_fit


@dataclass
class ImagePolarity:
    """The polarity evidence without clicks."""

    scores: dict            # {polarity: max refined GC over its starts}
    starts: dict            # {polarity: [(6,) start pose]}
    registered: dict        # {polarity: [LabellingFit refined from the start of the same index]}
    maps: dict              # {polarity: (ny, nz) spatial map (no in-plane turn) the starts' sweep began with;
    #                         none without shading: only the plain image's map serves the spatial stage}
    without_shading_mm: float = 0.0  # > 0: every image compared without its shading above this scale (the second
    #                                  opinion, ``image.shading``)

    def as_dict(self) -> dict:
        return {"scores": dict(self.scores), "without_shading_mm": self.without_shading_mm,
                "starts": {p: [[float(x) for x in s] for s in starts] for p, starts in self.starts.items()},
                "similarity": {p: [f.similarity for f in fits] for p, fits in self.registered.items()}}

    def pairs(self, polarity: str) -> list[tuple[np.ndarray, LabellingFit]]:
        """(start pose, refined fit) of ``polarity``, for ``identify_from_image(registered=...)`` on the same image,
        compared the same way (``without_shading_mm``)."""
        return list(zip(self.starts.get(polarity, []), self.registered.get(polarity, []), strict=True))


def polarity_from_image(contexts: dict, starts: dict, maps: dict, progress=None,
                        without_shading_mm: float = 0.0) -> ImagePolarity:
    """Refine every start of every polarity (module docstring). ``contexts``: {polarity: FitContext} whose image is
    the X-ray converted as that polarity; ``starts``: {polarity: [(6,) pose]}, the peaks of ``maps`` (kept for the
    spatial stage); ``progress(done, total)`` is called before each refinement; ``without_shading_mm``: what the
    contexts' refinements and the maps compared (``ImagePolarity``)."""
    total = sum(len(s) for s in starts.values())
    registered, done = {}, 0
    for polarity, ctx in contexts.items():
        registered[polarity] = []
        for start in starts[polarity]:
            if progress is not None:
                progress(done, total)
            registered[polarity].append(unlabelled_fit(ctx, start))
            done += 1
    scores = {p: max((f.similarity for f in fits), default=float("nan")) for p, fits in registered.items()}
    return ImagePolarity(scores, {p: list(s) for p, s in starts.items()}, registered, dict(maps), without_shading_mm)
