"""Benchmark: which vertebra is which, and how accurate, on realistic simulated cases from two real CTs.

Not a test: run it by hand and paste its table into the README::

    .venv/bin/python Testing/Benchmarks/bench_levels.py --cases 54 --out Testing/Benchmarks

Cases alternate between the sample chest CT (T1-L1) and the second CT (TotalSegmentator's abdomen CT, L1-S1,
3 mm voxels; from ../shared, skipped when absent): every third case uses the second CT. Each case: a random
C-arm pose aimed within +-2 levels of a random labelled level (+-20 mm lateral, +-50 mm depth, +-10 deg each
rotation), realism drawn from the literature ranges (``simulate.sample_options``: bone contrast / kVp, scatter,
photons, vignetting, pincushion and S-distortion, K-wires, per-level motion), three adjacent levels clicked
with ~0.9 mm noise. The database is built once per CT and cached (preoperative). Modes per case:

- ``unnamed``: the three clicks without names: the levels stage must name them;
- ``none``: no clicks: the levels in view are named from the image alone;
- ``named``: the clicks correctly named: the check should be confident (contradicted = false alarm);
- ``wrong``: every name one level off (up or down at random): the check must not be confident.

Accuracy is the projection distance, on the detector, between each visible CT centroid projected under the found
and under the true pose (``Logic.evaluation``), for the levels NOT clicked; "landmark stages" is the fine
(Algorithm 4) pose of the same run, before the image refinement.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_registration import load_case, simulate  # noqa: E402
from second_ct import load_second_ct  # noqa: E402

from carmreg.logic.io.landmarks import Landmarks2D  # noqa: E402
from carmreg.logic.registration.labellings import shifted_labels  # noqa: E402
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters  # noqa: E402
from carmreg.logic.simulation.evaluation import evaluate  # noqa: E402

MODES = ("unnamed", "none", "named", "wrong")


def clicks_for(mode: str, sim, centroids, rng) -> Landmarks2D | None:
    c = sim.clicks
    if mode == "unnamed":
        return Landmarks2D([None] * len(c.labels), c.uv_px, "unnamed")
    if mode == "none":
        return Landmarks2D([], np.zeros((0, 2)), "none")
    if mode == "named":
        return c
    for shift in ((1, -1) if rng.random() < 0.5 else (-1, 1)):
        labels = shifted_labels(c.labels, shift, centroids.labels)
        if labels is not None:
            return Landmarks2D(labels, c.uv_px, f"shifted {shift:+d}")
    return None


def level_offset(result_P, centroids, truth) -> int:
    """Most common level offset between where the found pose puts each visible level and the true vertebra
    nearest to it (0 = right names, +-1 = off by one)."""
    from carmreg.logic.geometry.camera import project

    visible = [lb for lb in centroids.sorted().labels if truth["levels"].get(lb, {}).get("visible")]
    if not visible:
        return 0
    true_uv = np.array([truth["levels"][lb]["uv_true_px"] for lb in visible])
    offsets = []
    for k, lb in enumerate(visible):
        uv = project(result_P, centroids.as_dict()[lb][None])[0]
        offsets.append(int(np.argmin(np.linalg.norm(true_uv - uv, axis=1))) - k)
    values, counts = np.unique(offsets, return_counts=True)
    return int(values[np.argmax(counts)])


def run(ct, centroids, sim, xray, clicks, params) -> dict:
    t0 = time.perf_counter()
    result = CarmRegLogic().register(ct, centroids, xray, clicks, params)
    seconds = time.perf_counter() - t0
    truth = sim.ground_truth()
    clicked = set(sim.clicks.labels) if len(clicks.labels) else set()
    score = evaluate(result.projection_matrix, centroids.as_dict(), truth, clicked,
                     shown=result.geometry.intrinsics.distortion.distort)
    stages = {s.name: s for s in result.stages}
    fine = stages.get("fine")
    landmark = evaluate(result.geometry.projection_matrix(fine.pose), centroids.as_dict(), truth, clicked) \
        if fine is not None and fine.mpde_mm is not None else None
    lc = result.level_check.to_dict() if result.level_check else {}
    return {"seconds": seconds, "ok": result.ok, "status": lc.get("status"), "margin": lc.get("margin"),
            "assigned": lc.get("assigned_labels"), "truth_labels": list(sim.clicks.labels),
            "given": list(l or "" for l in clicks.labels),
            "correct_names": lc.get("assigned_labels") == list(sim.clicks.labels),
            "all_named_correctly": score["all_named_correctly"],
            "offset": level_offset(result.projection_matrix, centroids, truth),
            "unfitted_mm": score["unfitted_pde_pose_mm"],
            "landmark_unfitted_mm": landmark["unfitted_pde_pose_mm"] if landmark else None,
            "stage_seconds": {k: s.seconds for k, s in stages.items()},
            "reasons": lc.get("reasons"), "checks": lc.get("checks"),
            "appearance": result.appearance.as_dict() if result.appearance is not None else None}


def _pct(values, q) -> str:
    return f"{np.percentile(values, q):.2f}" if len(values) else "-"


def summarize(rows: list[dict]) -> str:
    cts = sorted({r["ct"] for r in rows})
    counts = ", ".join(f"{c}: {sum(r['ct'] == c for r in rows)}" for c in cts)
    lines = [f"{len(rows)} simulated cases ({counts}), "
             f"1024-px image-intensifier detector; {platform.processor() or platform.machine()}, 2 cores, "
             f"{time.strftime('%Y-%m-%d')}.", ""]
    lines += ["| mode | right levels | off by one | confident (no clicks: proposed) AND wrong | flagged ambiguous | "
              "contradicted | seconds per case, median (max) |", "|---|---|---|---|---|---|---|"]
    for mode in MODES:
        runs = [r[mode] for r in rows if r.get(mode)]
        if not runs:
            continue
        right = [_right(mode, x) for x in runs]
        n = len(runs)
        off1 = sum(abs(x["offset"]) == 1 for x in runs)
        conf_wrong = sum(x["status"] in ("confident", "proposed") and not ok for x, ok in zip(runs, right, strict=True))
        amb = sum(x["status"] == "ambiguous" for x in runs)
        contra = sum(x["status"] == "contradicted" for x in runs)
        secs = [x["seconds"] for x in runs]
        lines.append(f"| {mode} | {sum(right)} / {n} | {off1} / {n} | {conf_wrong} | {amb} / {n} | {contra} / {n} "
                     f"| {np.median(secs):.1f} ({max(secs):.1f}) |")
    lines += ["", "| levels not clicked: projection distance vs the true pose (detector mm) | median | 95th pct | "
              "max | within 5 mm |", "|---|---|---|---|---|"]
    for mode, key, name in (("unnamed", "landmark_unfitted_mm", "unnamed clicks, landmark stages only (paper)"),
                            ("unnamed", "unfitted_mm", "unnamed clicks, after the image refinement"),
                            ("named", "unfitted_mm", "named clicks, after the image refinement"),
                            ("none", "unfitted_mm", "no clicks (every visible level)")):
        values = np.concatenate([r[mode][key] for r in rows if r.get(mode) and r[mode][key] is not None] or [[]])
        if len(values):
            lines.append(f"| {name} | {np.median(values):.2f} | {_pct(values, 95)} | {values.max():.2f} | "
                         f"{np.mean(values < 5) * 100:.0f} % of {len(values)} |")
    return "\n".join(lines) + "\n"


def _right(mode: str, x: dict) -> bool:
    """Right answer per mode: names of the clicks (unnamed), levels in view (none), not confident in wrong
    names (wrong), confident or ambiguous in right names (named)."""
    if mode == "unnamed":
        return bool(x["correct_names"])
    if mode == "none":
        return bool(x["all_named_correctly"])
    if mode == "wrong":
        return x["status"] != "confident"
    return x["status"] != "contradicted"


def resummarize(path: Path) -> str:
    """The table again from a results JSON (e.g. after a status was renamed)."""
    return summarize(json.loads(path.read_text()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=54)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--size-px", type=int, default=1024)
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--out", type=Path, default=Path("Testing/Benchmarks"))
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    args = parser.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    cts = {"sample chest CT": load_case()}
    second = load_second_ct()
    if second is not None:
        cts["second CT (abdomen)"] = second
    params = RegistrationParameters(cache_dir=args.cache_dir)
    rows = []
    for seed in range(args.first, args.first + args.cases):
        name = list(cts)[1] if len(cts) > 1 and seed % 3 == 2 else list(cts)[0]
        ct, labels, centroids = cts[name]
        sim, xray, rng = simulate(ct, labels, centroids, seed, args.size_px)
        row = {"seed": seed, "ct": name, "clicked": list(sim.clicks.labels)}
        for mode in modes:
            clicks = clicks_for(mode, sim, centroids, rng)
            if clicks is not None:
                row[mode] = run(ct, centroids, sim, xray, clicks, params)
        rows.append(row)
        print(f"case {seed:2d} {name[:6]} {row['clicked']}: " + "; ".join(
            f"{m} {row[m]['assigned'] if m != 'none' else row[m]['offset']} {row[m]['status']} "
            f"{row[m]['margin']:.3f} {'OK' if _right(m, row[m]) else 'WRONG'} {row[m]['seconds']:.1f}s"
            for m in modes if m in row), flush=True)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results_levels.json").write_text(json.dumps(rows, indent=1, default=float))
    table = summarize(rows)
    (args.out / "results_levels.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
