"""Two appearance-benchmark runs of the same cases side by side: answers and the levels not clicked.

Not a test. Reads ``bench_appearance`` JSON files (several may make up one side) and compares the runs both
sides hold (same case, variant and mode): how many answers changed status or rightness, confident-wrong counts,
and the projection distance of the levels not clicked (found vs true pose, detector mm; unnamed and named
clicks, as ``bench_appearance`` reports it) per detector::

    .venv/bin/python Testing/Benchmarks/compare_runs.py --before results_appearance_s21_report.json \\
        results_appearance_s22_new_cases_report.json --after results_appearance_s23_calibrated_report.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def runs(paths: list[Path]) -> dict:
    """{(case, variant, mode): run} over the files (a later file's run replaces an earlier one's), each run with
    ``record`` = the name of the file it came from."""
    out = {}
    for path in paths:
        for run in json.loads(path.read_text())["runs"]:
            out[(run["case"], run["variant"], run["mode"])] = dict(run, record=path.name)
    return out


def pde_summary(rows: list[dict]) -> str:
    """'n levels, median / 95th percentile / max mm' of the levels not clicked (unnamed and named modes)."""
    values = np.concatenate([r["unfitted_pde_mm"] for r in rows if r["mode"] in ("unnamed", "named")
                             and r.get("unfitted_pde_mm")] or [[]])
    if not len(values):
        return "no levels"
    return (f"{len(values)} levels, {np.median(values):.2f} / {np.percentile(values, 95):.2f} / "
            f"{values.max():.2f} mm")


def confident_wrong(rows: list[dict]) -> int:
    return sum(r.get("status") == "confident" and not r.get("answer_right") for r in rows)


def compare(before: dict, after: dict) -> str:
    common = sorted(set(before) & set(after))
    b, a = [before[k] for k in common], [after[k] for k in common]
    changed = [k for k in common if (before[k].get("status"), before[k].get("answer_right"))
               != (after[k].get("status"), after[k].get("answer_right"))]
    lines = [f"{len(common)} runs in both; status or rightness changed in {len(changed)}",
             f"confident and wrong: before {confident_wrong(b)}, after {confident_wrong(a)}",
             f"confident: before {sum(r.get('status') == 'confident' for r in b)}, "
             f"after {sum(r.get('status') == 'confident' for r in a)}"]
    for k in changed:
        lines.append(f"  case {k[0]} {k[1]} {k[2]}: {before[k].get('status')} "
                     f"{'right' if before[k].get('answer_right') else 'wrong'} -> {after[k].get('status')} "
                     f"{'right' if after[k].get('answer_right') else 'wrong'}")
    for detector in ("ii", "fp"):
        sel = [k for k in common if k[1].startswith(detector + "-") and "mirrored" not in k[1]]
        if sel:
            lines.append(f"levels not clicked, {detector} (correctly displayed): before "
                         f"{pde_summary([before[k] for k in sel])}; after {pde_summary([after[k] for k in sel])}")
    times_b = [r["seconds"] for r in b if r.get("seconds") == r.get("seconds")]
    times_a = [r["seconds"] for r in a if r.get("seconds") == r.get("seconds")]
    if times_b and times_a:
        lines.append(f"seconds, median / worst: before {np.median(times_b):.1f} / {max(times_b):.1f}, "
                     f"after {np.median(times_a):.1f} / {max(times_a):.1f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, nargs="+", required=True)
    parser.add_argument("--after", type=Path, nargs="+", required=True)
    args = parser.parse_args(argv)
    print(compare(runs(args.before), runs(args.after)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
