"""Level labellings of X-ray clicks: which CT level each click could be (the hypotheses of ``levels``).

The clicks are put in spine order (``order_along_spine``: head first, since image rows run toward the feet,
CONVENTIONS.md). A *labelling* gives the k-th click in that order a CT level name; clicks are taken to sit on
consecutive vertebrae unless the surgeon named them:

- unnamed clicks: every run of n consecutive CT-labelled levels (T1-T3, T2-T4, ..., the ends included);
- named clicks (all or some): the labelling the names imply (unnamed clicks between named ones follow spine
  order) and that labelling shifted by +-1 ... +-``max_shift`` levels.
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.errors import LandmarkError
from carmreg.logic.io.landmarks import LEVEL_NAMES, Landmarks2D, Landmarks3D, level_index


def principal_axis(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit principal axis of (n >= 2, 2) points (the first right singular vector of the centred points, its sign
    as the SVD gives it) and their elongation: the first singular value over the second (inf on a line)."""
    singular, axes = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[1:]
    return axes[0], (np.inf if singular[1] == 0.0 else float(singular[0] / singular[1]))


def order_along_spine(uv_px: np.ndarray) -> np.ndarray:
    """Click indices head to sacrum: sorted along the clicks' principal axis (``principal_axis``), oriented so that
    the image row grows (rows run toward the patient's feet, CONVENTIONS.md). Ties keep the given order."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    if len(uv) < 2:
        return np.arange(len(uv))
    centred = uv - uv.mean(axis=0)
    axis = principal_axis(uv)[0]
    if axis[1] < 0 or (axis[1] == 0 and axis[0] < 0):
        axis = -axis
    return np.argsort(centred @ axis, kind="stable")


def ct_level_names(ct: Landmarks3D) -> list[str]:
    """The CT's labelled levels, head to sacrum."""
    return sorted(ct.labels, key=level_index)


def shifted_labels(labels: list[str], shift: int, available: list[str] | set[str]) -> list[str] | None:
    """``labels`` moved ``shift`` places along the available levels (head to sacrum), or None if off the end."""
    available = set(available)
    names = [n for n in LEVEL_NAMES if n in available]
    if not all(lb in names for lb in labels):
        return None
    moved = [names.index(lb) + shift for lb in labels]
    return [names[i] for i in moved] if all(0 <= i < len(names) for i in moved) else None


def identifiable_clicks(clicks: Landmarks2D, ct_names: list[str]) -> list[int]:
    """Indices of the clicks the levels stage works with: unnamed ones, and named ones with a CT centroid
    (a named click without one is left out, as in pairing by name)."""
    return [i for i, lb in enumerate(clicks.labels) if lb is None or lb in ct_names]


def check_labelling_possible(clicks: Landmarks2D, ct_names: list[str]) -> None:
    """LandmarkError now, before any registration, when no labelling can satisfy the (partly named) clicks."""
    used = identifiable_clicks(clicks, ct_names)
    order = order_along_spine(np.asarray(clicks.uv_px, float)[used])
    candidate_labellings([clicks.labels[used[k]] for k in order], ct_names, 0)


def implied_labels(names_in_order: list, ct_names: list[str]) -> list[str]:
    """The full labelling implied by partly named clicks in spine order (unnamed clicks are consecutive levels
    between and around the named ones); LandmarkError when the names contradict the spine order."""
    starts = set()
    for k, name in enumerate(names_in_order):
        if name is None:
            continue
        if name not in ct_names:
            raise LandmarkError(f"the X-ray click named {name} has no CT centroid; label {name} in the CT or leave "
                                "the click unnamed")
        starts.add(ct_names.index(name) - k)
    if len(starts) != 1:
        raise LandmarkError("the named X-ray clicks do not fit consecutive vertebrae in spine order (top of the "
                            "image = head): check the names, or click every vertebra between them")
    s = starts.pop()
    if s < 0 or s + len(names_in_order) > len(ct_names):
        raise LandmarkError("with these names some unnamed clicks fall beyond the CT's labelled levels "
                            f"({ct_names[0]}-{ct_names[-1]}): label more levels in the CT or fewer clicks")
    return ct_names[s:s + len(names_in_order)]


def candidate_labellings(names_in_order: list, ct_names: list[str], max_shift: int
                         ) -> tuple[list[tuple[int, list[str]]], int | None, str]:
    """(shift, labels) for every hypothesis, the index of the surgeon's labelling (or None) and the mode."""
    n = len(names_in_order)
    named = [lb for lb in names_in_order if lb is not None]
    if not named:
        runs = [(s, ct_names[s:s + n]) for s in range(len(ct_names) - n + 1)]
        if not runs:
            raise LandmarkError(f"{n} clicks but only {len(ct_names)} CT-labelled levels: label at least as many "
                                "vertebrae in the CT as you click on the X-ray")
        return runs, None, "unnamed"
    if len(named) == n:
        given, mode = list(names_in_order), "named"
    else:
        given, mode = implied_labels(names_in_order, ct_names), "partly_named"
    out = []
    for shift in range(-max_shift, max_shift + 1):
        labels = given if shift == 0 else shifted_labels(given, shift, ct_names)
        if labels is not None:
            out.append((shift, labels))
    return out, [s for s, _ in out].index(0), mode
