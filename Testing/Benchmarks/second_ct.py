"""The benchmark's second real CT: ``example_ct.nii.gz`` from the TotalSegmentator test data (../shared).

Abdomen and pelvis, 122 x 101 x 112 voxels of 3 mm, HU (Apache-2.0; see the data folder's README and LICENSE).
It has no vertebra segmentation, so:

- the named vertebral centroids (L1..L5, S1; LPS mm) are committed beside this file in
  ``data/example_ct_centroids.mrk.json``, derived by ``scripts/label_example_ct.py`` (disc detection along the
  vertebral bodies, names anchored to the TotalSegmentator labels of the crop ``example_seg.nii.gz``);
- the vertebra label map the simulator needs (each level moves rigidly on its own) is built from those
  centroids by ``carmreg.logic.geometry.vertebrae.label_map_from_centroids``: bone voxels (HU > 150) within
  ``LABEL_RADIUS_MM`` of the spine polyline, cut into slabs at the midpoints between centroids.

The CT itself is never copied into the repository; without ../shared the loader returns None.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carmreg.logic.geometry.vertebrae import label_map_from_centroids
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.landmarks import Landmarks3D, read_landmarks_3d
from carmreg.logic.io.volumes import load_volume

CENTROIDS_PATH = Path(__file__).resolve().parent / "data" / "example_ct_centroids.mrk.json"
CT_RELATIVE_PATH = Path("data") / "totalsegmentator-tests" / "example_ct.nii.gz"
LABEL_RADIUS_MM = 45.0
"""Reach of each level's label around the spine polyline: the vertebral body (front <= ~40 mm from the
centroid) and transverse processes; spinous-process tips (~55 mm) stay unlabelled, and so does most of the
iliac bone beside S1 (the sacroiliac joints lie ~50-55 mm from the midline)."""


def default_shared_dir() -> Path:
    """../shared beside the repository (``/work/main/../shared``)."""
    return Path(__file__).resolve().parents[2].parent / "shared"


def load_second_ct(shared_dir: Path | None = None) -> tuple[Volume, np.ndarray, Landmarks3D] | None:
    """(CT volume in HU, uint8 CarmReg vertebra label map on the CT grid, named centroids in LPS mm),
    or None when ``shared_dir`` (default ../shared) does not hold the CT."""
    path = (default_shared_dir() if shared_dir is None else Path(shared_dir)) / CT_RELATIVE_PATH
    if not path.is_file():
        return None
    ct = load_volume(path)
    centroids = read_landmarks_3d(CENTROIDS_PATH)
    labels = label_map_from_centroids(ct, centroids, radius_mm=LABEL_RADIUS_MM)
    return ct, labels, centroids
