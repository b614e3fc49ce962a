"""Which labellings of unnamed clicks are registered first: those the image agrees with at their landmark pose.

Unnamed clicks have one labelling per run of consecutive CT levels (``labellings``), and each costs an
800-evaluation image refinement, under each polarity and on each display judged. The checks take them in one order
(``levels.ContestPlan.first``): the polarity check at the clicks judges the first ``click_polarity.UNNAMED_LEADERS``
(up to ``MAX_UNNAMED_LEADERS``) under both polarities, the orientation check judges the same ones on each rival
display, and the levels contest registers the first ``IdentifyParameters.candidates``. When the true labelling is
not among the first, every check judges wrong ones first: unclear verdicts, then more labellings on more displays.

Until stop 65 the order was the source depth each labelling's click spacing implies (``depth.depth_search``),
nearest the nominal first. Where the C-arm's source is not at the nominal depth the spacing says little: on the
appearance benchmark's fresh report halves 421-455 (stops 62-64) the true labelling was outside the first two in
164 of 335 unnamed runs (median 13.8 s against 11.6 s), and case 435's seven correctly displayed images, judged on
T4-T6 and T5-T7 with T7-T9 clicked, took 30-33 s each.

Now each labelling L is scored before any image refinement, by the image::

    a(L) = max over displays o of |GC(X_o, DRR(p_o(L)))|

- ``X_o`` the X-ray as the caller's context converted it, shown as ``o``: as stored, mirrored left-right, flipped
  up-down or turned 180 degrees (``DISPLAYS``: the turns of ``turn.ORIENTATIONS`` that keep the detector's shape
  and the spine along it);
- ``p_o(L)`` L's landmark pose on ``o``: the depth search and the anchored fine search (Algorithm 4) of its clicks
  turned with the image and named head to sacrum along it (``labelling_fit.turned_labelling``), as the orientation
  check registers a labelling on a display;
- the DRR on the coarse refinement's grid (``image_refine.refine_grid``), GC over the exposed field.

``|GC|``: the polarity is not known yet, and the inverted image's GC is the negative. The max over displays: the
orientation check judges the same labellings on every display it judges, and labellings chosen on the stored
display alone would favour it (a mirrored display's true labelling agrees with it only mirrored).

The order is ``a`` descending, ties by the depth order before it. No threshold. It costs a depth and a fine search
per labelling and one batch of DRRs per display (about 0.1 s a display for 11 labellings), once per set of clicks
in a registration: ``LabellingOrders`` keeps it, so every check and every conversion of the image (each polarity,
with or without shading) takes its labellings in the same order. Frames and units as in ``labelling_fit``.

Measured on the appearance benchmark's tune half only (cases 0-46 even, 24 scenes a variant, the image converted as
bone dark; ``Testing/Benchmarks/labelling_order_ranks.py``, ``results_labelling_order_ranks_s65_tune.json``): the
true labelling first / in the first two / in the first three, by depth against by ``a``: intensifier PNG 8 / 20 / 20
against 18 / 23 / 23, flat-panel JPEG 7 / 16 / 19 against 20 / 23 / 24, large patient 7 / 16 / 19 against 15 / 17 /
20, low dose 8 / 20 / 20 against 18 / 23 / 23, mirrored display 8 / 20 / 20 against 18 / 23 / 23. Where bone barely
shows the agreement at landmark poses says little either way (stop 65: report case 455's large patient, second CT,
its four labellings at 0.12-0.23 and the true one last; README, the targets).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.registration.image_refine import refine_grid
from carmreg.logic.registration.labelling_fit import (
    FitContext,
    LabellingFit,
    landmark_fit,
    oriented_context,
    turned_labelling,
)
from carmreg.logic.similarity.metrics import gc

DISPLAYS = ("as-stored", "mirrored-left-right", "flipped-up-down", "turned-180")
"""The displays a labelling's agreement is taken on (module docstring)."""


def depth_order(fits: list[LabellingFit]) -> list[int]:
    """Indices of ``fits`` (planned labellings) by the source depth their clicks imply, nearest the nominal first."""
    return np.argsort([abs(f.pose[0]) for f in fits], kind="stable").tolist()


def display_agreement(ctx: FitContext, fits: list[LabellingFit]) -> np.ndarray:
    """(n,) ``a(L)`` of each planned labelling of unnamed clicks (``plan_labelling`` on ``ctx``, clicks in spine
    order): the best ``|GC|`` of the image shown as each of ``DISPLAYS`` against the DRR at the labelling's landmark
    pose on that display (module docstring)."""
    size_px = ctx.xray_line_integral.shape[::-1]
    best = np.zeros(len(fits))
    for name in DISPLAYS:
        shown = oriented_context(ctx, name)
        planned = [turned_labelling(shown, f, name, size_px, names_follow_clicks=False) for f in fits]
        poses = np.array([landmark_fit(shown, f).pose for f in planned])
        grid = refine_grid(shown.geometry.intrinsics, shown.refine, shown.xray_line_integral, shown.mask)
        agreement = gc(grid.image, grid.line_integrals(shown.mu, shown.geometry, poses), grid.mask)
        best = np.maximum(best, np.abs(np.asarray(agreement, float)))
    return best


def ranked_by_agreement(agreement: np.ndarray, fits: list[LabellingFit]) -> list[int]:
    """Indices of ``fits`` by their ``agreement`` (``display_agreement``) descending, ties in ``depth_order``."""
    depth_rank = {i: k for k, i in enumerate(depth_order(fits))}
    return sorted(range(len(fits)), key=lambda i: (-agreement[i], depth_rank[i]))


def agreement_order(ctx: FitContext, fits: list[LabellingFit]) -> list[int]:
    """Indices of ``fits`` by ``display_agreement`` descending, ties in ``depth_order``."""
    return ranked_by_agreement(display_agreement(ctx, fits), fits)


@dataclass
class LabellingOrders:
    """The order of each set of unnamed clicks' labellings in one registration (one per ``RegistrationState``,
    passed to every ``FitContext`` by ``labelling_fit.state_context``): computed on the first context that asks
    (``agreement_order``), the same for every later one. Keyed by the labellings' names and clicks: a display the
    checks judge as turned has its clicks turned, and its own order."""

    orders: dict = field(default_factory=dict)

    def order(self, ctx: FitContext, fits: list[LabellingFit]) -> list[int]:
        key = tuple((tuple(f.labels), np.asarray(f.uv_px, float).tobytes()) for f in fits)
        if key not in self.orders:
            self.orders[key] = agreement_order(ctx, fits)
        return list(self.orders[key])


def unnamed_order(ctx: FitContext, fits: list[LabellingFit]) -> list[int]:
    """The order unnamed clicks' labellings are registered in (module docstring): ``ctx.labelling_orders``'s, or
    computed here when the context keeps none."""
    orders = ctx.labelling_orders
    return orders.order(ctx, fits) if orders is not None else agreement_order(ctx, fits)
