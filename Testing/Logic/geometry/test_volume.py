"""CT volume: HU -> mu, isotropic resampling keeps physical positions, the mu pyramid caches levels."""

import numpy as np
import pytest

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.camera import rotation_matrix
from carmreg.logic.geometry.volume import (
    MU_WATER_PER_MM,
    MuPyramid,
    Volume,
    apply_affine,
    hu_to_mu,
    resample_isotropic,
)


def oblique_affine(spacing=(0.8, 0.9, 2.5), origin=(-40.0, 25.0, 100.0)):
    """ijk -> LPS with a rotated, axis-flipped direction matrix."""
    direction = rotation_matrix([1, 2, 3], 25.0) @ np.diag([1.0, -1.0, 1.0])
    affine = np.eye(4)
    affine[:3, :3] = direction * np.asarray(spacing)
    affine[:3, 3] = origin
    return affine


def test_hu_to_mu_values():
    hu = np.array([-2048, -1024, -1000, 0, 1000, 3071], dtype=np.int16)
    mu = hu_to_mu(hu)
    assert mu.dtype == np.float32
    expected = MU_WATER_PER_MM * np.array([0.0, 0.0, 0.0, 1.0, 2.0, 4.071])
    assert np.allclose(mu, expected, rtol=1e-6, atol=1e-9)
    assert np.allclose(hu_to_mu(np.array([0.0]), mu_water_per_mm=0.03), [0.03])


def blob_volume(affine, shape=(60, 50, 24), centre_ijk=(33.3, 21.7, 11.4), sigma_vox=(3.0, 3.0, 1.2)):
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    r2 = (((ijk - np.asarray(centre_ijk)) / np.asarray(sigma_vox)) ** 2).sum(-1)
    return (1000.0 * np.exp(-0.5 * r2)).astype(np.float32)


def world_centroid(values, affine):
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in values.shape], indexing="ij"), -1).reshape(-1, 3)
    w = values.reshape(-1).astype(np.float64)
    return apply_affine(affine, (ijk * w[:, None]).sum(0) / w.sum())


@pytest.mark.parametrize("spacing_mm", [2.0, 4.0])
def test_resample_isotropic_keeps_world_positions(spacing_mm):
    affine = oblique_affine()
    values = blob_volume(affine)
    out, new_affine = resample_isotropic(values, affine, spacing_mm)
    assert np.allclose(np.linalg.norm(new_affine[:3, :3], axis=0), spacing_mm, rtol=0.1)
    # same index axes (directions), only the spacing changes
    assert np.allclose(new_affine[:3, :3] / np.linalg.norm(new_affine[:3, :3], axis=0),
                       affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0))
    shift_mm = np.linalg.norm(world_centroid(out, new_affine) - world_centroid(values, affine))
    assert shift_mm < 0.5 * spacing_mm
    assert shift_mm < 0.3  # a smooth blob keeps its centre much better than half a voxel


def test_resample_isotropic_keeps_the_physical_box():
    affine = oblique_affine()
    volume = Volume(np.zeros((60, 50, 24), np.float32), affine)
    out, new_affine = resample_isotropic(volume.hu, affine, 4.0)
    coarse = Volume(out, new_affine)
    assert np.allclose(np.sort(coarse.corners_lps_mm(), 0), np.sort(volume.corners_lps_mm(), 0), atol=1e-9)


def test_pyramid_caches_levels():
    affine = oblique_affine()
    volume = Volume(blob_volume(affine) - 1000.0, affine)
    pyramid = MuPyramid(volume)
    full = pyramid.level(None)
    assert pyramid.level() is full
    assert np.allclose(full.mu_per_mm, hu_to_mu(volume.hu))
    assert full.mu_per_mm.dtype == np.float32 and full.mu_per_mm.flags.c_contiguous
    coarse = pyramid.level(4.0)
    assert pyramid.level(4.0) is coarse
    assert pyramid.level(4.00001) is coarse
    assert coarse.spacing_mm == 4.0
    assert coarse.mu_per_mm.dtype == np.float32 and coarse.mu_per_mm.flags.c_contiguous
    assert pyramid.level(2.0) is not coarse


def test_pyramid_levels_kept_in_the_cache_are_the_levels_bit_for_bit(tmp_path):
    """A second run takes the resampled level from the cache folder: the same voxels and affine, exactly; a
    damaged cache entry is a miss (resampled again), never trusted."""
    from carmreg.logic.io.array_cache import ArrayCache

    affine = oblique_affine()
    volume = Volume(blob_volume(affine) - 1000.0, affine)
    first = MuPyramid(volume, cache=ArrayCache(tmp_path)).level(3.0)
    entries = sorted(tmp_path.glob("mu-*.npy"))
    assert len(entries) == 1
    again = MuPyramid(volume, cache=ArrayCache(tmp_path)).level(3.0)
    assert np.array_equal(again.mu_per_mm, first.mu_per_mm) and np.array_equal(again.ijk_to_lps, first.ijk_to_lps)
    assert again.mu_per_mm.flags.c_contiguous and again.mu_per_mm.flags.writeable
    data = np.load(entries[0])
    data.flat[0] += 1.0
    np.save(entries[0], data)  # the sidecar's SHA-256 no longer matches
    repaired = MuPyramid(volume, cache=ArrayCache(tmp_path)).level(3.0)
    assert np.array_equal(repaired.mu_per_mm, first.mu_per_mm)
    other = MuPyramid(Volume(volume.hu + 1.0, affine), cache=ArrayCache(tmp_path)).level(3.0)
    assert not np.array_equal(other.mu_per_mm, first.mu_per_mm)  # another CT: another key


def test_volume_rejects_bad_geometry():
    with pytest.raises(InputFileError):
        Volume(np.zeros((4, 4), np.float32), np.eye(4))
    with pytest.raises(InputFileError):
        Volume(np.zeros((4, 4, 4), np.float32), np.diag([1.0, 0.0, 1.0, 1.0]))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(InputFileError):
        Volume(np.zeros((4, 4, 4), np.float32), bad)


def test_volume_centre_and_containment():
    affine = oblique_affine()
    volume = Volume(np.zeros((10, 20, 30), np.float32), affine)
    centre = volume.center_lps_mm()
    assert np.allclose(centre, apply_affine(affine, [4.5, 9.5, 14.5]))
    assert np.allclose(volume.corners_lps_mm().mean(0), centre)
    outside = apply_affine(affine, [-3.0, 5.0, 5.0])
    assert volume.contains_lps(np.array([centre, outside])).tolist() == [True, False]
