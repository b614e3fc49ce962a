"""Choose the confidence rule's thresholds on the tune half of recorded benchmark runs; report them on the other.

Not a test: run it by hand on the JSON of ``bench_appearance.py`` (or several)::

    .venv/bin/python Testing/Benchmarks/calibrate_confidence.py Testing/Benchmarks/results_appearance.json

Every run records the numbers the rule judges (``result.json["level_check"]``: the margin and the checks'
evidence), so a run can be judged again under other thresholds exactly as CarmReg would have judged it
(``level_confidence.judge``, the product's own rule, not a copy; the appearance by today's
``trusted_appearance``). Grid: margin, GC floor, landmark ratio and
slack. On the **tune** half (even case index) a rule is admissible when it gives no CONFIDENT wrong answer; among
those, the one with the most useful answers (confident and right, plus names one level off contradicted, less
right names contradicted) wins, ties going to the stricter rule. The chosen and the current rule are then counted
on the **report** half, which took no part in the choice. Image-only runs (no clicks) are left out: their best is
"proposed", never confident.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import asdict
from pathlib import Path

from carmreg.logic.image.appearance import trusted_appearance
from carmreg.logic.registration.level_confidence import ConfidenceRule, Evidence, judge

GRID = {"margin": (0.01, 0.015, 0.02, 0.03, 0.04, 0.05),
        "min_similarity": (0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50),
        "landmark_ratio": (1.25, 1.5, 2.0),
        "landmark_slack_mm": (0.25, 0.5, 1.0)}


def judged(runs: list[dict]) -> list[dict]:
    """The runs the rule can judge again: a level check with its margin and evidence recorded."""
    return [r for r in runs if r.get("mode") != "none" and r.get("checks") and r.get("margin") is not None
            and "image_agreement" in r["checks"]]


def evidence(run: dict) -> Evidence:
    """The run's recorded evidence, its appearance judged by today's rule (``trusted_appearance``) when the run
    recorded what that rule reads."""
    e = Evidence.from_checks(run["checks"])
    a = run.get("appearance") or {}
    if {"clear", "orientation", "orientation_clear"} <= set(a):
        e.appearance_ok = trusted_appearance(a["clear"], a["orientation"], a["orientation_clear"])
    return e


def counts(runs: list[dict], rule: ConfidenceRule) -> dict:
    """Status against right / wrong under ``rule``: confident_wrong is the number that must be 0."""
    out = {"runs": len(runs), "confident_right": 0, "confident_wrong": 0, "contradicted_wrong_names": 0,
           "contradicted_right_names": 0, "ambiguous": 0}
    for r in runs:
        status, _, _ = judge(float(r["margin"]), evidence(r), rule)
        if status == "confident":
            out["confident_right" if r["answer_right"] else "confident_wrong"] += 1
        elif status == "contradicted":
            out["contradicted_right_names" if r["answer_right"] else "contradicted_wrong_names"] += 1
        else:
            out["ambiguous"] += 1
    out["useful"] = out["confident_right"] + out["contradicted_wrong_names"]
    return out


def strictness(rule: ConfidenceRule) -> tuple:
    return (rule.margin, rule.min_similarity, -rule.landmark_ratio, -rule.landmark_slack_mm)


def choose(tune: list[dict]) -> tuple[ConfidenceRule, dict]:
    best = None
    for values in itertools.product(*GRID.values()):
        rule = ConfidenceRule(**dict(zip(GRID, values, strict=True)))
        c = counts(tune, rule)
        if c["confident_wrong"]:
            continue
        key = (c["useful"] - c["contradicted_right_names"], strictness(rule))
        if best is None or key > best[0]:
            best = (key, rule, c)
    if best is None:
        raise SystemExit("no rule in the grid gives zero confident wrong answers on the tune half")
    return best[1], best[2]


def margins(runs: list[dict]) -> dict:
    """Where the thresholds could sit: the smallest margin and GC of the runs judged confident and right, and
    the largest margin of the runs whose winner was a wrong labelling (what a threshold must stay above)."""
    right = [r for r in runs if r["mode"] == "unnamed" and r["answer_right"] and r["margin"] is not None]
    wrong = [r for r in runs if r["mode"] == "unnamed" and not r["answer_right"] and r["margin"] is not None]
    gc = [r["checks"]["image_agreement"]["gc"] for r in right]
    return {"right_min_margin": min((r["margin"] for r in right), default=None),
            "right_min_gc": min(gc, default=None),
            "wrong_winner_max_margin": max((r["margin"] for r in wrong), default=None),
            "wrong_winner_max_gc": max((r["checks"]["image_agreement"]["gc"] for r in wrong), default=None)}


def flat_ranges(tune: list[dict], base: ConfidenceRule) -> dict:
    """For each threshold alone (the others at ``base``): the grid values that give as many useful answers on
    the tune half as ``base`` and no confident wrong one."""
    want = counts(tune, base)["useful"]
    out = {}
    for name, values in GRID.items():
        keep = []
        for v in values:
            c = counts(tune, ConfidenceRule(**{**asdict(base), name: v}))
            if not c["confident_wrong"] and c["useful"] >= want:
                keep.append(v)
        out[name] = keep
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", type=Path, help="bench_appearance JSON file(s)")
    args = parser.parse_args(argv)
    runs = judged([r for path in args.results for r in json.loads(path.read_text())["runs"]])
    tune, report = [r for r in runs if r["half"] == "tune"], [r for r in runs if r["half"] == "report"]
    chosen, on_tune = choose(tune)
    current = ConfidenceRule()
    doc = {"grid": GRID, "chosen": asdict(chosen), "current": asdict(current),
           "flat_ranges_on_tune": flat_ranges(tune, current),
           "margins": {"tune": margins(tune), "report": margins(report)},
           "tune": {"chosen": on_tune, "current": counts(tune, current)},
           "report": {"chosen": counts(report, chosen), "current": counts(report, current)}}
    json.dump(doc, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
