"""Benchmark: per-stage time and accuracy of the registration on realistic simulated cases.

Not a test: run it by hand and paste its table into the README::

    .venv/bin/python Testing/Benchmarks/bench_registration.py --cases 24 --out Testing/Benchmarks

Each case: the sample CT, a random C-arm pose around a random labelled level (+-2 levels, +-20 mm lateral,
+-50 mm depth, +-10 deg), realism parameters drawn from the literature ranges (``simulate.sample_options``:
kVp bone contrast, scatter, photons, vignetting, pincushion and S-distortion, K-wires, per-level motion), three
adjacent levels clicked with ~0.9 mm noise. The database is built once (preoperative) and cached.
Accuracy is measured on the levels the fit did NOT use (``Logic.evaluation``).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from carmreg.logic.io.landmarks import read_landmarks_3d
from carmreg.logic.io.volumes import load_volume
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.fine import FineParameters
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters
from carmreg.logic.resources import sample_case
from carmreg.logic.similarity.metrics import METRICS
from carmreg.logic.simulation.evaluation import evaluate
from carmreg.logic.simulation.options import SimulationOptions, default_geometry, sample_options
from carmreg.logic.simulation.scene import random_pose
from carmreg.logic.simulation.simulator import simulate_case


def load_case():
    case = sample_case()
    ct = load_volume(case["ct"])
    labels = np.asarray(load_volume(case["vertebrae"]).hu).astype(np.uint8)
    return ct, labels, read_landmarks_3d(case["ct_landmarks"])


def simulate(ct, labels, centroids, seed: int, size_px: int):
    """One realistic case: (simulation, X-ray, the case's random generator for any further draws). The aim level
    leaves +-2 levels of room inside the labelled range (+-1 on a short one)."""
    rng = np.random.default_rng(1000 + seed)
    base = SimulationOptions(size_px=(size_px, size_px), pixel_spacing_mm=0.25 * 1024 / size_px)
    options = sample_options(rng, base)
    geometry = default_geometry(ct, options)
    names = centroids.sorted().labels
    inner = names[2:-2] if len(names) > 5 else names[1:-1]
    pose = random_pose(rng, options, centroids, inner[int(rng.integers(len(inner)))], geometry=geometry)
    sim = simulate_case(ct, labels, centroids, geometry, pose, options, seed=seed)
    xray = XrayImage(sim.pixels.astype(np.float32), geometry.intrinsics, geometry.sod_mm, True, f"sim-{seed}")
    return sim, xray, rng


def run_case(ct, centroids, sim, xray, params, clicks=None):
    logic = CarmRegLogic()
    t0 = time.perf_counter()
    result = logic.register(ct, centroids, xray, clicks or sim.clicks, params)
    total = time.perf_counter() - t0
    truth = sim.ground_truth()
    fitted = {lv["label"] for lv in result.levels if lv["fitted"]}
    score = evaluate(result.projection_matrix, centroids.as_dict(), truth, fitted,
                     shown=result.geometry.intrinsics.distortion.distort)
    stages = {s.name: {"mpde_mm": s.mpde_mm, "seconds": s.seconds, **s.extra} for s in result.stages}
    fine_pose = next(s.pose for s in result.stages if s.name == "fine")
    landmark_score = evaluate(result.geometry.projection_matrix(fine_pose), centroids.as_dict(), truth, fitted)
    return {"seed": sim.seed, "ok": result.ok, "total_s": total, "stages": stages, "score": score,
            "landmark_score": landmark_score,
            "level_check": result.level_check.to_dict() if result.level_check else None,
            "pose_true": sim.pose.as_dict(), "pose_found": result.pose.as_dict(),
            "spatial_per_metric": stages["spatial"]["per_metric"]}


def shifted_clicks(sim, centroids, shift: int = 1):
    """The same clicks with every label moved one level caudally (T10, T11, T12 -> T11, T12, L1)."""
    from carmreg.logic.io.landmarks import Landmarks2D
    from carmreg.logic.registration.labellings import shifted_labels

    labels = shifted_labels(sim.clicks.labels, shift, set(centroids.labels))
    return None if labels is None else Landmarks2D(labels, sim.clicks.uv_px, "shifted")


def _status_counts(rows: list[dict]) -> str:
    statuses = [(r["level_check"] or {}).get("status", "off") for r in rows]
    return ", ".join(f"{name} {statuses.count(name)}" for name in ("confident", "ambiguous", "contradicted"))


def summarize(rows: list[dict], free_rows: list[dict], shifted_rows: list[dict] = ()) -> str:
    def med(values):
        return float(np.median(values)) if len(values) else float("nan")

    def pct(values, q):
        return float(np.percentile(values, q)) if len(values) else float("nan")

    unfitted = np.concatenate([r["score"]["unfitted_pde_pose_mm"] for r in rows])
    landmark_only = np.concatenate([r["landmark_score"]["unfitted_pde_pose_mm"] for r in rows])
    unfitted_img = np.concatenate([r["score"]["unfitted_pde_image_mm"] for r in rows])
    lines = [
        f"{len(rows)} simulated cases, sample CT, 1024-px image-intensifier detector; "
        f"{platform.processor() or platform.machine()}, {time.strftime('%Y-%m-%d')}.",
        "",
        "| stage | mPDE on clicked levels, median (max) | seconds, median (max) | paper |",
        "|---|---|---|---|",
    ]
    paper = {"database": "(preoperative)", "spatial": "20.41 mm, ~10 s coarse", "depth": "12.18 mm",
             "fine": "0.36 mm, ~15 s", "refine": "(not in the paper)", "levels": "(not in the paper)",
             "final_drr": "~90 s"}
    for name in ("database", "spatial", "levels", "depth", "fine", "refine", "final_drr"):
        m = [r["stages"][name]["mpde_mm"] for r in rows if r["stages"][name]["mpde_mm"] is not None]
        s = [r["stages"][name]["seconds"] if name != "spatial" else
             r["stages"][name]["seconds_by_metric"][r["stages"][name]["metric"]] for r in rows]
        ms = f"{med(m):.2f} ({max(m):.2f}) mm" if m else "-"
        lines.append(f"| {name} | {ms} | {med(s):.2f} ({max(s):.2f}) | {paper[name]} |")
    totals = [r["total_s"] - sum(v for k, v in r["stages"]["spatial"]["seconds_by_metric"].items()
                                 if k != r["stages"]["spatial"]["metric"]) for r in rows]
    core = [t - r["stages"]["levels"]["seconds"] for t, r in zip(totals, rows, strict=True)]
    lines += [f"| **whole registration** (database cached), without / with the level check | | {med(core):.2f} "
              f"({max(core):.2f}) / {med(totals):.2f} ({max(totals):.2f}) | ~2 min |", ""]
    named = sum(r["score"]["all_named_correctly"] for r in rows)
    success = np.mean(unfitted < 5.0) * 100
    lines += [
        "| accuracy on levels NOT used in the fit | value |", "|---|---|",
        f"| projection distance vs true pose after the landmark stages (paper), median / 95th pct / max | "
        f"{med(landmark_only):.2f} / {pct(landmark_only, 95):.2f} / {landmark_only.max():.2f} mm |",
        f"| same after the image refinement (default), median / 95th pct / max | {med(unfitted):.2f} / "
        f"{pct(unfitted, 95):.2f} / {unfitted.max():.2f} mm |",
        f"| unfitted visible levels within 5 mm, landmark stages only | {np.mean(landmark_only < 5) * 100:.1f} % |",
        f"| distance to where the vertebra appears (motion + distortion), median / 95th pct | "
        f"{med(unfitted_img):.2f} / {pct(unfitted_img, 95):.2f} mm |",
        f"| unfitted visible levels within 5 mm, with refinement | {success:.1f} % of {len(unfitted)} |",
        f"| cases with every visible level named correctly | {named} / {len(rows)} |",
        f"| same, landmark stages only | {sum(r['landmark_score']['all_named_correctly'] for r in rows)} / "
        f"{len(rows)} |",
        f"| cases passing the pipeline's own checks (`ok`) | {sum(r['ok'] for r in rows)} / {len(rows)} |",
        f"| level check, labels as clicked (correct) | {_status_counts(rows)} |",
    ]
    if shifted_rows:
        lines.append(f"| level check, every label one level off (wrong) | {_status_counts(shifted_rows)}; "
                     f"reported `ok` {sum(r['ok'] for r in shifted_rows)} / {len(shifted_rows)} |")
    if free_rows:
        free = np.concatenate([r["score"]["unfitted_pde_pose_mm"] for r in free_rows])
        lines.append(f"| same, fine stage unanchored (no prior, wide bounds): median / max | {med(free):.2f} / "
                     f"{free.max():.2f} mm |")
    lines += ["", "| spatial-search metric | mPDE after stage 1b, median (max) | cases within 20 mm |", "|---|---|---|"]
    for metric in METRICS:
        m = np.array([r["spatial_per_metric"][metric]["mpde_mm"] for r in rows])
        lines.append(f"| {metric.upper()} | {np.median(m):.1f} ({m.max():.1f}) mm | {np.sum(m < 20)} / {len(m)} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=24)
    parser.add_argument("--size-px", type=int, default=1024)
    parser.add_argument("--out", type=Path, default=Path("Testing/Benchmarks"))
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    parser.add_argument("--unanchored", action="store_true", help="also run the fine stage without anchoring")
    parser.add_argument("--shifted", action="store_true", help="also run with every label one level off")
    args = parser.parse_args(argv)
    ct, labels, centroids = load_case()
    params = RegistrationParameters(cache_dir=args.cache_dir, all_metrics=True)
    free_params = RegistrationParameters(cache_dir=args.cache_dir, all_metrics=True, fine=FineParameters(
        rotation_weight_mm_per_deg2=0.0, bounds=(200, 200, 200, 90, 90, 90), sigma=(10, 3, 3, 20, 20, 20)))
    rows, free_rows, shifted_rows = [], [], []
    for seed in range(args.cases):
        sim, xray, _ = simulate(ct, labels, centroids, seed, args.size_px)
        row = run_case(ct, centroids, sim, xray, params)
        rows.append(row)
        if args.unanchored:
            free_rows.append(run_case(ct, centroids, sim, xray, free_params))
        wrong = shifted_clicks(sim, centroids) if args.shifted else None
        if wrong is not None:
            shifted_rows.append(run_case(ct, centroids, sim, xray, params, wrong))
            print(f"         labels one level off: {shifted_rows[-1]['level_check']['status']}", flush=True)
        s = row["score"]
        print(f"case {seed:2d}: fine mPDE {row['stages']['fine']['mpde_mm']:.2f} mm, unfitted max "
              f"{s['max_unfitted_pde_pose_mm']:.2f} mm, named {'ok' if s['all_named_correctly'] else 'WRONG'}, "
              f"{row['total_s']:.2f} s (db {row['stages']['database']['seconds']:.2f} s), levels "
              f"{(row['level_check'] or {}).get('status')}", flush=True)
    table = summarize(rows, free_rows, shifted_rows)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results_registration.md").write_text(table)
    (args.out / "results_registration.json").write_text(json.dumps(rows, indent=1, default=float))
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
