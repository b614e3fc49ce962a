"""What the two curve analyses share (``refinement_curves``: the levels contest's refinements; ``check_curves``:
the appearance checks'): the evaluation counts they look at, a curve's value after e evaluations, and the table of
what was still to come after them. Not a test."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

EVALUATIONS = (160, 240, 320, 480, 640)


def extract(load: Path | None, save: Path | None, read):
    """The curves: from a stored extract (``load``), else ``read()`` from a benchmark's files; written as a compact
    JSON extract to ``save`` when given."""
    curves = json.loads(load.read_text()) if load else read()
    if save:
        save.write_text(json.dumps(curves, separators=(",", ":")))
    return curves


def allowances(found: dict, safety: float, margin: float) -> dict:
    """{e: ``safety`` x the largest gain still to come after e in ``found`` (every curve's) + ``margin``}."""
    return {e: safety * max(found[e][0]) + margin for e in EVALUATIONS}


def value_after(evaluations: list, values: list, e: int):
    """The value recorded at the last generation with at most ``e`` evaluations (None before the first)."""
    k = int(np.searchsorted(evaluations, e, side="right")) - 1
    return values[k] if k >= 0 else None


def still_to_come_table(found: dict, what: str, every_one: str, subset: str) -> str:
    """The markdown table of ``found`` = {e: (every curve's gain after e, the ``subset``'s gains)}: per e, every
    curve's median / 95th percentile / max ``what`` and the subset's max (nan when it has none)."""
    lines = [f"| after e evaluations | {what}, {every_one}: median / 95th pct / max | {subset}: max |",
             "|---|---|---|"]
    for e in EVALUATIONS:
        every, part = (np.asarray(x) for x in found[e])
        lines.append(f"| {e} | {np.median(every):.3f} / {np.percentile(every, 95):.3f} / {every.max():.3f} | "
                     f"{part.max() if part.size else float('nan'):.3f} |")
    return "\n".join(lines)
