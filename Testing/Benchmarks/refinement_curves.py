"""How much a labelling's coarse image refinement still improves after e evaluations (issue 11's time target).

Not a test: it reads the ``level_check.hypotheses[].start_curves`` of the ``result.json`` files a benchmark left
(``bench_appearance.py --work W``: ``W/caseNNN/<variant>/out_<mode>/result.json``), or a stored extract, and prints

- per e: the improvement after e, obj(e) - obj(end), over every start and over the final winner's starts
  (obj = the refinement's best objective so far, lower is better; ``labelling_fit``);
- an optimistic bound on what stopping hopeless refinements could save: a start that is not the winner's stops at
  the first e where obj(e) - delta(e) exceeds the winner's final score, delta(e) the largest improvement after e
  seen (with ``--safety K --margin T``: K delta(e) + T). It is optimistic twice over: the leader's score is not
  known before it is registered, and delta is taken from the very runs it is applied to. A rule for the product
  must be chosen on the tune half and checked on the report half, and must always complete the leaders (their
  late improvements are the largest).

    .venv/bin/python Testing/Benchmarks/refinement_curves.py W [--save curves.json]
    .venv/bin/python Testing/Benchmarks/refinement_curves.py --load \
        Testing/Benchmarks/results_refinement_curves_s17.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from curve_tables import EVALUATIONS, allowances, extract, still_to_come_table, value_after


def read_runs(work: Path) -> list[dict]:
    """From the result.json files: [{run, hypotheses: [{labels, score, winner, curves: [[evaluations],
    [objective]] per start}]}]."""
    runs = []
    for path in sorted(work.glob("case*/*/out_*/result.json")):
        hyps = [h for h in (json.loads(path.read_text()).get("level_check") or {}).get("hypotheses", [])
                if h.get("refined") and h.get("start_curves")]
        if not hyps:
            continue
        best = min(h["score"] for h in hyps)
        runs.append({"run": "/".join(path.parts[-4:-1]), "hypotheses": [
            {"labels": h["labels"], "score": h["score"], "winner": h["score"] == best,
             "curves": [[c["evaluations"], [round(x, 5) for x in c["objective"]]] for c in h["start_curves"]]}
            for h in hyps]})
    return runs


def _at(curve: list, e: int) -> float | None:
    """The best objective after e evaluations (None before the first generation)."""
    return value_after(*curve, e)


def improvements(runs: list[dict]) -> dict:
    """{e: (every start's obj(e) - obj(end), the winners' starts' ones)}."""
    out = {e: ([], []) for e in EVALUATIONS}
    for run in runs:
        for h in run["hypotheses"]:
            for curve in h["curves"]:
                for e in EVALUATIONS:
                    value = _at(curve, e)
                    if value is not None:
                        out[e][0].append(value - curve[1][-1])
                        if h["winner"]:
                            out[e][1].append(value - curve[1][-1])
    return out


def oracle_savings(runs: list[dict], delta: dict) -> tuple[int, int]:
    """(evaluations saved, evaluations run) by the optimistic stopping rule of the module docstring."""
    saved = total = 0
    for run in runs:
        leader = min(h["score"] for h in run["hypotheses"])
        for h in run["hypotheses"]:
            for curve in h["curves"]:
                total += curve[0][-1]
                if h["winner"]:
                    continue
                stop = next((e for e in EVALUATIONS if (v := _at(curve, e)) is not None and v - delta[e] > leader),
                            None)
                saved += curve[0][-1] - stop if stop is not None else 0
    return saved, total


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, nargs="?", help="a bench_appearance --work folder")
    parser.add_argument("--load", type=Path, help="a stored extract (--save) instead")
    parser.add_argument("--save", type=Path, help="write the curves as a compact JSON extract")
    parser.add_argument("--safety", type=float, default=1.0,
                        help="stop only when a start trails by more than this times the largest improvement seen")
    parser.add_argument("--margin", type=float, default=0.0, help="... plus this (objective units)")
    args = parser.parse_args(argv)
    runs = extract(args.load, args.save, lambda: read_runs(args.work))
    found = improvements(runs)
    print(f"{len(runs)} runs, {sum(len(h['curves']) for r in runs for h in r['hypotheses'])} refinements")
    print(still_to_come_table(found, "improvement still to come", "every start", "the winners' starts"))
    saved, total = oracle_savings(runs, allowances(found, args.safety, args.margin))
    print(f"optimistic bound (a start stops once it trails the winner's final score by {args.safety:g} x the largest "
          f"improvement seen + {args.margin:g}): {saved} of {total} coarse-refinement evaluations saved "
          f"({saved / total:.0%})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
