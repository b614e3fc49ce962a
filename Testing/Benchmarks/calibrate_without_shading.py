"""Check the no-click second opinion's clear gap (the first verdict's, ``CLEAR_REFINED_GC``) on the tune half.

Not a test: run it by hand on appearance-benchmark case folders already registered without clicks
(``bench_appearance.py --modes none``: ``out_none/result.json`` and ``truth.json`` beside the X-ray)::

    .venv/bin/python Testing/Benchmarks/calibrate_without_shading.py /tmp/w/case0*/* --cache-dir /tmp/c \\
        --out /tmp/without_shading_tune.json

Without clicks, a polarity still unclear on an image taken as stored gets a second opinion
(``pipeline._polarity_without_shading``): the same image-alone search with every image compared without its
shading above ``WITHOUT_SHADING_MM`` (``image.shading``), its verdict taken when it leads by the clear gap. A wrong
polarity called clear there is the danger (stop 28's partial experiments pushed a large patient's wrong polarity
past the first verdict's gap), so the gap is judged on the second opinion measured on **every** image of the tune
half (even case index), not only on those it was asked about (``asked``: the run recorded it). Printed: the
smallest gap on ``GRID`` above every wrong verdict's lead that keeps the most right verdicts clear where asked
(``choose``), and the counts at the gap in use. Stop 29 kept the first verdict's gap (0.22) rather than the
smallest admissible (0.09): the tune half's wrong second opinions led by at most 0.081 (a large patient; a
mirrored display 0.059), two samples of how far a wrong one can lead, and every right one asked about but a
mirrored display's led by 0.31 or more. Counted again, unchanged, on the report half (``--threshold``).
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from carmreg.logic.image.appearance import CLEAR_REFINED_GC, WITHOUT_SHADING_MM, database_gc, image_polarity
from carmreg.logic.io.landmarks import Landmarks2D, read_landmarks_3d
from carmreg.logic.io.volumes import load_volume
from carmreg.logic.io.xray import load_xray
from carmreg.logic.registration.pipeline import CarmRegLogic
from carmreg.logic.registration.state import RegistrationParameters

GRID = tuple(round(0.01 * k, 2) for k in range(5, 41))


def state_after_database(folder: Path, cache_dir: str):
    """(logic, state after the database stage, {storage: GC map}) of ``folder`` as the CLI ran it without clicks."""
    result = json.loads((folder / "out_none" / "result.json").read_text())
    inputs, g = result["inputs"], result["geometry"]
    xray = load_xray(inputs["xray"], sdd_mm=g["sdd_mm"], pixel_spacing_mm=g["pixel_spacing_mm"][0])
    ct, ct_lm = load_volume(inputs["ct"]), read_landmarks_3d(inputs["ct_landmarks"])
    logic = CarmRegLogic()
    state = logic.prepare(ct, ct_lm, xray, Landmarks2D([], np.zeros((0, 2))), RegistrationParameters(
        cache_dir=cache_dir))
    logic.run_stage(state, "database")
    rows, cols = state.database.drrs.shape[2:]
    _, gc_by_storage = database_gc(xray.pixels, state.mask, state.database.drrs.reshape(-1, rows, cols),
                                   state.coarse_factor)
    return logic, state, gc_by_storage


def first_verdict(result: dict) -> dict:
    """The first no-click verdict a run recorded (its plain refined scores, ``scores["without_clicks"]``) and
    whether the pipeline then asked the second opinion (``scores["without_clicks_without_shading"]``)."""
    a = result.get("appearance") or {}
    recorded = a.get("scores") or {}
    plain = (recorded.get("without_clicks") or {}).get("scores")
    polarity, gap = image_polarity(plain) if plain else (a.get("polarity"), float("nan"))
    return {"polarity": polarity, "gap": gap, "clear": bool(gap >= CLEAR_REFINED_GC),
            "asked": "without_clicks_without_shading" in recorded}


def measure(folder: Path, cache_dir: str) -> dict:
    """One image: its first verdict (as recorded) and the second opinion's scores, measured here."""
    result = json.loads((folder / "out_none" / "result.json").read_text())
    truth = json.loads((folder / "truth.json").read_text())
    logic, state, gc_by_storage = state_after_database(folder, cache_dir)
    unshaded = logic._polarity_from_image(state, gc_by_storage, without_shading_mm=WITHOUT_SHADING_MM)
    seen, gap = image_polarity(unshaded.scores)
    first = first_verdict(result)
    return {"case": int(folder.parent.name.removeprefix("case")), "variant": folder.name, "folder": str(folder),
            "truth": "bone-bright" if truth["bone_bright_displayed"] else "bone-dark", "first": first,
            "second_opinion_runs": first["asked"], "scores": unshaded.scores, "polarity": seen, "gap": gap}


