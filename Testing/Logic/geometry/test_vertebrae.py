"""Vertebral centroids from label maps: centre of mass through the affine, completeness, label conventions."""

from __future__ import annotations

import numpy as np
import pytest

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.vertebrae import (
    CARMREG_VERTEBRAE,
    TOTALSEGMENTATOR_V2_VERTEBRAE,
    carmreg_label_value,
    centroids_from_labels,
    level_ordinals,
    summarize_labels,
    superior_axis,
    to_carmreg_labels,
)
from carmreg.logic.geometry.volume import apply_affine
from carmreg.logic.io.landmarks import LEVEL_NAMES


def oblique_affine(spacing_mm, angles_deg) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix() * np.asarray(spacing_mm)
    affine[:3, 3] = (-101.25, 37.5, 812.125)
    return affine


def test_totalsegmentator_v2_ids():
    ts = TOTALSEGMENTATOR_V2_VERTEBRAE
    assert (ts[43], ts[42], ts[33], ts[32], ts[31], ts[30], ts[29]) == ("T1", "T2", "T11", "T12", "L1", "L2",
                                                                        "L3")
    assert (ts[26], ts[27], ts[44], ts[50]) == ("S1", "L5", "C7", "C1")
    assert 25 not in ts and len(ts) == 25


def test_carmreg_values():
    assert [carmreg_label_value(n) for n in ("C1", "T1", "T12", "L1", "S1")] == [1, 8, 19, 21, 27]
    assert all(CARMREG_VERTEBRAE[1 + i] == n for i, n in enumerate(LEVEL_NAMES))
    labels = np.array([[[0, 32, 31, 5, 25]]])
    np.testing.assert_array_equal(to_carmreg_labels(labels, TOTALSEGMENTATOR_V2_VERTEBRAE), [[[0, 19, 21, 0, 0]]])


def test_centroid_is_centre_of_mass_through_oblique_affine():
    affine = oblique_affine(spacing_mm=(0.7, 0.8, 2.0), angles_deg=(5.0, -8.0, 12.0))
    labels = np.zeros((30, 25, 20), np.uint8)
    labels[4:9, 3:10, 5:8] = 19          # T12: a box
    labels[10:20, 12:15, 9:15] = 21      # L1
    labels[10, 12, 14] = 0               # make L1 asymmetric
    lm = centroids_from_labels(labels, affine, CARMREG_VERTEBRAE)
    assert lm.labels == ["T12", "L1"]
    expected_t12 = apply_affine(affine, np.array([6.0, 6.0, 6.0]))
    expected_l1 = apply_affine(affine, np.argwhere(labels == 21).mean(axis=0))
    np.testing.assert_allclose(lm.points_lps_mm, [expected_t12, expected_l1], atol=1e-9)


def test_vertebra_touching_first_or_last_slice_is_incomplete():
    affine = np.diag([0.8, 0.8, 2.5, 1.0])
    labels = np.zeros((10, 10, 12), np.uint8)
    labels[2:5, 2:5, 0:3] = 21     # L1 touches slice 0 -> cut by the scan
    labels[2:5, 2:5, 4:7] = 19     # T12 complete
    labels[2:5, 2:5, 9:12] = 18    # T11 touches the last slice
    labels[0:3, 5:8, 4:7] = 17     # T10 touches an in-plane edge only: still complete
    summary = {s.name: s.complete for s in summarize_labels(labels, affine, CARMREG_VERTEBRAE)}
    assert summary == {"T10": True, "T11": False, "T12": True, "L1": False}
    assert centroids_from_labels(labels, affine, CARMREG_VERTEBRAE).labels == ["T10", "T12"]
    assert centroids_from_labels(labels, affine, CARMREG_VERTEBRAE, include_incomplete=True).labels == [
        "T10", "T11", "T12", "L1"]


def test_slice_axis_follows_the_affine():
    # volume stored with the superior-inferior axis first: completeness must use axis 0
    affine = np.array([[0, 0, 0.8, 0], [0, 0.8, 0, 0], [2.5, 0, 0, 0], [0, 0, 0, 1.0]])
    assert superior_axis(affine) == 0
    labels = np.zeros((8, 10, 10), np.uint8)
    labels[0:2, 3:5, 0:3] = 19     # touches i = 0 (a z end) -> incomplete
    labels[3:5, 3:5, 0:3] = 20     # touches k = 0, an in-plane edge -> complete
    assert centroids_from_labels(labels, affine, CARMREG_VERTEBRAE).labels == ["T13"]


def test_no_vertebra_raises():
    with pytest.raises(LandmarkError, match="no complete vertebra"):
        centroids_from_labels(np.zeros((4, 4, 4), np.uint8), np.eye(4), CARMREG_VERTEBRAE)


def test_level_ordinals_skip_absent_transitional_levels():
    assert level_ordinals(["T11", "T12", "L1"]) == {"T11": 17, "T12": 18, "L1": 19}
    with_t13 = level_ordinals(["T12", "T13", "L1"])
    assert with_t13["L1"] - with_t13["T12"] == 2 and with_t13["T13"] - with_t13["T12"] == 1
    assert level_ordinals(["L5", "S1"])["S1"] - level_ordinals(["L5", "S1"])["L5"] == 1
