"""The image intensifier's radial distortion (``geometry.distortion``) and how the detector carries it."""

import numpy as np
import pytest

from carmreg.logic.errors import GeometryError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
from carmreg.logic.geometry.distortion import RadialDistortion
from carmreg.logic.registration.labelling_fit import oriented_geometry


def test_an_image_point_100_mm_out_is_distortion_mm_outward_of_its_ideal_point():
    warp = RadialDistortion.from_shift(3.0, (511.5, 383.5), (0.25, 0.5))
    shown = np.array([[511.5 + 400.0, 383.5], [511.5, 383.5 - 200.0]])   # 100 mm right, 100 mm up
    ideal = warp.undistort(shown)
    np.testing.assert_allclose(ideal, [[511.5 + 388.0, 383.5], [511.5, 383.5 - 194.0]], atol=1e-9)
    assert warp.shift_at_100_mm == pytest.approx(3.0)


@pytest.mark.parametrize("shift_mm", [4.0, -2.5])
def test_distort_and_undistort_invert_each_other(shift_mm):
    warp = RadialDistortion.from_shift(shift_mm, (300.0, 280.0), (0.3, 0.3))
    uv = np.random.default_rng(3).uniform(0, 600, (50, 2))
    np.testing.assert_allclose(warp.undistort(warp.distort(uv)), uv, atol=1e-9)
    np.testing.assert_allclose(warp.distort(warp.undistort(uv)), uv, atol=1e-9)
    moved = np.linalg.norm(warp.distort(uv) - uv, axis=1)
    assert moved.max() > 1.0  # it does move points (pixels) near the rim


def test_no_distortion_leaves_points_where_they_are():
    uv = np.array([[0.25, 7.0], [1023.0, 0.0]])
    warp = CarmIntrinsics(1000.0, (0.3, 0.3), (1024, 1024)).distortion
    assert warp.k_per_mm2 == 0.0
    assert np.array_equal(warp.distort(uv), uv) and np.array_equal(warp.undistort(uv), uv)


def test_binned_and_turned_detectors_keep_the_distortion_about_the_same_centre():
    intr = CarmIntrinsics(1000.0, (0.25, 0.25), (960, 960), distortion_mm=3.0)
    small = intr.binned(8)
    assert small.distortion_mm == 3.0 and small.distortion.k_per_mm2 == intr.distortion.k_per_mm2
    point_px = np.array([800.0, 120.0])
    binned_px = (point_px - 3.5) / 8  # the same detector point on the binned grid
    np.testing.assert_allclose(small.distortion.distort(binned_px), (intr.distortion.distort(point_px) - 3.5) / 8,
                               atol=1e-9)
    turned = oriented_geometry(CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0), "turned-90").intrinsics
    assert turned.distortion_mm == 3.0


@pytest.mark.parametrize("shift_mm", [10.5, float("nan"), 9.0])
def test_an_implausible_distortion_is_refused_with_the_option_to_fix(shift_mm):
    size = (1536, 1536) if shift_mm == 9.0 else (512, 512)   # 9 mm is allowed, but not on a 600 mm detector
    with pytest.raises(GeometryError, match="is not plausible: give --distortion-mm from the C-arm's calibration"):
        CarmIntrinsics(1000.0, (0.39, 0.39), size, distortion_mm=shift_mm)
    CarmIntrinsics(1000.0, (0.39, 0.39), (512, 512), distortion_mm=-4.0)  # barrel: accepted
