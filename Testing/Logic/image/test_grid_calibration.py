"""An intensifier's pincushion measured on a bead-grid X-ray (``image.grid_calibration``, ``carmreg
calibrate-distortion``): grids drawn through CarmReg's model are recovered exactly, a grid drawn through another
pincushion model gives that model's shift 100 mm out, and what is no grid is refused in one line."""

import numpy as np
import pytest
from grid_images import PIXEL_MM, STEP_MM, grid_image

from carmreg.cli import main
from carmreg.logic.errors import InputFileError, RegistrationError
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.image.grid_calibration import calibrate, calibrate_for_detector
from carmreg.logic.io.xray import write_png16


@pytest.mark.parametrize("shift_mm, beads_dark", [(3.0, True), (-1.5, True), (0.0, False), (6.0, False)])
def test_a_grid_drawn_through_carmregs_model_gives_its_shift_back(shift_mm, beads_dark):
    cal = calibrate(grid_image(shift_mm, beads_dark=beads_dark), (PIXEL_MM, PIXEL_MM))
    assert cal.distortion_mm == pytest.approx(shift_mm, abs=0.03)
    assert cal.beads > 450 and cal.rms_mm < 0.04 and cal.grid_step_mm == pytest.approx(STEP_MM, abs=0.1)
    if shift_mm:
        assert cal.rms_pinhole_mm > 5 * cal.rms_mm  # the pincushion explains what a pinhole leaves


def test_a_grid_drawn_through_another_model_gives_that_models_shift_100_mm_out():
    """r (1 + k r^2) with k = 3e-6: an image point 100 mm out comes from r = 97.19 mm, a 2.81 mm shift; the fit over
    the whole field (out to 110 mm) finds within 0.15 mm of it."""
    ideal_r = 100.0
    for _ in range(50):
        ideal_r = 100.0 / (1 + 3e-6 * ideal_r**2)
    cal = calibrate(grid_image(3.0, model="forward"), (PIXEL_MM, PIXEL_MM))
    assert cal.distortion_mm == pytest.approx(100.0 - ideal_r, abs=0.15)


def test_an_image_without_a_grid_is_refused():
    rng = np.random.default_rng(4)
    blank = 1000.0 + rng.normal(0.0, 15.0, (400, 400))
    with pytest.raises(RegistrationError, match="found 0 beads on one grid .* needs at least 16"):
        calibrate(blank, (0.3, 0.3))
    scattered = blank.copy()
    rows, cols = np.mgrid[0:400, 0:400]
    for u, v in rng.uniform(30, 370, (60, 2)):
        scattered -= 600.0 * np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / 10.0)
    with pytest.raises(RegistrationError, match="needs at least 16|do not lie on one distorted grid"):
        calibrate(scattered, (0.3, 0.3))


def test_the_command_prints_the_value_to_give_and_refuses_in_one_line(tmp_path, capsys):
    png = write_png16(tmp_path / "grid.png", grid_image(3.0).astype(np.uint16))
    assert main(["calibrate-distortion", "--image", str(png), "--pixel-spacing-mm", str(PIXEL_MM)]) == 0
    out = capsys.readouterr().out
    assert "pincushion 3.00 mm at 100 mm from the centre" in out and "use: --distortion-mm 3.00" in out
    assert main(["calibrate-distortion", "--image", str(png)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the detector pixel spacing is not in the file; give --pixel-spacing-mm" in err


def test_a_grid_image_takes_the_x_rays_spacing_and_centre_only_when_it_has_the_x_rays_size():
    """``calibrate_for_detector``: a grid image without its own pixel spacing and of the X-ray's size is measured
    with the X-ray's spacing and principal point; of another size, it is refused in one line."""
    grid = grid_image(3.0)
    xray = CarmIntrinsics(1000.0, (PIXEL_MM, PIXEL_MM), grid.shape[::-1])
    assert calibrate_for_detector(grid, None, xray).distortion_mm == pytest.approx(3.0, abs=0.03)
    moved = CarmIntrinsics(1000.0, (PIXEL_MM, PIXEL_MM), grid.shape[::-1], (420.0, 360.0))
    assert calibrate_for_detector(grid, None, moved).distortion_mm != pytest.approx(3.0, abs=0.03)
    other = CarmIntrinsics(1000.0, (PIXEL_MM, PIXEL_MM), (grid.shape[1] + 10, grid.shape[0]))
    with pytest.raises(InputFileError, match="grid.png: the grid image .* states no pixel spacing"):
        calibrate_for_detector(grid, None, other, "grid.png")
    assert calibrate_for_detector(grid, (PIXEL_MM, PIXEL_MM), other).distortion_mm == pytest.approx(3.0, abs=0.03)
