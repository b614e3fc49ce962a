"""Where the true labelling of unnamed clicks stands in the order the checks take labellings in.

For each case and variant of the appearance benchmark (``bench_appearance``: the scene, the image as stored, its
unnamed clicks), in process up to the DRR database, then the clicks' labellings planned on the X-ray converted as bone
dark (``levels.plan_contest``, without a stored order) and ranked two ways: by the source depth their click spacing
implies (``labelling_order.depth_order``, the order before stop 65) and by the image's agreement at their landmark
pose on the four shape-keeping displays (``labelling_order.agreement_order``, the order since). Prints, per
variant, how often the true labelling is first, in the first two and in the first three. Displays flipped up-down or
turned 180 degrees are left out: their clicks named head to sacrum along the stored image pair no true labelling.

    python labelling_order_ranks.py --cases 0,2,4 --variants ii-dark-log-png,fp-bright-jpeg --out ranks.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_appearance as ba  # noqa: E402

from carmreg.logic.image.prepare import attenuation  # noqa: E402
from carmreg.logic.registration.labelling_fit import state_context  # noqa: E402
from carmreg.logic.registration.labelling_order import (  # noqa: E402
    depth_order,
    display_agreement,
    ranked_by_agreement,
)
from carmreg.logic.registration.levels import plan_contest  # noqa: E402

NO_TRUE_LABELLING = ("flipped", "turned180", "turned90")


def ranks(maker: ba.CaseMaker, case: int, variant: str, cache_dir: str) -> dict:
    """The true labelling's place by depth and by agreement (0 = first; None: not a candidate) and each candidate's
    agreement."""
    logic, state, truth = ba.prepared_case(maker, case, variant, Path(tempfile.mkdtemp()), cache_dir, clicks=True)
    logic.run_through(state, "database")
    image = attenuation(state.xray.pixels, state.mask, True, "log-display")
    ctx = state_context(state, image, 0.0, 0.0, None)
    ctx.labelling_orders = None
    plan = plan_contest(ctx, state.ct_landmarks, state.xray_landmarks, state.parameters.identify)
    agreement = display_agreement(ctx, plan.fits)
    depth = depth_order(plan.fits)
    by_agreement = ranked_by_agreement(agreement, plan.fits)
    true = next((i for i, f in enumerate(plan.fits) if f.names(truth["clicked"])), None)
    return {"case": case, "variant": variant, "truth": list(truth["clicked"]),
            "labels": [list(f.labels) for f in plan.fits], "agreement": [float(a) for a in agreement],
            "rank_depth": depth.index(true) if true is not None else None,
            "rank_agreement": by_agreement.index(true) if true is not None else None}


def table(rows: list[dict]) -> str:
    by_variant = defaultdict(list)
    for r in rows:
        if r["rank_depth"] is not None:
            by_variant[r["variant"]].append((r["rank_depth"], r["rank_agreement"]))
    lines = ["| variant | scenes | by depth: first / first two / first three | by agreement: first / two / three |",
             "|---|---|---|---|"]
    for v, got in by_variant.items():
        counts = [" / ".join(str(sum(r[k] < n for r in got)) for n in (1, 2, 3)) for k in (0, 1)]
        lines.append(f"| {v} | {len(got)} | {counts[0]} | {counts[1]} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", required=True, help="comma-separated case numbers (tune half: even)")
    parser.add_argument("--variants", default="ii-dark-log-png,fp-bright-jpeg,fp-bright-large-tiff,"
                                              "ii-dark-lowdose-tiff,ii-dark-mirrored-png")
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    maker = ba.CaseMaker(second_ct=True)
    rows = []
    for case in (int(c) for c in args.cases.split(",")):
        for variant in args.variants.split(","):
            if any(word in variant for word in NO_TRUE_LABELLING):
                continue
            rows.append(ranks(maker, case, variant, args.cache_dir))
            r = rows[-1]
            print(case, variant, "depth", r["rank_depth"], "agreement", r["rank_agreement"],
                  np.round(r["agreement"], 2).tolist(), flush=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