def counts(rows: list[dict], threshold: float) -> dict:
    """Clear wrong / clear right second opinions over every image, and over those it would be asked about."""
    c = {"images": len(rows), "clear_wrong": 0, "clear_right": 0, "asked": 0, "asked_clear_right": 0,
         "asked_clear_wrong": 0, "asked_first_wrong": 0}
    for r in rows:
        clear, right = r["gap"] >= threshold, r["polarity"] == r["truth"]
        c["clear_wrong"] += clear and not right
        c["clear_right"] += clear and right
        if r["second_opinion_runs"]:
            c["asked"] += 1
            c["asked_first_wrong"] += r["first"]["polarity"] != r["truth"]
            c["asked_clear_right"] += clear and right
            c["asked_clear_wrong"] += clear and not right
    return c


def choose(tune: list[dict]) -> float:
    """No clear wrong verdict on any tune image, then the most clear right ones where asked, then the lower."""
    def rank(threshold: float) -> tuple:
        c = counts(tune, threshold)
        return c["clear_wrong"], -c["asked_clear_right"], -c["clear_right"], threshold

    return min(GRID, key=rank)


def table(rows: list[dict]) -> str:
    """The per-image rows as a markdown table."""
    lines = ["| case | variant | true polarity | first verdict | asked | second opinion GC dark / bright "
             "| its verdict, gap |", "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["case"], r["variant"])):
        f, s = r["first"], r["scores"]
        lines.append(f"| {r['case']} | {r['variant']} | {r['truth']} | {f['polarity']}"
                     f"{'' if f['polarity'] == r['truth'] else ' WRONG'}{'' if f['clear'] else ' (unclear)'}, "
                     f"{f['gap']:.3f} | {'yes' if r['second_opinion_runs'] else ''} "
                     f"| {s['bone-dark']:.3f} / {s['bone-bright']:.3f} | {r['polarity']}"
                     f"{'' if r['polarity'] == r['truth'] else ' WRONG'}, {r['gap']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="*", type=Path, help="case/variant folders with out_none/result.json")
    parser.add_argument("--cache-dir", required=True)
    parser.add_argument("--out", type=Path, required=True, help="JSON of the measured rows (read back if it exists "
                                                                 "and no folder is given)")
    parser.add_argument("--threshold", type=float, help="count this gap instead of choosing one (report half)")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args(argv)
    if args.folders:
        folders = [f for f in args.folders if (f / "out_none" / "result.json").is_file()]
        with ProcessPoolExecutor(args.jobs) as pool:
            rows = list(pool.map(measure, folders, [args.cache_dir] * len(folders)))
        args.out.write_text(json.dumps({"rows": rows}, indent=1))
    else:
        rows = json.loads(args.out.read_text())["rows"]
    print(table(rows))
    chosen = args.threshold if args.threshold is not None else choose(rows)
    for name, threshold in (("chosen" if args.threshold is None else "given", chosen),
                            ("current", CLEAR_REFINED_GC)):
        print(f"\n{name} gap {threshold:.2f}: {counts(rows, threshold)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
