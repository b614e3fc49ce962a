"""An image without its shading (``image.shading``): the shading goes, the detail and the field's edge stay."""

import numpy as np
import pytest

from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.image.shading import without_shading
from carmreg.logic.registration.image_refine import RefineParameters, grid_scores, refine_grid
from carmreg.logic.similarity.metrics import gc


def _field(rows: int = 120, cols: int = 160) -> np.ndarray:
    """A circular field (rows, cols), as an image intensifier's."""
    v, u = np.mgrid[:rows, :cols]
    return (u - cols / 2) ** 2 + (v - rows / 2) ** 2 < (0.45 * rows) ** 2


def _spine(rows: int = 120, cols: int = 160) -> np.ndarray:
    """A bright vertical band 8 px wide with a notch every 20 rows: the detail the shading hides."""
    image = np.zeros((rows, cols))
    image[:, cols // 2 - 4:cols // 2 + 4] = 1.0
    image[::20, cols // 2 - 4:cols // 2 + 4] = 0.3
    return image


def _hump(amplitude: float, width_px: float = 40.0) -> np.ndarray:
    """A slow hump of shading (rows, cols) = (120, 160) beside the spine."""
    v, u = np.mgrid[:120, :160]
    return amplitude * np.exp(-((u - 50.0) ** 2 + (v - 70.0) ** 2) / (2 * width_px ** 2))


def test_a_shading_wider_than_the_scale_is_removed_and_the_detail_kept():
    mask = _field()
    out = without_shading(_spine() + _hump(3.0), mask, 6.0)
    clean = without_shading(_spine(), mask, 6.0)
    residue = out - clean  # the filter is linear: what is left of the hump
    assert np.ptp(residue[mask]) < 0.1 * np.ptp(_hump(3.0)[mask])
    assert np.ptp(clean[mask]) > 0.8  # the band's contrast (1) mostly kept
    assert np.all(out[~mask] == 0.0)
    assert np.abs(without_shading(np.full((120, 160), 7.0), mask, 6.0)).max() < 1e-9  # the field's edge is no edge


def test_a_stack_is_each_image_alone_and_the_dtype_kept():
    mask = _field()
    stack = np.stack([_spine(), 2.0 * _spine()[::-1], _spine() + _hump(2.0)]).astype(np.float32)
    out = without_shading(stack, mask, 5.0)
    assert out.dtype == np.float32
    for image, alone in zip(stack, out, strict=True):
        np.testing.assert_allclose(alone, without_shading(image, mask, 5.0), atol=1e-5)
    assert without_shading(np.ones((120, 160), np.uint16), mask, 5.0).dtype == np.float32


def test_the_refinement_compared_without_shading_scores_the_bone_more_than_the_hump():
    """A faint spine under a hump of shading (a large patient's scatter): plain GC (0.52) follows the hump as much
    as the spine; compared without shading (``RefineParameters.without_shading_mm``), the spine agrees (0.79)."""
    mask = _field()
    xray = 0.2 * _spine() + _hump(3.0)  # bone bright
    drr = _spine()[None]
    detector = CarmIntrinsics(1000.0, (2.0, 2.0), (160, 120))  # 2 mm pixels: the refinement's grid, not binned
    grid = refine_grid(detector, RefineParameters(detector_pixel_mm=2.0), xray, mask)
    assert grid.image.shape == xray.shape and np.array_equal(grid.mask, mask)
    plain = grid_scores(RefineParameters(), grid)(drr)[0]
    unshaded = grid_scores(RefineParameters(without_shading_mm=20.0), grid)(drr)[0]
    fixed = grid.image  # the X-ray as the refinement holds it (float32)
    assert plain == pytest.approx(gc(fixed, drr, mask)[0]) and plain < 0.6
    assert unshaded > plain + 0.2
    sigma_px = 20.0 / 2.0
    assert unshaded == pytest.approx(gc(without_shading(fixed, mask, sigma_px), without_shading(drr, mask, sigma_px),
                                        mask)[0], abs=1e-7)  # float32 images: their rounding
