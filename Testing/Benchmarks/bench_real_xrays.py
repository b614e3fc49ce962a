"""Benchmark: real vendor X-rays that do not show the CT's spine, registered to the sample CT (never confident).

Not a test. The two real clinical files of ``../shared/data/real-xray-dicom`` (no CT of their patients exists)
are registered to the sample case's chest CT by ``carmreg register`` as a subprocess, as a user who loaded the
wrong image would run it:

- ``siemens_rf_fluoro.dcm``, a SIEMENS RF fluoroscopy frame of a **shoulder** (humeral head, clavicle, a K-wire;
  no vertebra in view). The file has no distances and no pixel spacing, so the user's guess for a 9-inch
  intensifier is given (``--sdd-mm 1000 --pixel-spacing-mm 0.45``). Modes: **none** (``--no-clicks``), and
  ``PLACEMENTS`` sets of three clicks drawn at random (seeded) where a user might put them - a line of three
  points 25-40 mm apart, within 20 degrees of the image's vertical, inside the central 60 % of the image -
  given **unnamed** and **named** (three consecutive levels of the CT drawn at random). There is no vertebra to
  name: a run is *right* when it is not CONFIDENT (ambiguous, contradicted, proposed or refused), and a
  CONFIDENT answer is a confident wrong one.
- ``cr_monochrome1_jpeg.dcm``, a KONICA MINOLTA CR chest radiograph (MONOCHROME1, 0.175 mm) of **another
  patient**: its vertebrae are real but not the CT's. Mode **none** with a chest stand's distance
  (``--sdd-mm 1800``). No ground truth: the status and the levels proposed are recorded, not scored.

Each run's seconds are the whole process with the DRR database cached (the first run of each X-ray builds it:
those are marked ``built_database``). Writes ``results_real_xrays.json`` into ``--out`` and prints a table::

    .venv/bin/python Testing/Benchmarks/bench_real_xrays.py --out /tmp/real-xrays
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "data" / "real-xray-dicom"
SAMPLE = ROOT / "Resources" / "SampleCase"
SHOULDER, CHEST = "siemens_rf_fluoro.dcm", "cr_monochrome1_jpeg.dcm"
SHOULDER_PIXEL_MM = 0.45  # the user's guess for a 9-inch intensifier's 512 px (the file gives none)
GEOMETRY = {SHOULDER: ["--sdd-mm", "1000", "--pixel-spacing-mm", str(SHOULDER_PIXEL_MM)], CHEST: ["--sdd-mm", "1800"]}
PLACEMENTS = 5
SEED = 52


def click_placements(size_px: tuple[int, int], pixel_mm: float, n: int, seed: int) -> list[np.ndarray]:
    """``n`` sets of three clicks (3, 2) (column, row) px, head to feet (module docstring): centre uniform in the
    central 60 % of the image (columns, rows) ``size_px``, direction within 20 degrees of the image's vertical,
    spacing 25-40 mm."""
    rng = np.random.default_rng(seed)
    cols, rows = size_px
    out = []
    for _ in range(n):
        centre = np.array([rng.uniform(0.2, 0.8) * cols, rng.uniform(0.2, 0.8) * rows])
        angle = math.radians(rng.uniform(-20.0, 20.0))
        step_px = rng.uniform(25.0, 40.0) / pixel_mm
        direction = np.array([math.sin(angle), math.cos(angle)])  # +row = toward the feet
        out.append(centre + np.outer([-1.0, 0.0, 1.0], direction) * step_px)
    return out


def ct_levels() -> list[str]:
    """The sample CT's levels, head to feet (its centroids' names, in their file's order)."""
    doc = json.loads((SAMPLE / "ct_centroids.mrk.json").read_text())
    return [p["label"] for p in doc["markups"][0]["controlPoints"]]


def runs(size_px: tuple[int, int]) -> list[dict]:
    """Every run: {"xray", "mode", "placement", "clicks"} (clicks: None, a list, or {name: [column, row]})."""
    rng = np.random.default_rng(SEED + 1)
    levels = ct_levels()
    todo = [{"xray": SHOULDER, "mode": "none", "placement": None, "clicks": None}]
    for k, uv in enumerate(click_placements(size_px, SHOULDER_PIXEL_MM, PLACEMENTS, SEED)):
        first = int(rng.integers(0, len(levels) - 2))
        named = {name: p.tolist() for name, p in zip(levels[first:first + 3], uv, strict=True)}
        todo += [{"xray": SHOULDER, "mode": "unnamed", "placement": k, "clicks": uv.tolist()},
                 {"xray": SHOULDER, "mode": "named", "placement": k, "clicks": named}]
    return todo + [{"xray": CHEST, "mode": "none", "placement": None, "clicks": None}]


