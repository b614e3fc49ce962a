"""The appearance benchmark's latest record of every run, pooled over several result files (no run is made).

Not a test: run it by hand. Each run (case, variant, mode) keeps its record from the last file that has it (files
are given oldest first: a half run for the first time, then the runs a later stop re-ran), only cases in
``--cases FIRST-LAST``; the tables are ``bench_appearance``'s own (``write_results``)::

    .venv/bin/python Testing/Benchmarks/pool_appearance.py --cases 108-167 \\
        --out /tmp/pooled results_appearance_s32_unseen108_cases_report.json ...

Each pooled run records the file it came from (``record``); the file names are the ``--out`` folder's
``results_appearance.json`` meta's ``sources``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_appearance as bench  # noqa: E402
import compare_runs  # noqa: E402


def latest_runs(files: list[Path], first: int, last: int) -> list[dict]:
    """Every run of cases ``first``..``last`` as its last file (in ``files``' order) recorded it, sorted by (case,
    variant, mode), each with ``record`` = that file's name."""
    runs = compare_runs.runs(files)
    return [runs[key] for key in sorted(runs) if first <= key[0] <= last]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", nargs="+", type=Path, help="result JSON files, oldest first")
    parser.add_argument("--cases", required=True, help="FIRST-LAST (inclusive)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    first, last = (int(x) for x in args.cases.split("-"))
    rows = latest_runs(args.files, first, last)
    meta = {"description": f"The latest record of every run of cases {first}-{last} in the files of 'sources' "
                           "(later files win), pooled by `Testing/Benchmarks/pool_appearance.py`; no run was made "
                           "for this file. " + bench._description(),
            "commit": "each run's own file", "command": "(pooled, not run)", "machine": "as each source file says",
            "date": time.strftime("%Y-%m-%d"),
            "sources": [p.name for p in args.files]}
    bench.write_results(args.out, rows, meta)
    print(f"{len(rows)} runs pooled into {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
