"""Vertebra label maps from centroids, and the benchmark's second real CT (TotalSegmentator example_ct).

The real-CT tests need ../shared/data/totalsegmentator-tests and skip cleanly without it.
"""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.vertebrae import (
    TOTALSEGMENTATOR_V2_VERTEBRAE,
    carmreg_label_value,
    label_map_from_centroids,
    spine_slab_planes,
    summarize_labels,
)
from carmreg.logic.geometry.volume import Volume, apply_affine
from carmreg.logic.io.landmarks import Landmarks3D, level_index

REPO = Path(__file__).resolve().parents[3]
SHARED = REPO.parent / "shared"
TOTALSEG = SHARED / "data" / "totalsegmentator-tests"


def _second_ct_module():
    spec = importlib.util.spec_from_file_location("second_ct", REPO / "Testing" / "Benchmarks" / "second_ct.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------------------------- synthetic

def two_block_volume(affine: np.ndarray, shape=(40, 40, 60)) -> tuple[Volume, dict]:
    """Soft tissue (40 HU) with bone blocks (600 HU, 20 mm cubes) at LPS z = +20 and -20 mm on the z axis,
    plus single bone voxels at chosen places; voxels are filled by their LPS centre (any affine)."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    x = apply_affine(affine, ijk.astype(float))
    hu = np.full(len(x), 40.0, np.float32)
    for zc in (20.0, -20.0):
        hu[np.all(np.abs(x - (0.0, 0.0, zc)) <= 10.0, axis=1)] = 600.0
    return Volume(hu.reshape(shape), affine, "synthetic"), {"x": x.reshape(shape + (3,))}


def centered_affine(spacing_mm: float, shape, angles_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix() * spacing_mm
    affine[:3, 3] = -affine[:3, :3] @ ((np.asarray(shape, float) - 1.0) / 2.0)
    return affine


@pytest.mark.parametrize("angles", [(0.0, 0.0, 0.0), (20.0, -15.0, 35.0)])
def test_two_blocks_get_their_own_labels(angles):
    shape = (40, 40, 60)
    ct, extra = two_block_volume(centered_affine(2.0, shape, angles), shape)
    centroids = Landmarks3D(["L2", "L1"], [[0.0, 0.0, -20.0], [0.0, 0.0, 20.0]])  # L1 superior (+z)
    labels = label_map_from_centroids(ct, centroids)
    x, hu = extra["x"], ct.hu
    upper = (hu > 150) & (x[..., 2] > 5)
    lower = (hu > 150) & (x[..., 2] < -5)
    assert upper.sum() > 500 and lower.sum() > 500
    assert np.all(labels[upper] == carmreg_label_value("L1")) and carmreg_label_value("L1") == 21
    assert np.all(labels[lower] == carmreg_label_value("L2"))
    assert np.all(labels[hu <= 150] == 0)
    assert labels.dtype == np.uint8


def test_radius_end_slabs_and_threshold():
    shape = (60, 60, 60)
    affine = centered_affine(2.0, shape)   # voxel centres at odd LPS mm coordinates
    ct, _ = two_block_volume(affine, shape)
    probes = {"lateral_39": (39.0, 1.0, 1.0), "lateral_45": (45.0, 1.0, 1.0),
              "above_end_19": (1.0, 1.0, 39.0), "above_end_23": (1.0, 1.0, 43.0),
              "below_mid_3": (1.0, 29.0, -3.0), "posterior_41": (1.0, 41.0, 11.0)}
    to_ijk = np.linalg.inv(affine)
    index = {}
    for name, p in probes.items():
        ijk = apply_affine(to_ijk, np.array([p]))[0]
        assert np.allclose(ijk, np.round(ijk))
        index[name] = tuple(int(v) for v in np.round(ijk))
        ct.hu[index[name]] = 400.0
    centroids = Landmarks3D(["L1", "L2"], [[0.0, 0.0, 20.0], [0.0, 0.0, -20.0]])
    labels = label_map_from_centroids(ct, centroids, radius_mm=40.0, bone_hu=150.0)
    got = {name: int(labels[idx]) for name, idx in index.items()}
    assert got == {"lateral_39": 21,      # 39.0 mm from the polyline, above the mid-plane z = 0: L1
                   "lateral_45": 0,       # beyond the 40 mm radius
                   "above_end_19": 21,    # the end slab reaches half a spacing (20 mm) above L1
                   "above_end_23": 0,
                   "below_mid_3": 22,     # below the mid-plane: L2
                   "posterior_41": 0}
    assert int(label_map_from_centroids(ct, centroids, bone_hu=500.0)[index["lateral_39"]]) == 0
    assert int(label_map_from_centroids(ct, centroids, radius_mm=50.0)[index["lateral_45"]]) == 21


def test_slab_planes_follow_a_bent_spine():
    c = np.array([[0.0, 0.0, 60.0], [0.0, 0.0, 30.0], [0.0, -15.0, 4.0]])
    points, normals = spine_slab_planes(c)
    assert points.shape == (4, 3) and np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.allclose(points[0], [0, 0, 75]) and np.allclose(points[1], [0, 0, 45])
    assert np.allclose(points[2], (c[1] + c[2]) / 2)
    assert np.allclose(points[3], c[2] + (c[2] - c[1]) / 2)
    assert np.allclose(normals[2], (c[2] - c[1]) / np.linalg.norm(c[2] - c[1]))


def test_needs_two_distinct_centroids():
    shape = (10, 10, 10)
    ct, _ = two_block_volume(centered_affine(2.0, shape), shape)
    with pytest.raises(LandmarkError, match="at least 2"):
        label_map_from_centroids(ct, Landmarks3D(["L1"], [[0.0, 0.0, 0.0]]))
    with pytest.raises(LandmarkError, match="coincide"):
        label_map_from_centroids(ct, Landmarks3D(["L1", "L2"], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))


# ----------------------------------------------------------------------------------------------- real CT

@pytest.fixture(scope="module")
def second_ct():
    loaded = _second_ct_module().load_second_ct(SHARED)
    if loaded is None:
        pytest.skip(f"the second real CT is absent from {TOTALSEG}")
    return loaded


def test_loader_returns_none_without_shared(tmp_path):
    assert _second_ct_module().load_second_ct(tmp_path) is None


def test_label_map_is_fast_and_covers_each_level(second_ct):
    ct, labels, centroids = second_ct
    t0 = time.perf_counter()
    again = label_map_from_centroids(ct, centroids)
    assert time.perf_counter() - t0 < 2.0
    assert labels.shape == ct.shape and labels.dtype == np.uint8
    for name in centroids.labels:
        assert int(np.sum(again == carmreg_label_value(name))) > 800, name
    assert set(np.unique(labels)) == {0, *(carmreg_label_value(n) for n in centroids.labels)}


def test_committed_centroids_in_bone_and_evenly_spaced(second_ct):
    ct, _, centroids = second_ct
    assert centroids.labels == ["L1", "L2", "L3", "L4", "L5", "S1"]
    ijk = np.argwhere(np.ones(ct.shape, bool))
    x = apply_affine(ct.ijk_to_lps, ijk.astype(float))
    hu = ct.hu.reshape(-1)
    for name, c in centroids.as_dict().items():
        near = np.linalg.norm(x - c, axis=1) < 20.0
        assert np.mean(hu[near] > 150) > 0.2, name      # soft tissue of this CT: 0.0
    spacing = np.linalg.norm(np.diff(centroids.sorted().points_lps_mm, axis=0), axis=1)
    assert np.all((spacing > 20.0) & (spacing < 45.0)), spacing
    assert np.all(np.diff(centroids.sorted().points_lps_mm[:, 2]) < 0)   # head to sacrum = descending z


def _seg_summaries(ct: Volume):
    from carmreg.logic.io.volumes import load_volume

    crop = np.asarray(load_volume(TOTALSEG / "example_ct_sm.nii.gz").hu)
    full = np.asarray(ct.hu)
    n = crop.shape[2]
    k0 = next(k for k in range(full.shape[2] - n + 1) if np.array_equal(full[:, :, k:k + n], crop))
    shift = np.eye(4)
    shift[2, 3] = k0   # the crop's header repeats the full CT's affine
    seg = np.asarray(load_volume(TOTALSEG / "example_seg.nii.gz").hu)
    return k0, summarize_labels(seg, ct.ijk_to_lps @ shift, TOTALSEGMENTATOR_V2_VERTEBRAE)


def test_names_agree_with_example_seg(second_ct):
    ct, _, centroids = second_ct
    k0, summaries = _seg_summaries(ct)
    assert k0 == 82
    found = centroids.as_dict()
    complete = [s for s in summaries if s.complete]
    assert [s.name for s in complete] == ["L1"]
    for s in complete:
        assert np.linalg.norm(found[s.name] - s.centroid_lps_mm) < 5.0
    for s in summaries:   # every labelled level, cut or not, is nearest to the centroid of the same name
        if s.name in found:
            nearest = min(found, key=lambda n: np.linalg.norm(found[n] - s.centroid_lps_mm))
            assert nearest == s.name
    assert "T12" not in found   # T12 reaches the top slice of the scan
    assert sorted(found, key=level_index) == centroids.labels


def test_simulated_image_of_second_ct_shows_several_levels(second_ct):
    from carmreg.logic.simulation.options import SimulationOptions, default_geometry, sample_options
    from carmreg.logic.simulation.scene import random_pose
    from carmreg.logic.simulation.simulator import simulate_case

    ct, labels, centroids = second_ct
    rng = np.random.default_rng(1000)
    options = sample_options(rng, SimulationOptions(size_px=(512, 512), pixel_spacing_mm=0.5))
    geometry = default_geometry(ct, options)
    names = centroids.sorted().labels
    pose = random_pose(rng, options, centroids, names[len(names) // 2], geometry=geometry)
    sim = simulate_case(ct, labels, centroids, geometry, pose, options, seed=0)
    assert sim.pixels.shape == (512, 512)
    visible = [n for n, v in sim.visible.items() if v]
    assert len(visible) >= 3, sim.visible
    assert len(sim.clicks.labels) == 3 and set(sim.clicks.labels) <= set(visible)
    assert set(sim.motions) == set(names)   # every level moved on its own
