"""Benchmark: CarmReg on the independent cases of ``../shared/data/independent-cases`` (another simulator's images).

Not a test, and never a place to choose a threshold (the cases' README says so): it reports how CarmReg fares on
X-rays it did not make. Each case is registered by ``carmreg register`` as a subprocess, with ``--sdd-mm`` and
``--pixel-spacing-mm`` only (the principal point is unknown to the user), the X-ray as given (16-bit PNG, bone
bright) and inverted inside its field (bone dark), in the cases' four modes: the clicks **unnamed**, named
**right**, named **one level off** (each name moved one level toward the feet), and **none** (``--no-clicks``: the
levels in view named from the image alone, never confident by design). The CT is the sample CT (the same chest
CT); the CT centroids are the cases' own (``ct_centroids_lps.json``), those inside the sample's crop.

Scoring as the cases' README says: project every visible level's centroid with the found and the true P; a level is
named right when its projection is nearer its own true position than any other level's; pose-PDE of the levels not
clicked in detector mm. A run is **right** when: unnamed, its assigned names are the truth; named right, the
names are confirmed (confident; otherwise they are *flagged*); one level off, the wrong names are not confident;
no clicks, every visible level is named right. Writes ``results_independent.json`` and prints the table::

    .venv/bin/python Testing/Benchmarks/bench_independent.py --out /tmp/independent [--modes named none]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
CASES = ROOT.parent / "shared" / "data" / "independent-cases"
SAMPLE_CT = ROOT / "Resources" / "SampleCase" / "ct.nrrd"
MODES = ("unnamed", "named", "one-level-off", "none")


def _project(P: np.ndarray, point: list) -> np.ndarray:
    h = P @ np.r_[point, 1.0]
    return h[:2] / h[2]


def prepare(case: Path, variant: str, mode: str, inside: dict, work: Path) -> list[str]:
    """Write the run's inputs into ``work``; the ``carmreg register`` arguments."""
    d = json.loads((case / "case.json").read_text())
    work.mkdir(parents=True, exist_ok=True)
    (work / "ct.json").write_text(json.dumps(inside))
    xray = case / "xray.png"
    if variant == "bone-dark":
        a = np.asarray(Image.open(xray)).astype(np.int64)
        Image.fromarray(np.where(a > 0, 65535 - a, 0).astype(np.uint16)).save(work / "xray.png")
        xray = work / "xray.png"
    clicks = d["xray_points_px"]
    clicks_args = ["--no-clicks"]
    if mode != "none":
        given = list(clicks.values()) if mode == "unnamed" else dict(clicks)
        if mode == "one-level-off":
            order = sorted(inside, key=lambda n: -inside[n][2])  # head to feet
            given = {order[order.index(k) + 1]: v for k, v in clicks.items()}
        (work / "clicks.json").write_text(json.dumps(given))
        clicks_args = ["--xray-landmarks", str(work / "clicks.json")]
    intr = d["intrinsics"]
    return ["register", "--ct", str(SAMPLE_CT), "--ct-landmarks", str(work / "ct.json"), "--xray", str(xray),
            *clicks_args, "--out", str(work / "out"),
            "--sdd-mm", str(intr["sdd_mm"]), "--pixel-spacing-mm", str(intr["pixel_spacing_mm"])]


def right(row: dict) -> bool:
    """Whether a scored run is right (module docstring)."""
    return {"unnamed": row["assigned"] == row["truth"], "named": row["status"] == "confident",
            "one-level-off": row["status"] != "confident", "none": row["all_named_right"]}[row["mode"]]


