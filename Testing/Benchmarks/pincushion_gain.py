"""Should a pincushion estimate be kept only when it lowers the objective by a margin? (stop 38; the answer was no.)

Not a test. The refine stage's estimate (``registration.pincushion``) keeps the shift whose refinement has the
lowest final objective, however small its lead over the pinhole (shift 0). On the independent cases a shift won
by a hair of objective now and then moved the pose by the refinement's own noise (README, stop 37). Candidate
rules, each keeping the estimate's shift ``s`` only when, else the pinhole's refinement::

    tau:   f(0) - f(s) >= tau                                  (an absolute gain)
    noise: f(0) - f(s) >= k * sd_seeds f(0)                     (the gain against the refinement's seed noise)
    mean3: mean over seeds 1-3 of f(s) < the same of f(0)      (the profile's two ends averaged over seeds)

are scored here on appearance-benchmark cases (named clicks, the intensifier variants): the registration runs as
the CLI runs it up to the fine stage (database cached), then the refine stage itself, each of its refinements
recorded (its shift, final objective and pose), and the shift-0 and kept-shift refinements run again with seeds
2 and 3. Each refinement's pose is scored by the projection distance of the levels not clicked from the true
pose's (pinhole P, detector mm; ``simulation.evaluation``), as ``bench_appearance`` scores them::

    .venv/bin/python Testing/Benchmarks/pincushion_gain.py run /tmp/gain_tune.jsonl 132,134 ii-dark-log-png \\
        --cache-dir /tmp/c
    .venv/bin/python Testing/Benchmarks/pincushion_gain.py table /tmp/gain_tune.jsonl
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_appearance as bench  # noqa: E402

from carmreg.logic.registration.pipeline import CarmRegLogic  # noqa: E402
from carmreg.logic.simulation.evaluation import evaluate  # noqa: E402

SEEDS = (2, 3)


@contextlib.contextmanager
def recorded_refinements(record: list, score):
    """Every local refinement the pipeline runs inside the block, appended to ``record`` as {shift, obj, pde}."""
    original = CarmRegLogic._local_refine

    def spy(self, state, start_pose, shift_mm=None):
        r = original(self, state, start_pose, shift_mm)
        record.append({"shift": shift_mm, "obj": r.objective_end, "pde": score(r.pose)})
        return r

    CarmRegLogic._local_refine = spy
    try:
        yield original
    finally:
        CarmRegLogic._local_refine = original


def run_case(maker: bench.CaseMaker, case: int, vname: str, cache_dir: str) -> dict:
    """One case and variant, named clicks: the refine stage's profile and the seeds' re-runs (module docstring)."""
    logic, state, truth = bench.prepared_case(maker, case, vname, Path(tempfile.mkdtemp()), cache_dir,
                                              names=lambda t: t["clicked"])
    logic.run_through(state, "fine")
    prepared = state.geometry
    cents, clicked = state.ct_landmarks.as_dict(), set(truth["clicked"])

    def score(pose) -> list:
        return evaluate(prepared.projection_matrix(pose), cents, truth, clicked)["unfitted_pde_pose_mm"]

    profile, noise = [], []
    with recorded_refinements(profile, score) as local_refine:
        start, _ = logic._coarse_refined_pose(state, state.pairs.points_lps_mm, state.pairs.uv_px)
        logic.run_stage(state, "refine")
        pin = next(s for s in state.stages if s.name == "refine").extra.get("pincushion")
        if pin is not None:
            if state.pinhole is not None:  # the detector and clicks as prepared
                state.geometry, state.pairs = state.pinhole[0], state.pinhole[1]
            params = state.parameters.refine
            for seed in SEEDS:
                state.parameters.refine = dataclasses.replace(params, seed=seed)
                for shift in sorted({0.0, float(pin["shift_at_100_mm"])}):
                    r = local_refine(logic, state, start, shift)
                    noise.append({"seed": seed, "shift": shift, "obj": r.objective_end, "pde": score(r.pose)})
            state.parameters.refine = params
    k_true = ((truth.get("distortion") or {}).get("k_per_mm2") or 0.0) * 1e6
    return {"case": case, "variant": vname, "true_shift_mm": k_true, "pincushion": pin,
            "profile": profile, "noise": noise}


def kept_pde(row: dict, rule: str, value: float = 0.0) -> list:
    """The levels' PDE of the refinement ``rule`` keeps on one run (module docstring)."""
    prof = {p["shift"]: p for p in row["profile"]}
    best = row["pincushion"]["shift_at_100_mm"]
    seeds = {s: [n["obj"] for n in row["noise"] if n["shift"] == s] + [prof[s]["obj"]] for s in {0.0, best}}
    gain = prof[0.0]["obj"] - prof[best]["obj"]
    keep = {"estimate": True, "pinhole": False, "tau": gain >= value,
            "noise": gain >= value * np.std(seeds[0.0], ddof=1),
            "mean3": np.mean(seeds[best]) < np.mean(seeds[0.0])}[rule]
    return prof[best]["pde"] if keep and best else prof[0.0]["pde"]


RULES = [("pinhole", 0.0), ("estimate", 0.0), ("mean3", 0.0), ("tau", 0.0005), ("tau", 0.001), ("tau", 0.002),
         ("noise", 1.0), ("noise", 2.0), ("noise", 3.0)]


def table(rows: list) -> str:
    """The rule table: median / 95th / max of the levels' PDE over every run with an estimate."""
    rows = [r for r in rows if r["pincushion"] is not None]
    lines = [f"{len(rows)} runs ({sum(bool(r['pincushion']['shift_at_100_mm']) for r in rows)} with a shift "
             "kept); levels not clicked, PDE to the true pose (detector mm)", "",
             "| rule | median | 95th | max |", "|---|---|---|---|"]
    for rule, value in RULES:
        v = np.concatenate([kept_pde(r, rule, value) for r in rows])
        name = rule if rule in ("pinhole", "estimate", "mean3") else f"{rule} {value:g}"
        lines.append(f"| {name} | {np.median(v):.2f} | {np.percentile(v, 95):.2f} | {v.max():.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run")
    run.add_argument("out", type=Path)
    run.add_argument("cases")
    run.add_argument("variants")
    run.add_argument("--cache-dir", default=None)
    show = sub.add_parser("table")
    show.add_argument("jsonl", type=Path)
    a = ap.parse_args(argv)
    if a.command == "table":
        print(table([json.loads(line) for line in a.jsonl.read_text().splitlines() if line.strip()]))
        return 0
    maker = bench.CaseMaker(second_ct=True)
    with a.out.open("a") as out:
        for case in map(int, a.cases.split(",")):
            for vname in a.variants.split(","):
                out.write(json.dumps(run_case(maker, case, vname, a.cache_dir)) + "\n")
                out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
