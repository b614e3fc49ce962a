"""How the levels contest's refits end, and what stopping them once back at their labelling's pose would cost
(stop 41's choice of ``early_stop.REJOIN_SPREAD``, ``REJOIN_DISTANCE``, ``REJOIN_GAIN``).

Not a test. The product does not record a refit's search distribution; this reads it from ``result.json`` files of
a benchmark run whose checkout was patched to record it (each ``level_check.hypotheses[]`` then carries
``start_traces``: per start the labelling's registered ``p0`` pose and ``s0`` score before it (None for its first
registration), the refinement's first steps ``sigma0``, its final objective ``end`` and per CMA-ES generation
``[evaluations, best objective, mean (6), stds (6)]``; the patch adds a ``trace`` list to
``image_refine.intensity_refine`` filled after each ``tell`` and hands it up through ``labelling_fit._refine_from``),
or a stored extract of them (``--load``), which keeps per refit only what the rule reads: per generation
(evaluations, best, d, w) with d = max_k |mean_k - p0_k| / s_k and w = max_k stds_k / s_k, from the first
generation where w <= 0.3 (the widest spread tried; the rule cannot fire before it).

For each (spread, distance, gain) tried it prints the share of the refits' evaluations a stop would have saved and
the improvements it would have forfeited: min(s0, best at the stop) - min(s0, end), the polish the rest of the
search would have added (listed when above 0.002)::

    .venv/bin/python Testing/Benchmarks/rejoin_traces.py W [--save extract.json]
    .venv/bin/python Testing/Benchmarks/rejoin_traces.py --load Testing/Benchmarks/results_rejoin_traces_s41.json
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from carmreg.logic.registration.early_stop import REJOIN_DISTANCE, REJOIN_GAIN, REJOIN_SPREAD, rejoins

SPREADS = (0.1, 0.2, 0.3)
DISTANCES = (0.1, 0.2, 0.3)
GAINS = (0.0, 0.01)
KINDS = {1: "from the other's pose", 2: "tilted -8", 3: "tilted +8", 4: "restarted"}


def extract(work: Path) -> list[dict]:
    """Every refit (a start after the labelling's first registration) of the run's result.json files."""
    out = []
    for path in sorted(work.glob("case*/*/out_*/result.json")):
        check = json.loads(path.read_text()).get("level_check") or {}
        for h in check.get("hypotheses", []):
            for k, t in enumerate(h.get("start_traces") or []):
                if t["s0"] is None or not t["gens"]:
                    continue
                p0, s = np.asarray(t["p0"]), np.asarray(t["sigma0"])
                gens = [[g[0], round(g[1], 5), round(float(np.max(np.abs(np.asarray(g[2:8]) - p0) / s)), 4),
                         round(float(np.max(np.asarray(g[8:14]) / s)), 4)] for g in t["gens"]]
                first = next((i for i, g in enumerate(gens) if g[3] <= max(SPREADS)), len(gens))
                out.append({"run": str(path.parent.relative_to(work)), "labels": h["labels"], "start": k,
                            "s0": round(t["s0"], 5), "end": round(t["end"], 5), "evaluations": gens[-1][0],
                            "gens": gens[first:]})
    return out


def first_stop(refit: dict, spread: float, distance: float, gain: float) -> tuple[int, float] | None:
    """(evaluations, best) at the first generation where the product's rule holds (``early_stop.rejoins`` at these
    thresholds), or None. The extract keeps each generation's largest coordinate in units of the first steps, so the
    rule is asked about one coordinate at the pose 0 with a unit step: d <= distance and w <= spread."""
    settled = rejoins(np.zeros(1), refit["s0"], np.ones(1), spread, distance, gain)
    for e, best, d, w in refit["gens"]:
        if settled(best, [d], [w]):
            return e, best
    return None


def table(refits: list[dict]) -> None:
    total = sum(r["evaluations"] for r in refits)
    print(f"{len(refits)} refits, {total} evaluations")
    for spread, distance, gain in itertools.product(SPREADS, DISTANCES, GAINS):
        saved, forfeits, stopped = 0, [], 0
        for r in refits:
            stop = first_stop(r, spread, distance, gain)
            if stop is None:
                continue
            stopped += 1
            saved += r["evaluations"] - stop[0]
            forfeits.append(min(r["s0"], stop[1]) - min(r["s0"], r["end"]))
        big = sorted(round(f, 3) for f in forfeits if f > 0.002)
        print(f"spread {spread} distance {distance} gain {gain}: {stopped} stopped, {saved / total:.1%} saved, "
              f"forfeits > 0.002: {len(big)} (largest {max(forfeits, default=0):.4f})")


def by_kind(refits: list[dict], spread: float, distance: float, gain: float) -> None:
    for k, name in KINDS.items():
        rs = [r for r in refits if min(r["start"], 4) == k]
        total = sum(r["evaluations"] for r in rs)
        stops = [first_stop(r, spread, distance, gain) for r in rs]
        saved = sum(r["evaluations"] - s[0] for r, s in zip(rs, stops, strict=True) if s is not None)
        print(f"  {name}: {len(rs)} refits, {sum(s is not None for s in stops)} stopped, {saved / max(total, 1):.0%} "
              "of their evaluations saved")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("work", nargs="?", type=Path)
    ap.add_argument("--save", type=Path)
    ap.add_argument("--load", type=Path)
    a = ap.parse_args()
    refits = json.loads(a.load.read_text())["refits"] if a.load else extract(a.work)
    if a.save:
        a.save.write_text(json.dumps({"refits": refits}, separators=(",", ":")))
    table(refits)
    print("the product's setting, by kind of refit:")
    by_kind(refits, REJOIN_SPREAD, REJOIN_DISTANCE, REJOIN_GAIN)


if __name__ == "__main__":
    main()
