"""The no-click polarity's second opinion, without the image's shading, measured on every image of a half.

Not a test: run it by hand on appearance-benchmark case folders already registered without clicks
(``bench_appearance.py --modes none``: ``out_none/result.json`` and ``truth.json`` beside the X-ray)::

    .venv/bin/python Testing/Benchmarks/measure_without_shading.py /tmp/w/case0*/* --cache-dir /tmp/c \\
        --out /tmp/without_shading_tune.json

Without clicks, a polarity still unclear on an image taken as stored gets a second opinion
(``appearance_checks._polarity_without_shading``): the same image-alone search with every image compared without its
shading above ``WITHOUT_SHADING_MM`` (``image.shading``). Where it leads with the other polarity it is used, never
clear. Its danger is a wrong lead, so it is measured here on **every** image (``asked``: whether the run asked it,
as its ``result.json`` records), with the first verdict as the run recorded it. Printed: per image, and the counts:
where asked, the disagreements right / wrong; over every image, the second opinion's wrong leads and the largest.
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


def registered_without_clicks(folder: Path, cache_dir: str, stages: tuple = ("database",)):
    """(logic, state after ``stages``) of ``folder`` as the CLI ran it without clicks (its ``result.json``'s inputs
    and geometry)."""
    result = json.loads((folder / "out_none" / "result.json").read_text())
    inputs, g = result["inputs"], result["geometry"]
    xray = load_xray(inputs["xray"], sdd_mm=g["sdd_mm"], pixel_spacing_mm=g["pixel_spacing_mm"][0])
    ct, ct_lm = load_volume(inputs["ct"]), read_landmarks_3d(inputs["ct_landmarks"])
    logic = CarmRegLogic()
    state = logic.prepare(ct, ct_lm, xray, Landmarks2D([], np.zeros((0, 2))), RegistrationParameters(
        cache_dir=cache_dir))
    for name in stages:
        logic.run_stage(state, name)
    return logic, state


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
    logic, state = registered_without_clicks(folder, cache_dir)
    rows, cols = state.database.drrs.shape[2:]
    _, gc_by_storage = database_gc(state.xray.pixels, state.mask, state.database.drrs.reshape(-1, rows, cols),
                                   state.coarse_factor)
    unshaded = logic._appearance.polarity_from_image(state, gc_by_storage, without_shading_mm=WITHOUT_SHADING_MM)
    seen, gap = image_polarity(unshaded.scores)
    first = first_verdict(result)
    return {"case": int(folder.parent.name.removeprefix("case")), "variant": folder.name, "folder": str(folder),
            "truth": "bone-bright" if truth["bone_bright_displayed"] else "bone-dark", "first": first,
            "scores": unshaded.scores, "polarity": seen, "gap": gap}


def counts(rows: list[dict]) -> dict:
    """Where asked: the first verdict wrong, the second opinion disagreeing right / wrong. Over every image: the
    second opinion wrong, its largest wrong lead, and clear (at the first verdict's gap) and right."""
    asked = [r for r in rows if r["first"]["asked"]]
    disagree = [r for r in asked if r["polarity"] != r["first"]["polarity"]]
    wrong = [r for r in rows if r["polarity"] != r["truth"]]
    return {"images": len(rows), "asked": len(asked),
            "asked_first_wrong": sum(r["first"]["polarity"] != r["truth"] for r in asked),
            "asked_disagree_right": sum(r["polarity"] == r["truth"] for r in disagree),
            "asked_disagree_wrong": sum(r["polarity"] != r["truth"] for r in disagree),
            "second_wrong": len(wrong), "second_wrong_max_lead": max((r["gap"] for r in wrong), default=0.0),
            "second_clear_right": sum(r["gap"] >= CLEAR_REFINED_GC and r["polarity"] == r["truth"] for r in rows),
            "first_clear_right": sum(r["first"]["clear"] and r["first"]["polarity"] == r["truth"] for r in rows)}


def table(rows: list[dict]) -> str:
    """The per-image rows as a markdown table."""
    lines = ["| case | variant | true polarity | first verdict | asked | second opinion GC dark / bright "
             "| its verdict, gap |", "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["case"], r["variant"])):
        f, s = r["first"], r["scores"]
        lines.append(f"| {r['case']} | {r['variant']} | {r['truth']} | {f['polarity']}"
                     f"{'' if f['polarity'] == r['truth'] else ' WRONG'}{'' if f['clear'] else ' (unclear)'}, "
                     f"{f['gap']:.3f} | {'yes' if f['asked'] else ''} "
                     f"| {s['bone-dark']:.3f} / {s['bone-bright']:.3f} | {r['polarity']}"
                     f"{'' if r['polarity'] == r['truth'] else ' WRONG'}, {r['gap']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="*", type=Path, help="case/variant folders with out_none/result.json")
    parser.add_argument("--cache-dir", required=True)
    parser.add_argument("--out", type=Path, required=True, help="JSON of the measured rows (read back if it exists "
                                                                 "and no folder is given)")
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
    print(f"\n{counts(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
