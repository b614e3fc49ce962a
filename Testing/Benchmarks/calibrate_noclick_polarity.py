"""Choose the no-click polarity's clear gap (``appearance.CLEAR_REFINED_GC``) on the tune half of recorded runs.

Not a test: run it by hand on the JSON of ``bench_appearance.py --modes none`` (one file or several)::

    .venv/bin/python Testing/Benchmarks/calibrate_noclick_polarity.py \\
        Testing/Benchmarks/results_appearance_s13_noclicks_peaks_*.json

Without clicks the polarity is the one whose refined image-alone registration agrees better (GC); it is *clear*
when it leads the other by the threshold. Unclear, the same polarity is used, but no level answer is proposed
(``level_confidence.decide_image_only``: "ambiguous"). A threshold therefore changes only two things, both
judged again here exactly from what each run recorded (``result.json["appearance"]["scores"]["refined"]`` and its
status): whether a polarity verdict is called clear, and whether a proposed answer stays proposed. Runs whose
polarity the file stated are untouched (``decided_by`` not "image (refined)", or a file stating the polarity the
image agrees with, which is clear whatever the gap: ``appearance.decide_polarity``).

On the **tune** half (even case index) the thresholds giving the fewest clear and wrong polarity verdicts are
admissible; among them the one keeping the most clear and right verdicts wins (ties: the lower). The chosen and
the current thresholds are then counted on the **report** half, which took no part in the choice.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from carmreg.logic.image.appearance import CLEAR_REFINED_GC, image_polarity

GRID = tuple(round(0.01 * k, 2) for k in range(3, 31))
REFINED_BY_IMAGE = "image (refined)"


def noclick_runs(paths: list[Path]) -> list[dict]:
    """The no-click runs with a refined polarity verdict, from every file."""
    runs = []
    for path in paths:
        runs += [r for r in json.loads(path.read_text())["runs"]
                 if r.get("mode") == "none" and ((r.get("appearance") or {}).get("scores") or {}).get("refined")]
    return runs


def judged_again(run: dict, threshold: float) -> tuple[bool, bool, str]:
    """(polarity right, polarity clear, status) of ``run`` had the clear gap been ``threshold``."""
    a = run["appearance"]
    right = a["polarity"] == run["polarity_truth"]
    if a.get("decided_by") != REFINED_BY_IMAGE or "as the file states" in a.get("note", ""):
        return right, bool(a.get("clear")), run["status"]
    _, gap = image_polarity(a["scores"]["refined"])
    clear = gap >= threshold
    status = "ambiguous" if run["status"] == "proposed" and a.get("clear") and not clear else run["status"]
    return right, clear, status


def counts(runs: list[dict], threshold: float) -> dict:
    c = {"runs": len(runs), "clear_wrong": 0, "clear_right": 0, "proposed_right": 0, "proposed_wrong": 0}
    for run in runs:
        right, clear, status = judged_again(run, threshold)
        c["clear_wrong"] += clear and not right
        c["clear_right"] += clear and right
        if status == "proposed":
            c["proposed_right" if run.get("answer_right") else "proposed_wrong"] += 1
    return c


def choose(tune: list[dict]) -> float:
    """Fewest clear and wrong verdicts, then most clear and right ones, then the lower threshold."""
    def rank(threshold: float) -> tuple:
        c = counts(tune, threshold)
        return c["clear_wrong"], -c["clear_right"], threshold

    return min(GRID, key=rank)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", nargs="+", type=Path, help="bench_appearance JSON file(s) with --modes none")
    args = parser.parse_args(argv)
    runs = noclick_runs(args.results)
    tune = [r for r in runs if r["case"] % 2 == 0]
    report = [r for r in runs if r["case"] % 2 == 1]
    if not tune:
        print("no no-click runs of the tune half in these files", file=sys.stderr)
        return 2
    chosen = choose(tune)
    print(f"{len(runs)} no-click runs ({len(tune)} tune, {len(report)} report); current {CLEAR_REFINED_GC}, "
          f"chosen on the tune half {chosen}\n")
    print("| clear gap | half | polarity clear and wrong | clear and right | proposed and right | proposed and wrong |")
    print("|---|---|---|---|---|---|")
    for threshold in sorted({0.05, 0.08, 0.10, chosen, 0.15, 0.20, CLEAR_REFINED_GC}):
        for half, subset in (("tune", tune), ("report", report)):
            c = counts(subset, threshold)
            print(f"| {threshold:.2f} | {half} | {c['clear_wrong']} / {c['runs']} | {c['clear_right']} | "
                  f"{c['proposed_right']} | {c['proposed_wrong']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
