"""The grid a refinement compares on (``image_refine.refine_grid``): the binned detector nearest the asked pixel,
the image and its field binned onto it, only the field's rows traced, and its DRRs those of the full binned
detector inside the field."""

import numpy as np
import pytest

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.registration.image_refine import RefineParameters, refine_grid


def _detector() -> CarmIntrinsics:
    return CarmIntrinsics(1000.0, (0.388, 0.388), (203, 150))


def test_the_grid_is_the_binned_detector_nearest_the_asked_pixel_with_image_and_field_binned_alike():
    """0.388 mm pixels asked at 4 mm: binned by 10 (3.88 mm; 11 would give 4.27), the 203 x 150 detector to the
    20 x 15 bins that fit. The image's bins are the means of its 10 x 10 blocks; a bin is in the field when its
    whole block is (here columns 0-99: bins 0-9), and each row is traced one bin beyond the field (bins 0-10)."""
    cols_px, rows_px = _detector().size_px
    image = np.arange(rows_px * cols_px, dtype=np.float32).reshape(rows_px, cols_px)
    mask = np.zeros((rows_px, cols_px), bool)
    mask[:, :100] = True
    grid = refine_grid(_detector(), RefineParameters(detector_pixel_mm=4.0), image, mask)
    assert grid.detector.size_px == (20, 15)
    assert grid.detector.pixel_spacing_mm == pytest.approx((3.88, 3.88))
    assert grid.image.shape == grid.mask.shape == (15, 20)
    assert grid.image[1, 2] == pytest.approx(image[10:20, 20:30].mean())
    assert grid.mask[:, :10].all() and not grid.mask[:, 10:].any()
    assert grid.spans.shape == (15, 2) and (grid.spans[:, 0] == 0).all() and (grid.spans[:, 1] == 11).all()


def test_the_grids_drrs_are_the_full_binned_detectors_inside_the_field():
    """A uniform cube seen from the nominal AP pose: inside the field (grown by one bin) the grid's DRR is the
    full binned detector's, bit for bit; outside it is not traced (0)."""
    ijk_to_lps = np.diag([4.0, 4.0, 4.0, 1.0])
    ijk_to_lps[:3, 3] = -4.0 * 15.5
    level = MuLevel(np.full((32, 32, 32), 0.02, np.float32), ijk_to_lps, 4.0)
    geometry = CarmGeometry(_detector(), (0.0, 0.0, 0.0), 600.0)
    cols_px, rows_px = _detector().size_px
    mask = np.zeros((rows_px, cols_px), bool)
    mask[30:120, 40:160] = True
    grid = refine_grid(_detector(), RefineParameters(detector_pixel_mm=4.0), np.zeros(mask.shape, np.float32),
                       mask)
    pose = np.zeros((1, 6))
    traced = grid.line_integrals(level, geometry, pose)[0]
    full = render_line_integrals(level, geometry, pose, grid.detector)[0]
    inside = np.zeros(traced.shape, bool)
    for row, (first, last) in enumerate(grid.spans):
        inside[row, first:last] = True
    assert inside.sum() < inside.size and grid.mask.sum() > 0 and (full[grid.mask] > 0).all()
    np.testing.assert_array_equal(traced[inside], full[inside])
    assert not traced[~inside].any()
