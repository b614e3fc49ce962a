"""What the window shows and what the files show agree: the X-ray's default contrast is the exposed field's
display range (burned-out air and the collimator left out), and the ``overlay.png`` that ``carmreg register``
writes looks like the window's overlay of the same result (one composite, one label style)."""

import numpy as np
import pytest
from gui_helpers import ready

pytestmark = pytest.mark.gui


def test_the_default_xray_window_is_the_fields_1st_to_99th_percentile_without_burned_out_air(window):
    from carmreg.logic.image.field import field_mask
    from carmreg.logic.io.xray import load_xray
    from carmreg.logic.resources import sample_case

    xray = load_xray(sample_case()["xray"])
    window.set_xray_image(xray)
    view = window.xray_view
    ready(view)
    field = xray.pixels[field_mask(xray.pixels)]
    span = float(field.max() - field.min())
    unclipped = field[(field > field.min()) & (field < field.max())]  # 1.7 % of the field is air at 65535
    expected = np.percentile(unclipped, [1.0, 99.0])
    shown = (view.level - view.window / 2, view.level + view.window / 2)
    assert shown == pytest.approx(tuple(expected), abs=0.005 * span)
    assert shown[1] < field.max() - 0.03 * span  # the saturated air does not set the top of the window
    assert shown[0] > np.percentile(field, 1.0) + 0.03 * span  # nor the zero-filled metal its bottom
    assert window.xray_window_spin.value() == pytest.approx(view.window, abs=0.5)  # the spin boxes show it
    window.xray_window_spin.setValue(1000.0)
    window.invert_check.setChecked(True)
    view.auto_window()  # "Auto contrast" goes back to the default and keeps the inversion
    assert (view.level - view.window / 2, view.level + view.window / 2) == pytest.approx(shown)
    assert view.invert


def _viewport_rgb(view) -> np.ndarray:
    """The view's viewport as drawn, (rows, cols, 3) uint8."""
    from qtpy import QtGui

    image = view.viewport().grab().toImage().convertToFormat(QtGui.QImage.Format.Format_RGB888)
    width, height, stride = image.width(), image.height(), image.bytesPerLine()
    data = np.frombuffer(image.constBits(), np.uint8, count=stride * height).reshape(height, stride)
    return data[:, : width * 3].reshape(height, width, 3).copy()


def _image_on_screen(view, size_px) -> np.ndarray:
    """The part of the viewport showing the image, resampled to the image's (columns, rows) ``size_px``."""
    from PIL import Image

    rect = view.image_rect()
    top_left = view.mapFromScene(rect.topLeft())
    bottom_right = view.mapFromScene(rect.bottomRight())
    shot = _viewport_rgb(view)[max(top_left.y(), 0): bottom_right.y(), max(top_left.x(), 0): bottom_right.x()]
    assert shot.shape[0] > 0.8 * (bottom_right.y() - top_left.y()), "the whole image is on screen"
    return np.asarray(Image.fromarray(shot).resize(size_px, Image.Resampling.BILINEAR))


def _blocks(rgb: np.ndarray, n: int = 16) -> np.ndarray:
    """Mean colour of n x n blocks (rows, cols, 3) -> (n, n, 3) float."""
    rows, cols = rgb.shape[0] // n * n, rgb.shape[1] // n * n
    return rgb[:rows, :cols].reshape(n, rows // n, n, cols // n, 3).mean(axis=(1, 3))


def test_overlay_png_of_register_looks_like_the_windows_overlay(window, synthetic_case, tmp_path):
    from PIL import Image
    from test_surgeon_window import _load_case

    from carmreg.logic.report.result_files import save_result

    _load_case(window, synthetic_case)
    window.run_registration(wait=True)
    result = window.result
    assert result is not None and result.ok
    clicked = {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv.get("clicked_uv_px") is not None}
    paths = save_result(result, tmp_path / "cli", window.xray.pixels, clicked)  # what `carmreg register` does
    png = np.asarray(Image.open(paths["overlay"]).convert("RGB"))
    assert png.shape[:2] == window.xray.pixels.shape  # on the X-ray's pixel grid
    view = window.overlay_view
    window.view_tabs.setCurrentIndex(2)
    ready(view)
    screen = _image_on_screen(view, (png.shape[1], png.shape[0]))
    below_banner = slice(png.shape[0] // 4, None)  # overlay.png carries the level answer over its top rows
    file_blocks, screen_blocks = _blocks(png[below_banner]), _blocks(screen[below_banner])
    difference = np.abs(file_blocks - screen_blocks)
    assert float(difference.mean()) < 8.0, difference.mean()  # of 255: the same composite and contrast
    assert np.abs(file_blocks.mean(axis=(0, 1)) - screen_blocks.mean(axis=(0, 1))).max() < 6.0  # same tint
    amber = file_blocks[..., 0] - file_blocks[..., 2]  # the DRR in amber (red > blue), not in another colour
    assert float(amber.mean()) > 5.0 and float((screen_blocks[..., 0] - screen_blocks[..., 2]).mean()) > 5.0
