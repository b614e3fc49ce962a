"""Choose the GC a registration needs before its keeping the clicks fitted counts for its polarity
(``appearance.FITTED_MIN_GC``) on the tune half of recorded verdicts.

Not a test: run it by hand on the JSON of ``bench_appearance.py`` runs with clicks (default: every
``results_appearance*.json`` beside this script)::

    .venv/bin/python Testing/Benchmarks/calibrate_fitted_gc.py [--out DIR] [FILE.json ...]

With clicks the polarity is judged where the clicks put the CT (``verdict_at_clicks``): the polarity whose best
registration keeps the clicks fitted is preferred, then the higher GC. A registration on the clicks may agree with
the image not at all (GC about 0: the clicks hold it there whatever the image says), so keeping them counts only
from a GC floor. Every recorded verdict (``result.json["appearance"]["scores"]`` ``at_clicks`` and ``on_mirror``:
the scores and the fits) is judged again exactly at each floor of ``GRID``; pairs recorded more than once (the same
run in several files) count once. A floor below ``MIN_CLICKS_GC`` never changes a clear verdict (clear needs the
winner fitted with GC >= ``MIN_CLICKS_GC``, preferred at any such floor), only which polarity an unclear verdict
uses, so the counts are: verdicts wrong, and among those the floor changed, set right and set wrong.

On the **tune** half (even case index) the floors that set no verdict wrong are admissible (a floor must not turn a
right polarity wrong); among them the one setting the most right wins, ties to the lowest. The chosen floor is then
counted on the **report** half, which took no part in the choice.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from carmreg.logic.image.appearance import FITTED_MIN_GC, verdict_at_clicks

GRID = (0.0, 0.02, 0.05, 0.10, 0.15, 0.20, 0.25)
HERE = Path(__file__).resolve().parent


def recorded_verdicts(paths: list[Path]) -> list[dict]:
    """One entry per distinct recorded (run, where, scores, fits): half, scores, fits, the true polarity."""
    seen, out = set(), []
    for path in paths:
        for run in json.loads(path.read_text()).get("runs", []):
            scores = ((run.get("appearance") or {}).get("scores")) or {}
            for where in ("at_clicks", "on_mirror"):
                judged = scores.get(where)
                if not judged or "fits" not in judged or not run.get("polarity_truth"):
                    continue
                key = (run["case"], run.get("ct"), run["variant"], run["mode"], where,
                       json.dumps(judged["scores"], sort_keys=True), json.dumps(judged["fits"], sort_keys=True))
                if key not in seen:
                    seen.add(key)
                    out.append({"half": "tune" if run["case"] % 2 == 0 else "report", "scores": judged["scores"],
                                "fits": judged["fits"], "truth": run["polarity_truth"], "key": key[:5],
                                "file": path.name})
    return out


def counts(verdicts: list[dict], floor: float) -> dict:
    c = {"verdicts": len(verdicts), "wrong": 0, "clear_wrong": 0, "set_right": 0, "set_wrong": 0}
    for v in verdicts:
        used, _, clear = verdict_at_clicks(v["scores"], v["fits"], floor)
        before = verdict_at_clicks(v["scores"], v["fits"], 0.0)[0]
        c["wrong"] += used != v["truth"]
        c["clear_wrong"] += clear and used != v["truth"]
        if used != before:
            c["set_right" if used == v["truth"] else "set_wrong"] += 1
    return c


def choose(tune: list[dict]) -> float:
    """The floor of ``GRID`` setting no tune verdict wrong and the most right; ties: the lowest."""
    admissible = [(counts(tune, f), f) for f in GRID]
    admissible = [(c["set_right"], -f) for c, f in admissible if c["set_wrong"] == 0]
    return -max(admissible)[1]


def table(verdicts: list[dict], chosen: float) -> list[str]:
    lines = ["| floor | half | verdicts | wrong | clear and wrong | changed from floor 0: set right / set wrong |",
             "|---|---|---|---|---|---|"]
    for floor in GRID:
        for half in ("tune", "report"):
            c = counts([v for v in verdicts if v["half"] == half], floor)
            mark = " (chosen)" if floor == chosen else " (current)" if floor == FITTED_MIN_GC else ""
            lines.append(f"| {floor:.2f}{mark} | {half} | {c['verdicts']} | {c['wrong']} | {c['clear_wrong']} | "
                         f"{c['set_right']} / {c['set_wrong']} |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="*", type=Path)
    parser.add_argument("--out", type=Path, help="write results_fitted_gc.md here")
    args = parser.parse_args(argv)
    paths = args.files or sorted(HERE.glob("results_appearance*.json"))
    verdicts = recorded_verdicts(paths)
    tune = [v for v in verdicts if v["half"] == "tune"]
    if not tune:
        print("calibrate_fitted_gc: error: no recorded tune-half verdict at the clicks in these files", file=sys.stderr)
        return 2
    chosen = choose(tune)
    changed = [f"- {v['half']} {v['key']}: scores {v['scores']}, fits {v['fits']}, truth {v['truth']} ({v['file']})"
               for v in verdicts if verdict_at_clicks(v["scores"], v["fits"], chosen)[0]
               != verdict_at_clicks(v["scores"], v["fits"], 0.0)[0]]
    lines = [f"# The GC before keeping the clicks counts (`FITTED_MIN_GC`): replayed on {len(verdicts)} recorded "
             f"verdicts ({len(tune)} tune, {len(verdicts) - len(tune)} report) from {len(paths)} files", "",
             f"Chosen on the tune half: **{chosen:.2f}** (none set wrong, the most set right, then the lowest).",
             "",
             *table(verdicts, chosen), "", f"Verdicts the chosen floor changes ({len(changed)}):", "", *changed]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        (args.out / "results_fitted_gc.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
