"""How much the appearance checks' registrations still gain after e evaluations (issue 11's time target, next step).

Not a test. The polarity check at the clicks registers the leading labellings under both polarities, the orientation
check on the mirror (and other rivals): four to six coarse refinements per clicked run, most of them for the side
that loses by far. Stopping those early needs a bound on the GC they could still reach, and stop 17's curves
(``refinement_curves.py``) hold the objective of the contest's refinements only. This reads the curves recorded by
a data-collection snapshot (one JSON line per refinement: the calling functions, the polarity or orientation
judged, and ``[evaluations, best objective, GC at that pose]`` per generation; ``CARMREG_CURVES`` in a copy of
``image_refine.intensity_refine``, not in the product) and prints

- per e: the GC still to come, GC(end) - GC(e), of the checks' registrations (every one; and the losers': the
  polarity not used, every rival orientation);
- an optimistic bound on what stopping the losers could save: a loser stops at the first e where
  GC(e) + K delta(e) + T < bar, delta(e) the largest gain seen after e, bar = the winner's final GC (a rival
  orientation's winner: the polarity check's best registration, the image as stored) minus the lead
  the verdict needs (``--lead``, default 0.30: the largest of the rules that reuse these registrations,
  ``click_polarity.CLEAR_WITH_WINNER_GC``). Optimistic twice over, as in ``refinement_curves``: the winner's score
  is not known in advance, and delta comes from the very runs it is applied to.

    .venv/bin/python Testing/Benchmarks/check_curves.py CURVES_FOLDER [--save extract.json]
    .venv/bin/python Testing/Benchmarks/check_curves.py --load Testing/Benchmarks/results_check_curves_s19.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from curve_tables import EVALUATIONS, allowances, extract, still_to_come_table, value_after

ROLES = {"_polarity_on_display": "polarity on a turned display", "judged_also": "polarity with the winner",
         "polarity_at_clicks": "polarity", "orientation_at_clicks": "orientation"}


def read_curves(folder: Path) -> list[dict]:
    """[{run, role, side, curve: [[e, objective, gc], ...]}] of the checks' registrations (the first of ``ROLES``
    among the callers names the role; the side is the polarity or orientation judged)."""
    out = []
    for path in sorted(folder.glob("*.jsonl")):
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            role = next((ROLES[f] for f in ROLES if f in rec["roles"]), None)
            if role is None or not rec["curve"]:
                continue
            side = rec["where"].get("name") if role == "orientation" else rec["where"].get("polarity")
            run = "/".join(Path(rec["out"]).parts[-3:])
            out.append({"run": run, "role": role, "side": side,
                        "curve": [[e, round(o, 5), round(g, 5)] for e, o, g in rec["curve"]]})
    return out


def _gc_at(curve: list, e: int) -> float | None:
    """GC at the best objective after e evaluations (None before the first generation)."""
    return value_after([c[0] for c in curve], [c[2] for c in curve], e)


def with_outcome(curves: list[dict]) -> list[dict]:
    """Each curve with ``bar_gc`` (the winning side's final GC in that run and role) and ``loser``."""
    best = {}
    for c in curves:
        key = (c["run"], c["role"], c["side"])
        best[key] = max(best.get(key, -np.inf), c["curve"][-1][2])
    for c in curves:
        if c["role"] == "orientation":  # the stored orientation's score: the polarity check's best registration
            stored = [v for (run, role, _), v in best.items() if (run, role) == (c["run"], "polarity")]
            c["bar_gc"], c["loser"] = (max(stored), True) if stored else (None, False)
        else:
            mine = best[(c["run"], c["role"], c["side"])]
            others = [v for (run, role, side), v in best.items() if (run, role) == (c["run"], c["role"])
                      and side != c["side"]]
            c["bar_gc"], c["loser"] = (max(others), True) if others and max(others) > mine else (None, False)
    return curves


def gains(curves: list[dict]) -> dict:
    """{e: (every curve's GC(end) - GC(e), the losers' ones)}."""
    out = {e: ([], []) for e in EVALUATIONS}
    for c in curves:
        for e in EVALUATIONS:
            value = _gc_at(c["curve"], e)
            if value is not None:
                out[e][0].append(c["curve"][-1][2] - value)
                if c["loser"]:
                    out[e][1].append(c["curve"][-1][2] - value)
    return out


def oracle_savings(curves: list[dict], delta: dict, lead: float) -> tuple[int, int, int]:
    """(evaluations saved, evaluations of the losers, evaluations of every check registration)."""
    saved = losers = total = 0
    for c in curves:
        n = c["curve"][-1][0]
        total += n
        if not c["loser"] or c["bar_gc"] is None:
            continue
        losers += n
        stop = next((e for e in EVALUATIONS if (g := _gc_at(c["curve"], e)) is not None
                     and g + delta[e] < c["bar_gc"] - lead), None)
        saved += n - stop if stop is not None and stop < n else 0
    return saved, losers, total


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, nargs="?", help="the CARMREG_CURVES folder of a benchmark run")
    parser.add_argument("--load", type=Path, help="a stored extract (--save) instead")
    parser.add_argument("--save", type=Path, help="write the curves as a compact JSON extract")
    parser.add_argument("--safety", type=float, default=2.0, help="K: times the largest gain seen")
    parser.add_argument("--margin", type=float, default=0.05, help="T: plus this (GC)")
    parser.add_argument("--lead", type=float, default=0.30, help="the lead the verdict needs (GC)")
    args = parser.parse_args(argv)
    curves = with_outcome(extract(args.load, args.save, lambda: read_curves(args.folder)))
    found = gains(curves)
    roles = {r: sum(c["role"] == r for c in curves) for r in ROLES.values()}
    print(f"{len({c['run'] for c in curves})} runs, {len(curves)} check registrations: {roles}")
    print(still_to_come_table(found, "GC still to come", "every one", "the losers'"))
    saved, losers, total = oracle_savings(curves, allowances(found, args.safety, args.margin), args.lead)
    print(f"optimistic bound (a loser stops once its GC + {args.safety:g} x the largest gain seen + {args.margin:g} "
          f"trails the winner's final GC - {args.lead:g}): {saved} of the losers' {losers} evaluations saved, "
          f"{saved / max(total, 1):.0%} of all {total} check evaluations")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
