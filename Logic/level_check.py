"""Wrong-level check: would the X-ray match better if the clicked levels were named one level up or down?

Naming the vertebrae on the X-ray is where wrong-level surgery starts, and a rigid fit of three centroids is
just as happy with the wrong names: the neighbouring vertebrae look alike and are about as far apart. The
image is not: ribs, the thoracolumbar transition and the shape of the column differ from level to level.

For each hypothesis h in {-1, +1} the clicked labels are shifted by h levels along the CT's labelled levels
(T10, T11, T12 -> T9, T10, T11 for h = -1) and the registration is redone for them from the spatial stage's
(ty, tz): depth search with re-centring, the anchored fine search, then the image refinement. Each hypothesis
is scored by the gradient correlation GC its refinement reaches; the labels as given (h = 0) are scored by the
main refinement. With d = GC(as named) - max GC(shifted):

- d >= margin: **confident** - the names agree with the image;
- -margin < d < margin: **ambiguous** - the image cannot tell the levels apart; check another view or
  label a distinctive level (the last rib, the thoracolumbar transition);
- d <= -margin: **contradicted** - the image matches better one level away: the names are probably wrong.

Measured on 24 realistic simulated cases (README, margin 0.02): correct names were confident in 17, ambiguous
in 3 and contradicted in 4 (false alarms: a second look); names one level off were contradicted in 19,
ambiguous in 3 and confident in 1 (a miss). The check lowers the risk; it does not remove it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import CarmGeometry
from .depth_search import depth_search
from .fine_search import FineParameters, fine_search
from .intensity_refine import RefineParameters, intensity_refine
from .landmarks import LEVEL_NAMES
from .volume import MuLevel


@dataclass
class LevelHypothesis:
    shift: int
    labels: list
    pose: np.ndarray
    mpde_mm: float
    similarity: float


@dataclass
class LevelCheck:
    status: str                   # "confident" | "ambiguous" | "contradicted"
    margin: float                 # GC(as named) - best GC(shifted)
    hypotheses: list = field(default_factory=list)
    message: str = ""

    def as_dict(self) -> dict:
        return {"status": self.status, "margin": self.margin, "message": self.message,
                "hypotheses": [{"shift": h.shift, "labels": h.labels, "similarity": h.similarity,
                                "mpde_mm": h.mpde_mm} for h in self.hypotheses]}


def shifted_labels(labels: list[str], shift: int, available: set[str]) -> list[str] | None:
    """``labels`` moved ``shift`` places along the available levels (head to sacrum), or None if off the end."""
    names = [n for n in LEVEL_NAMES if n in available]
    if not all(lb in names for lb in labels):
        return None
    moved = [names.index(lb) + shift for lb in labels]
    return [names[i] for i in moved] if all(0 <= i < len(names) for i in moved) else None


def fit_hypothesis(level: MuLevel, geometry: CarmGeometry, points_lps_mm: np.ndarray, uv_px: np.ndarray,
                   start_ty_mm: float, start_tz_mm: float, xray_line_integral: np.ndarray, mask: np.ndarray,
                   fine: FineParameters, refine: RefineParameters, shift: int, labels: list,
                   should_stop=None) -> LevelHypothesis:
    """Depth search, anchored fine search and image refinement for one labelling; scored by its GC."""
    depth = depth_search(geometry, start_ty_mm, start_tz_mm, points_lps_mm, uv_px)
    start = np.array([depth.tx_mm, depth.ty_mm, depth.tz_mm, 0.0, 0.0, 0.0])
    landmark = fine_search(geometry, start, points_lps_mm, uv_px, fine, should_stop=should_stop)
    refined = intensity_refine(level, geometry, landmark.pose, xray_line_integral, mask, points_lps_mm, uv_px,
                               refine, should_stop=should_stop)
    return LevelHypothesis(shift, labels, refined.pose, refined.mpde_mm, refined.similarity_end)


def assess(named: LevelHypothesis, shifted: list[LevelHypothesis], margin: float = 0.02) -> LevelCheck:
    """Compare the labels as given with the shifted labellings (module docstring)."""
    if not shifted:
        return LevelCheck("confident", float("inf"), [named], "no neighbouring labelling to compare with")
    best = max(shifted, key=lambda h: h.similarity)
    d = named.similarity - best.similarity
    where = "higher (toward the head)" if best.shift < 0 else "lower (toward the sacrum)"
    if d >= margin:
        return LevelCheck("confident", d, [named, *shifted], "the level names agree with the image")
    if d > -margin:
        message = (f"level names AMBIGUOUS: the image fits about as well with every clicked level named one level "
                   f"{where} ({', '.join(best.labels)}); check another view or label a distinctive level")
        return LevelCheck("ambiguous", d, [named, *shifted], message)
    message = (f"level names CONTRADICTED: the image matches better with every clicked level named one level "
               f"{where} ({', '.join(best.labels)}: correlation {best.similarity:.3f} vs {named.similarity:.3f}); "
               "check the level names (another view, or label a distinctive level) before trusting this overlay")
    return LevelCheck("contradicted", d, [named, *shifted], message)
