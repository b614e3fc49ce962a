"""Where the search on the image alone starts: spatial-map peaks, swept over the C-arm's turn in the image plane
(``registration.image_starts``), on DRRs of the sample CT."""

import numpy as np
import pytest

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.camera import CarmIntrinsics, nominal_geometry
from carmreg.logic.geometry.volume import MuPyramid
from carmreg.logic.registration.database import build_database
from carmreg.logic.registration.image_starts import IN_PLANE_DEG, image_starts, spatial_peaks, turned_maps
from carmreg.logic.similarity.metrics import gc, gc_against_each


def test_spatial_peaks_are_separated_local_maxima_best_first():
    ty, tz = np.arange(-10.0, 12.0, 2.0), np.arange(-40.0, 42.0, 2.0)
    yy, zz = np.meshgrid(ty, tz, indexing="ij")
    score = np.exp(-((yy - 2) ** 2 + (zz - 10) ** 2) / 20) + 0.8 * np.exp(-((yy + 4) ** 2 + (zz + 16) ** 2) / 20)
    peaks = spatial_peaks(score, ty, tz, 3)
    assert peaks[:2] == [(2.0, 10.0), (-4.0, -16.0)]


@pytest.fixture(scope="module")
def grid_of_drrs(sample_ct):
    """A database of the sample CT at 4 mm on a 4 mm detector, (ty, tz) every 4 mm within +-24 mm."""
    ct = sample_ct[0]
    intrinsics = CarmIntrinsics(1000.0, (4.0, 4.0), (64, 64))
    geometry = nominal_geometry(intrinsics, ct, 600.0)
    level = MuPyramid(ct).level(4.0)
    axis = np.arange(-24.0, 25.0, 4.0)
    return level, geometry, build_database(level, geometry, intrinsics, axis, axis)


@pytest.mark.parametrize("rx_deg", [6.0, -9.0])
def test_an_xray_turned_in_its_plane_starts_at_its_pose_turn_included(grid_of_drrs, rx_deg):
    """The X-ray of the pose (ty, tz, rx): turned back by -rx it matches the DRR of (ty, tz) without rotation
    (the C-arm turns about the principal ray), so the best start is that pose, and the swept map scores the true
    (ty, tz) higher than the map without a turn does."""
    level, geometry, db = grid_of_drrs
    pose = np.array([0.0, 8.0, -12.0, rx_deg, 0.0, 0.0])
    xray = render_line_integrals(level, geometry, pose)
    field = np.ones(xray.shape, bool)
    best = image_starts(db, xray, field, 3)[0]
    np.testing.assert_allclose(best, [0.0, 8.0, -12.0, rx_deg, 0.0, 0.0], atol=1e-9)
    swept, angle = turned_maps(db, xray, field)
    flat, _ = turned_maps(db, xray, field, angles_deg=(0.0,))
    iy, iz = list(db.ty_mm).index(8.0), list(db.tz_mm).index(-12.0)
    assert angle[iy, iz] == -rx_deg and swept[iy, iz] > 0.9 and swept[iy, iz] > flat[iy, iz] + 0.05


def test_gc_against_several_fixed_images_is_gc_against_each(grid_of_drrs):
    """``metrics.gc_against_each``, which the sweep scores with, gives column by column what ``gc`` gives, bit for
    bit."""
    level, geometry, db = grid_of_drrs
    xray = render_line_integrals(level, geometry, np.array([0.0, -4.0, 4.0, 3.0, 0.0, 0.0]))
    field = np.zeros(xray.shape, bool)
    field[8:56, 6:60] = True
    fixed = np.stack([xray, xray[:, ::-1], np.roll(xray, 5, axis=0)])
    moving = db.drrs.reshape(-1, *xray.shape)[::7]
    each = gc_against_each(fixed, moving, field)
    assert each.shape == (len(moving), 3)
    for j in range(3):
        np.testing.assert_array_equal(each[:, j], gc(fixed[j], moving, field))
    assert each[:, 0].max() > 0.5 and not np.allclose(each[:, 0], each[:, 1], atol=0.05)
    assert np.all(gc_against_each(fixed, moving, np.zeros_like(field)) == 0.0)  # no pixel to compare


def test_the_turned_field_is_the_one_every_turn_exposes(grid_of_drrs):
    """A rectangular field loses its corners to the turns; a pose without turn still starts unturned."""
    level, geometry, db = grid_of_drrs
    xray = render_line_integrals(level, geometry, np.array([0.0, -4.0, 4.0, 0.0, 0.0, 0.0]))
    field = np.zeros(xray.shape, bool)
    field[4:60, 10:54] = True
    assert image_starts(db, xray, field, 1)[0].tolist() == [0.0, -4.0, 4.0, 0.0, 0.0, 0.0]
    outside = xray.copy()
    outside[~field] = 1e3  # nothing outside the field may count, whatever the turn
    np.testing.assert_array_equal(turned_maps(db, outside, field)[0], turned_maps(db, xray, field)[0])
    assert 0.0 in IN_PLANE_DEG and max(IN_PLANE_DEG) == -min(IN_PLANE_DEG) == 9.0


def test_a_field_too_small_for_the_turns_is_scored_without_a_turn(grid_of_drrs):
    level, geometry, db = grid_of_drrs
    xray = render_line_integrals(level, geometry, np.array([0.0, -4.0, 4.0, 0.0, 0.0, 0.0]))
    field = np.zeros(xray.shape, bool)
    field[28:35, 28:35] = True  # 7 x 7 px: nothing is left once shrunk by 2 and turned by 9 degrees
    best, angle = turned_maps(db, xray, field)
    plain = gc(xray, db.drrs.reshape(-1, *xray.shape), field).reshape(best.shape)
    np.testing.assert_allclose(best, plain, atol=1e-5)
    assert np.all(angle == 0.0) and np.ptp(best) > 0.1
