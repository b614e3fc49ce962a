"""Replay three shortcuts of the appearance checks on recorded verdicts (stop 22: each was dropped).

Not a test: run it by hand on the JSON of ``bench_appearance.py`` runs (default: every ``results_appearance*.json``
beside this script)::

    .venv/bin/python Testing/Benchmarks/replay_polarity_shortcuts.py [FILE.json ...]

1. **The other polarity on the first one's best labelling only.** ``click_polarity`` registers every judged
   labelling under both polarities. The shortcut registers them all under a first polarity F, the other polarity O
   only at F's best labelling k*, and stops when that verdict is clear for F with a lead >= X. score(F) and fits(F)
   are unchanged (their rival is O at k*); score(O) can only be lower. Each recorded verdict at the clicks (its
   per-labelling GC and click mPDE, ``appearance.scores.at_clicks`` / ``on_mirror``) is judged again exactly,
   with either polarity first; a verdict is "changed" when the shortcut would stop on a (polarity, clear) that
   the full verdict does not give.
2. **The database's polarity when the clicks leave it unclear**: clicked runs whose polarity stayed unclear at the
   clicks, the database's leaning against the truth.
3. **No check on the mirrored image when the database finds the stored orientation clearly best**: the database's
   lead of the stored orientation over every other on mirrored displays, against the correctly displayed runs that
   ran the check.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from carmreg.logic.image.appearance import POLARITIES, verdict_at_clicks
from carmreg.logic.registration.level_confidence import landmark_limit_mm
from carmreg.logic.registration.pipeline import RegistrationParameters

HERE = Path(__file__).resolve().parent
LEADS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)


def runs(paths: list[Path]) -> list[dict]:
    """Every recorded run, each once (the same case, variant, mode and scores in several files count once)."""
    seen, out = set(), []
    for path in paths:
        for run in json.loads(path.read_text()).get("runs", []):
            a = run.get("appearance") or {}
            key = (run["case"], run.get("ct"), run["variant"], run["mode"], json.dumps(a.get("scores"), sort_keys=True))
            if key not in seen:
                seen.add(key)
                out.append(run)
    return out


def _evidence(sim: dict, mpde: dict, done: dict, rule) -> tuple[dict, dict]:
    """score(p), fits(p) as ``click_polarity._evidence`` gives them when only the labellings ``done[p]`` were
    registered under polarity p (a rival registration that is missing counts as none: the cap alone)."""
    scores, fits = {}, {}
    for p in POLARITIES:
        k = max(done[p], key=lambda i: sim[p][i])
        other = next(q for q in POLARITIES if q != p)
        rival = mpde[other][k] if k in done[other] else float("nan")
        scores[p], fits[p] = sim[p][k], bool(mpde[p][k] <= landmark_limit_mm(rival, rule))
    return scores, fits


def other_at_best_only(all_runs: list[dict], rule) -> list[str]:
    rows = {lead: {"tune": [0, 0], "report": [0, 0]} for lead in LEADS}  # [stopped early, verdict changed]
    for run in all_runs:
        scores = (run.get("appearance") or {}).get("scores") or {}
        half = "tune" if run["case"] % 2 == 0 else "report"
        for where in ("at_clicks", "on_mirror"):
            judged = scores.get(where)
            if not judged or "similarity" not in judged:
                continue
            sim, mpde = judged["similarity"], judged["mpde_mm"]
            n = len(sim[POLARITIES[0]])
            full = verdict_at_clicks(*_evidence(sim, mpde, {p: range(n) for p in POLARITIES}, rule))
            for first in POLARITIES:
                other = next(q for q in POLARITIES if q != first)
                best = max(range(n), key=lambda i: sim[first][i])
                seen, lead, clear = verdict_at_clicks(*_evidence(sim, mpde, {first: range(n), other: [best]}, rule))
                for x in LEADS:
                    if seen == first and clear and lead >= x:
                        rows[x][half][0] += 1
                        rows[x][half][1] += (seen, clear) != (full[0], full[2])
    lines = ["| stop when the first polarity leads by | tune: stopped early / verdict changed | report: stopped "
             "early / verdict changed |", "|---|---|---|"]
    lines += [f"| {x:.1f} | {r['tune'][0]} / {r['tune'][1]} | {r['report'][0]} / {r['report'][1]} |"
              for x, r in rows.items()]
    return lines


def database_when_unclear(all_runs: list[dict]) -> list[str]:
    counts = {"tune": [0, 0], "report": [0, 0]}  # [database right, database wrong]
    used = {"tune": [0, 0], "report": [0, 0]}  # the same for the polarity used (the clicks' leaning)
    for run in all_runs:
        a = run.get("appearance") or {}
        database = (a.get("scores") or {}).get("database")
        if run["mode"] == "none" or not (a.get("scores") or {}).get("at_clicks") or a.get("clear") is not False \
                or not database or not run.get("polarity_truth"):
            continue
        leaning = max(POLARITIES, key=lambda p: database[p])
        half = "tune" if run["case"] % 2 == 0 else "report"
        counts[half][leaning != run["polarity_truth"]] += 1
        used[half][a.get("polarity") != run["polarity_truth"]] += 1
    return [f"clicked runs left unclear at the clicks, right / wrong: the database's leaning: tune "
            f"{counts['tune'][0]} / {counts['tune'][1]}, report {counts['report'][0]} / {counts['report'][1]}; "
            f"the polarity used: tune {used['tune'][0]} / {used['tune'][1]}, report {used['report'][0]} / "
            f"{used['report'][1]}"]


def mirror_gate(all_runs: list[dict]) -> list[str]:
    mirrored, checked = [], []
    for run in all_runs:
        a = run.get("appearance") or {}
        orientation = a.get("orientation_scores")
        if not orientation or run["mode"] == "none":
            continue
        lead = orientation["as-stored"] - max(v for k, v in orientation.items() if k != "as-stored")
        if "mirrored" in run["variant"]:
            mirrored.append(lead)
        elif (a.get("scores") or {}).get("on_mirror"):
            checked.append(lead)
    return [f"database lead of the stored orientation: mirrored displays up to {max(mirrored):.3f} ({len(mirrored)} "
            f"runs); correctly displayed runs that ran the mirror check {min(checked):.3f} to {max(checked):.3f} "
            f"({len(checked)} runs)" if mirrored and checked else "no runs to compare"]


def main(argv: list[str]) -> int:
    paths = [Path(a) for a in argv] or sorted(HERE.glob("results_appearance*.json"))
    all_runs = runs(paths)
    rule = RegistrationParameters().identify.rule
    print(f"{len(all_runs)} recorded runs from {len(paths)} files\n")
    print("1. the other polarity at the first one's best labelling only\n")
    print("\n".join(other_at_best_only(all_runs, rule)))
    print("\n2. " + database_when_unclear(all_runs)[0])
    print("\n3. " + mirror_gate(all_runs)[0])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
