"""How well the X-ray agrees with a registered labelling: the number the confidence rule's image-agreement floor
judges (``level_confidence``).

A labelling is registered on the X-ray converted as its appearance was found (``image.prepare.attenuation``:
polarity and storage), and its score's GC is measured on that conversion. A display processed in ways no
conversion models (gamma, edge enhancement, dynamic-range compression: a fluoroscopy JPEG) lowers that GC at the
right pose, and the floor then flags right names (seen: an image-intensifier JPEG of the second CT, GC 0.35 at
the right labelling where the same case's 16-bit log image gave 0.56). So the agreement is::

    A(pose) = max(GC_converted(pose), GC_equalised(pose))

GC_equalised is the GC of the same DRR (the labelling refinement's mu level and detector binning) against the
X-ray's rank image (``prepare.EQUALISED``: ``1 - R`` bone dark, ``R`` bone bright), which undoes every increasing
storage map. It is measured at the labelling's own refined pose and is a second opinion on the image only: the
contest (scores, margins, which labelling wins) is untouched, and an image with no equalised copy
(``FitContext.xray_equalised`` None) is judged on GC_converted alone.
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.registration.image_refine import refine_grid
from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit
from carmreg.logic.similarity.metrics import gc


def measure_agreement(ctx: FitContext, fits: list[LabellingFit]) -> None:
    """Measure GC_equalised at the refined pose of every fit that has none yet (``RefineResult.
    equalised_similarity``; a new refinement starts without one), all poses in one rendered batch."""
    if ctx.xray_equalised is None:
        return
    todo = [f for f in fits if f.refined and not np.isfinite(f.refine.equalised_similarity)]
    if not todo:
        return
    grid = refine_grid(ctx.geometry.intrinsics, ctx.refine, ctx.xray_equalised, ctx.mask)
    drrs = grid.line_integrals(ctx.mu, ctx.geometry, np.array([f.pose for f in todo]))
    for f, value in zip(todo, gc(grid.image, drrs, grid.mask), strict=True):
        f.refine.equalised_similarity = float(value)