def run_one(run: dict, work: Path, cache_dir: str) -> dict:
    """``carmreg register`` on one run; the row of the table."""
    work.mkdir(parents=True, exist_ok=True)
    clicks = ["--no-clicks"]
    if run["clicks"] is not None:
        (work / "clicks.json").write_text(json.dumps(run["clicks"]))
        clicks = ["--xray-landmarks", str(work / "clicks.json")]
    cmd = [str(Path(sys.executable).with_name("carmreg")), "register", "--ct", str(SAMPLE / "ct.nrrd"),
           "--ct-landmarks", str(SAMPLE / "ct_centroids.mrk.json"), "--xray", str(REAL / run["xray"]), *clicks,
           "--out", str(work / "out"), "--cache-dir", cache_dir, *GEOMETRY[run["xray"]]]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    row = {**run, "exit_code": done.returncode, "seconds": time.perf_counter() - t0,
           "stderr": done.stderr.strip().splitlines()[-1:] if done.returncode not in (0, 1) else []}
    result = work / "out" / "result.json"
    if result.is_file():
        doc = json.loads(result.read_text())
        lc, ap = doc.get("level_check") or {}, doc.get("appearance") or {}
        row.update(status=lc.get("status"), margin=lc.get("margin"), assigned=lc.get("assigned_labels"),
                   reasons=lc.get("reasons"), polarity=ap.get("polarity"), polarity_clear=ap.get("clear"),
                   agreement_gc=((lc.get("checks") or {}).get("image_agreement") or {}).get("gc"),
                   levels_in_view=[lv["label"] for lv in doc.get("levels") or [] if lv.get("in_image")])
    return row


def summarize(rows: list[dict]) -> str:
    """The markdown table: per X-ray and mode, the statuses and the seconds."""
    lines = ["| X-ray | mode | runs | CONFIDENT (wrong: no vertebra in view) | ambiguous | contradicted | proposed | "
             "refused / failed | seconds, median (max) |", "|---|---|---|---|---|---|---|---|---|"]
    for xray in (SHOULDER, CHEST):
        for mode in ("none", "unnamed", "named"):
            rs = [r for r in rows if r["xray"] == xray and r["mode"] == mode]
            if not rs:
                continue
            count = {s: sum(r.get("status") == s for r in rs) for s in ("confident", "ambiguous", "contradicted",
                                                                         "proposed")}
            seconds = [r["seconds"] for r in rs if not r.get("built_database")]
            times = f"{np.median(seconds):.1f} ({max(seconds):.1f})" if seconds else "-"
            lines.append(f"| {xray} | {mode} | {len(rs)} | {count['confident']} | {count['ambiguous']} | "
                         f"{count['contradicted']} | {count['proposed']} | {len(rs) - sum(count.values())} | "
                         f"{times} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/carmreg-real-xrays"))
    parser.add_argument("--cache-dir", default="/tmp/carmreg-real-xrays-cache")
    args = parser.parse_args(argv)
    if not REAL.is_dir():
        print(f"bench_real_xrays: {REAL} is absent (it comes with ../shared)", file=sys.stderr)
        return 2
    import pydicom

    shoulder = pydicom.dcmread(REAL / SHOULDER, stop_before_pixels=True)
    rows, built = [], set()
    for number, run in enumerate(runs((int(shoulder.Columns), int(shoulder.Rows))), 1):
        row = run_one(run, args.out / f"{number:02d}-{Path(run['xray']).stem}-{run['mode']}", args.cache_dir)
        row["built_database"] = run["xray"] not in built  # the first run of each X-ray builds its database
        built.add(run["xray"])
        rows.append(row)
        print(json.dumps({key: value for key, value in row.items() if key != "reasons"}), flush=True)
        (args.out / "results_real_xrays.json").write_text(json.dumps(rows, indent=1))
    print(summarize(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
