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

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.landmarks import LEVEL_NAMES, TRANSITIONAL_LEVELS, Landmarks3D, level_index, normalize_level_name

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


# ----------------------------------------------------------------------------------------------- labels from centroids

def spine_slab_planes(points_lps_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary planes of the vertebral slabs: ((n + 1, 3) points, (n + 1, 3) unit normals), LPS mm.

    ``points_lps_mm``: (n, 3) centroids c_0 .. c_{n-1}, head to sacrum, n >= 2. With d_k the unit direction
    of c_k -> c_{k+1} and h_k = |c_{k+1} - c_k|, plane b_k (k = 1 .. n-1) passes through the midpoint
    (c_{k-1} + c_k) / 2 with normal d_{k-1}; the end planes are b_0 through c_0 - d_0 h_0 / 2 (normal d_0)
    and b_n through c_{n-1} + d_{n-2} h_{n-2} / 2 (normal d_{n-2}). Normals point toward the sacrum.
    """
    c = np.asarray(points_lps_mm, float).reshape(-1, 3)
    if len(c) < 2:
        raise LandmarkError(f"a vertebra label map from centroids needs at least 2 centroids, got {len(c)}; "
                            "give the centroids of two or more adjacent levels")
    steps = np.diff(c, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    if np.any(lengths < 1e-6):
        raise LandmarkError("two consecutive vertebral centroids coincide; check the landmark file "
                            "(each level needs its own centroid)")
    d = steps / lengths[:, None]
    points = np.vstack([c[0] - d[0] * lengths[0] / 2, (c[:-1] + c[1:]) / 2, c[-1] + d[-1] * lengths[-1] / 2])
    normals = np.vstack([d[:1], d, d[-1:]])
    return points, normals


def distance_to_polyline(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(m,) Euclidean distance of each point (m, 3) to the polyline through ``vertices`` (v, 3), v >= 2:
    min over segments [a, b] of |x - a - clip(((x - a) . (b - a)) / |b - a|^2, 0, 1) (b - a)|."""
    best = np.full(len(points), np.inf)
    for a, b in zip(vertices[:-1], vertices[1:], strict=True):
        ab = b - a
        rel = points - a
        t = np.clip(rel @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(rel - t[:, None] * ab, axis=1))
    return best


def label_map_from_centroids(volume: Volume, centroids: Landmarks3D, *, radius_mm: float = 40.0,
                             bone_hu: float = 150.0) -> np.ndarray:
    """Approximate vertebra label map (uint8 on the CT grid, CarmReg values) from vertebral centroids alone.

    For a CT that has centroids but no segmentation: each bone voxel near the spine is given to the level
    whose slab holds it, so a simulation can move every vertebra rigidly on its own.

    Frames: voxel centres x = ijk_to_lps @ [i, j, k, 1] and the centroids are LPS mm (any oblique grid).
    Centroids c_0 .. c_{n-1} are taken head to sacrum (``Landmarks3D.sorted``); n >= 2.

    - Spine polyline: c_0 .. c_{n-1}, extended at both ends by half the adjacent intervertebral distance
      (the end points of ``spine_slab_planes``).
    - Slabs (``spine_slab_planes``): boundary planes through the midpoints of consecutive centroids,
      perpendicular to the local spine direction d_k = (c_{k+1} - c_k) / |c_{k+1} - c_k|; the end slabs reach
      half an intervertebral distance beyond the end centroids. With signed distances
      s_b(x) = (x - p_b) . n_b, level k holds the x with s_k(x) >= 0 > s_{k+1}(x) (the first such k when
      planes of a sharply bent spine cross near it).
    - A voxel is labelled when HU > ``bone_hu`` and its distance to the polyline is < ``radius_mm``
      (perpendicular distance along each segment, distance to the nearest vertex past a segment's end).

    Value of level ``name``: 1 + LEVEL_NAMES.index(name) (``carmreg_label_value``); 0 elsewhere.
    Bone of the pelvis or ribs within the radius goes with its slab's level; soft-tissue-density bone
    (HU <= bone_hu) stays unlabelled. Raises LandmarkError for fewer than 2 centroids or coincident ones.
    """
    lm = centroids.sorted()
    plane_points, normals = spine_slab_planes(lm.points_lps_mm)
    vertices = np.vstack([plane_points[:1], lm.points_lps_mm, plane_points[-1:]])
    labels = np.zeros(volume.shape, dtype=np.uint8)
    ijk = np.nonzero(np.asarray(volume.hu) > bone_hu)
    if not len(ijk[0]):
        return labels
    affine = volume.ijk_to_lps
    x = np.stack(ijk, axis=1).astype(np.float64) @ affine[:3, :3].T + affine[:3, 3]
    lo, hi = vertices.min(axis=0) - radius_mm, vertices.max(axis=0) + radius_mm
    near = np.nonzero(np.all((x >= lo) & (x <= hi), axis=1))[0]
    near = near[distance_to_polyline(x[near], vertices) < radius_mm]
    signed = x[near] @ normals.T - np.einsum("bj,bj->b", plane_points, normals)[None, :]
    inside = (signed[:, :-1] >= 0.0) & (signed[:, 1:] < 0.0)
    hit = inside.any(axis=1)
    level = inside.argmax(axis=1)[hit]
    values = np.array([carmreg_label_value(n) for n in lm.labels], dtype=np.uint8)
    chosen = near[hit]
    labels[ijk[0][chosen], ijk[1][chosen], ijk[2][chosen]] = values[level]
    return labels