def score(case: Path, result: dict, inside: dict) -> dict:
    d = json.loads((case / "case.json").read_text())
    P, P_true = np.asarray(result["projection_matrix"]), np.asarray(d["gt"]["P"])
    true_uv = d["gt"]["true_uv_px"]
    visible = [lb for lb in d["visible"] if lb in inside]
    named_right = all(int(np.argmin([np.linalg.norm(_project(P, inside[lb]) - np.asarray(true_uv[o]))
                                     for o in visible])) == visible.index(lb) for lb in visible)
    unclicked = [float(np.linalg.norm(_project(P, inside[lb]) - _project(P_true, inside[lb])))
                 * d["intrinsics"]["pixel_spacing_mm"] for lb in visible if lb not in d["labelled"]]
    lc, ap = result.get("level_check") or {}, result.get("appearance") or {}
    return {"status": lc.get("status"), "margin": lc.get("margin"), "assigned": lc.get("assigned_labels"),
            "truth": d["labelled"], "all_named_right": named_right, "unclicked_pde_mm": unclicked,
            "polarity": ap.get("polarity"), "polarity_gap_gc": ap.get("clarity_gc"), "reasons": lc.get("reasons")}


def summarize(rows: list[dict]) -> str:
    lines = ["| mode | stored as | right | CONFIDENT and wrong | confident | proposed (wrong) | ambiguous | "
             "contradicted | polarity right | levels not clicked (detector mm): median / 95th pct / max |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for mode in MODES:
        for variant in ("bone-bright", "bone-dark"):
            rs = [r for r in rows if r["mode"] == mode and r["variant"] == variant and r.get("status")]
            if not rs:
                continue
            ok = [right(r) for r in rs]
            wrong_conf = sum(r["status"] == "confident" and not good for r, good in zip(rs, ok, strict=True))
            proposed = [good for r, good in zip(rs, ok, strict=True) if r["status"] == "proposed"]
            pol = sum(r["polarity"] == variant for r in rs)
            pde = np.concatenate([r["unclicked_pde_mm"] for r in rs]) if mode in ("unnamed", "named") \
                else np.array([])
            acc = f"{np.median(pde):.2f} / {np.percentile(pde, 95):.2f} / {pde.max():.2f}" if pde.size else "-"
            lines.append(f"| {mode} | {variant} | {sum(ok)} / {len(rs)} | {wrong_conf} | "
                         f"{sum(r['status'] == 'confident' for r in rs)} | "
                         f"{len(proposed)} ({len(proposed) - sum(proposed)}) | "
                         f"{sum(r['status'] == 'ambiguous' for r in rs)} | "
                         f"{sum(r['status'] == 'contradicted' for r in rs)} | {pol} / {len(rs)} | {acc} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/carmreg-independent"))
    parser.add_argument("--cache-dir", default="/tmp/carmreg-independent-cache")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    args = parser.parse_args(argv)
    if not CASES.is_dir():
        print(f"bench_independent: {CASES} is absent (it comes with ../shared)", file=sys.stderr)
        return 2
    sys.path.insert(0, str(ROOT))
    from carmreg.logic.io.volumes import load_volume

    ct = load_volume(SAMPLE_CT)
    centroids = json.loads((CASES / "ct_centroids_lps.json").read_text())
    inside = {k: v for k, v in centroids.items() if ct.contains_lps(np.asarray([v]))[0]}
    carmreg = str(Path(sys.executable).with_name("carmreg"))
    rows = []
    for case in sorted(p for p in CASES.iterdir() if (p / "case.json").is_file()):
        for mode in args.modes:
            for variant in ("bone-bright", "bone-dark"):
                work = args.out / f"{case.name}-{mode}-{variant}"
                cmd = [carmreg, *prepare(case, variant, mode, inside, work), "--cache-dir", args.cache_dir]
                t0 = time.perf_counter()
                done = subprocess.run(cmd, capture_output=True, text=True)
                row = {"case": case.name, "mode": mode, "variant": variant, "exit_code": done.returncode,
                       "seconds": time.perf_counter() - t0}
                result_path = work / "out" / "result.json"
                if result_path.is_file():
                    row.update(score(case, json.loads(result_path.read_text()), inside))
                rows.append(row)
                print(json.dumps(row), flush=True)
                (args.out / "results_independent.json").write_text(json.dumps(rows, indent=1))
    print(summarize(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
