"""Vertebral centroids from a label map, and the label conventions CarmReg reads.

Centroid
--------
The centroid of a vertebra is the centre of mass of its voxels (all voxels weigh the same), taken in
continuous voxel index (voxel centres at integer ijk) and mapped through the volume's 4x4 ``ijk_to_lps``::

    c_lps_mm = ijk_to_lps @ [mean(i), mean(j), mean(k), 1]

An affine map commutes with the mean, so this is exactly the centre of mass in LPS mm, oblique grids too.

Completeness
------------
A vertebra whose voxels reach the first or last slice of the volume (the index axis that runs most nearly
superior-inferior) is cut by the edge of the scan: its centroid is biased toward the inside of the volume,
so it is reported as incomplete and left out of the landmarks.

Label values
------------
- TotalSegmentator v2 (``total`` task): 26 vertebrae_S1, 27 L5, 28 L4, ..., 31 L1, 32 T12, ..., 43 T1,
  44 C7, ..., 50 C1 (25 is the sacrum, not a level). ``TOTALSEGMENTATOR_V2_VERTEBRAE`` maps them to names.
- CarmReg's own vertebra label maps (e.g. ``Resources/SampleCase/vertebrae.nrrd``): value
  ``1 + LEVEL_NAMES.index(name)``, so C1 = 1, C7 = 7, T1 = 8, T12 = 19, L1 = 21, S1 = 27; 0 is background.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import LandmarkError
from .landmarks import LEVEL_NAMES, Landmarks3D, level_index, normalize_level_name

TOTALSEGMENTATOR_V2_VERTEBRAE: dict[int, str] = {
    26: "S1",
    **{27 + n: f"L{5 - n}" for n in range(5)},    # 27 L5 ... 31 L1
    **{32 + n: f"T{12 - n}" for n in range(12)},  # 32 T12 ... 43 T1
    **{44 + n: f"C{7 - n}" for n in range(7)},    # 44 C7 ... 50 C1
}
"""TotalSegmentator v2 ``total`` label value -> vertebral level name."""


def carmreg_label_value(name: str) -> int:
    """CarmReg label value of a level: 1 + LEVEL_NAMES.index(name) (T12 -> 19, L1 -> 21)."""
    return 1 + level_index(name)


CARMREG_VERTEBRAE: dict[int, str] = {carmreg_label_value(n): n for n in LEVEL_NAMES}
"""CarmReg label value -> level name (1 C1 ... 27 S1)."""


TRANSITIONAL_LEVELS = ("T13", "L6")
"""Levels most spines do not have; they count as a level only when a patient's labels include them."""


def level_ordinals(names) -> dict[str, int]:
    """Position of each level along this spine, counting T13 and L6 only if they are among ``names``.

    Adjacent vertebrae differ by exactly 1 (T12 -> L1 is 1 unless T13 is present), unlike ``level_index``.
    """
    present = {normalize_level_name(n) for n in names}
    sequence = [n for n in LEVEL_NAMES if n not in TRANSITIONAL_LEVELS or n in present]
    return {n: sequence.index(n) for n in present}


def superior_axis(ijk_to_lps: np.ndarray) -> int:
    """Index axis (0, 1 or 2) whose direction is closest to LPS z (superior-inferior): the 'slice' axis."""
    directions = np.asarray(ijk_to_lps, float)[:3, :3]
    directions = directions / np.linalg.norm(directions, axis=0, keepdims=True)
    return int(np.argmax(np.abs(directions[2])))


@dataclass
class LabelSummary:
    """What one label value holds: voxel count, index bounding box (inclusive) and completeness."""

    value: int
    name: str
    n_voxels: int
    ijk_min: tuple[int, int, int]
    ijk_max: tuple[int, int, int]
    complete: bool
    centroid_lps_mm: np.ndarray


def summarize_labels(label_map: np.ndarray, ijk_to_lps: np.ndarray,
                     value_to_name: dict[int, str]) -> list[LabelSummary]:
    """Centroid, bounding box and completeness of every named label present, ordered head to sacrum."""
    labels = np.asarray(label_map)
    axis = superior_axis(ijk_to_lps)
    n_slices = labels.shape[axis]
    present = [int(v) for v in np.unique(labels) if int(v) in value_to_name]
    boxes = ndimage.find_objects(labels.astype(np.int32, copy=False), max_label=max(present, default=0))
    out = []
    for value in present:
        box = boxes[value - 1]
        sub = labels[box] == value
        ijk = np.argwhere(sub) + np.array([s.start for s in box])
        lo, hi = ijk.min(axis=0), ijk.max(axis=0)
        centroid = ijk_to_lps[:3, :3] @ ijk.mean(axis=0) + ijk_to_lps[:3, 3]
        complete = bool(lo[axis] > 0 and hi[axis] < n_slices - 1)
        out.append(LabelSummary(value, normalize_level_name(value_to_name[value]), int(len(ijk)),
                                tuple(int(x) for x in lo), tuple(int(x) for x in hi), complete, centroid))
    return sorted(out, key=lambda s: level_index(s.name))


def centroids_from_labels(label_map: np.ndarray, ijk_to_lps: np.ndarray, value_to_name: dict[int, str], *,
                          include_incomplete: bool = False, source: str = "") -> Landmarks3D:
    """Landmarks3D of vertebral centroids (LPS mm), one per complete named label, head to sacrum.

    label_map: integer array on the CT grid, indexed [i, j, k]; ijk_to_lps: its 4x4 affine;
    value_to_name: label value -> level name (``TOTALSEGMENTATOR_V2_VERTEBRAE``, ``CARMREG_VERTEBRAE``).
    Labels cut by the first or last slice are left out unless ``include_incomplete``.
    Raises LandmarkError when no named vertebra is left.
    """
    summaries = [s for s in summarize_labels(label_map, ijk_to_lps, value_to_name)
                 if s.complete or include_incomplete]
    if not summaries:
        raise LandmarkError(f"{source or 'label map'}: no complete vertebra found among the label values "
                            f"{sorted(value_to_name)[:3]}...; check that the label map is a vertebra "
                            "segmentation on the CT grid and that the label convention is right")
    return Landmarks3D([s.name for s in summaries], np.array([s.centroid_lps_mm for s in summaries]),
                       source)


def to_carmreg_labels(label_map: np.ndarray, value_to_name: dict[int, str]) -> np.ndarray:
    """Relabel vertebrae to CarmReg values (uint8, 1 + LEVEL_NAMES.index); every other value -> 0."""
    lut = np.zeros(max(int(np.max(label_map)), max(value_to_name)) + 1, dtype=np.uint8)
    for value, name in value_to_name.items():
        lut[value] = carmreg_label_value(name)
    return lut[np.asarray(label_map).astype(np.intp, copy=False)]
