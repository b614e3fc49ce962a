"""An X-ray, its detector and its clicks turned (``image.turn``): pixels, detector and clicks move together, and
turning back restores all. (That the turned detector projects where the turned image shows a point, with the camera
turned the same way: ``Testing/Logic/registration/test_click_orientation.py``.)"""

import numpy as np
import pytest

from carmreg.logic.errors import CarmRegError
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.image.turn import (
    ORIENTATIONS,
    TURNS,
    UNDONE_BY,
    composed,
    orient_uv,
    stored_image,
    stored_uv,
    turned_clicks,
    turned_size,
    turned_xray,
)
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray_image import XrayImage


def _xray() -> XrayImage:
    """A 7 x 5 detector (columns x rows), non-square pixels, off-centre principal point, a pincushion."""
    intr = CarmIntrinsics(1000.0, (0.3, 0.4), (7, 5), (2.25, 1.5), {"sdd_mm": "manual"}, 1.5)
    pixels = np.arange(35, dtype=np.float32).reshape(5, 7)
    return XrayImage(pixels, intr, 600.0, True, "x.png", {"sdd_mm": "manual"})


@pytest.mark.parametrize("name", TURNS)
def test_a_turned_xray_shows_each_pixel_and_click_where_the_turn_puts_it(name):
    """Pixel (u, v) of the stored image holds the value the turned image holds at ``orient_uv((u, v))``, and a click
    on it turns to that very pixel, its name kept."""
    xray = _xray()
    turned = turned_xray(xray, name)
    cols, rows = turned.size_px
    assert turned.pixels.shape == (rows, cols) and turned.intrinsics.size_px == (cols, rows)
    v, u = np.mgrid[:5, :7]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    moved = orient_uv(uv, name, xray.size_px).round().astype(int)
    np.testing.assert_array_equal(turned.pixels[moved[:, 1], moved[:, 0]], xray.pixels.ravel())
    clicks = turned_clicks(Landmarks2D(["T11", None], uv[[3, 20]], pixel_spacing_mm=(0.3, 0.4)), name, xray.size_px)
    assert clicks.labels == ["T11", None] and clicks.pixel_spacing_mm == turned.intrinsics.pixel_spacing_mm
    np.testing.assert_array_equal(clicks.uv_px, moved[[3, 20]])
    assert name.replace("-", " ") in turned.sources["orientation"] and "orientation" not in xray.sources


@pytest.mark.parametrize("name", TURNS)
def test_turning_back_restores_the_xray(name):
    xray = _xray()
    back = turned_xray(turned_xray(xray, name), UNDONE_BY[name])
    np.testing.assert_array_equal(back.pixels, xray.pixels)
    assert back.intrinsics == xray.intrinsics
    np.testing.assert_array_equal(ORIENTATIONS[UNDONE_BY[name]](ORIENTATIONS[name](xray.pixels)), xray.pixels)


@pytest.mark.parametrize("name", ORIENTATIONS)
def test_points_and_images_on_the_turned_grid_go_back_to_the_stored_one(name):
    """``stored_uv`` undoes ``orient_uv`` (clicks exported, saved in a session, outputs on Slicer's X-ray volume);
    ``stored_image`` puts an image drawn on the turned X-ray (a DRR, an RGB overlay) back on the stored grid, each
    pixel where ``stored_uv`` puts it."""
    xray = _xray()
    turned = turned_xray(xray, name)
    assert turned_size(xray.size_px, name) == turned.size_px
    v, u = np.mgrid[:5, :7]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float) + [0.25, -0.5]
    np.testing.assert_allclose(stored_uv(orient_uv(uv, name, xray.size_px), name, xray.size_px), uv, atol=1e-12)
    np.testing.assert_array_equal(stored_image(turned.pixels, name), xray.pixels)
    rgb = np.stack([turned.pixels, 2 * turned.pixels, 3 * turned.pixels], axis=-1)
    np.testing.assert_array_equal(stored_image(rgb, name)[..., 2], 3 * xray.pixels)
    tu, tv = 4, 1  # a pixel of the turned grid, drawn back where stored_uv says
    (su, sv), = stored_uv(np.array([[tu, tv]], float), name, xray.size_px).round().astype(int)
    assert stored_image(turned.pixels, name)[sv, su] == turned.pixels[tv, tu]


def test_as_stored_is_the_xray_itself_an_incomplete_geometry_stays_so_and_an_unknown_turn_is_refused():
    xray = _xray()
    assert turned_xray(xray, "as-stored") is xray
    no_geometry = XrayImage(xray.pixels, None)
    turned = turned_xray(no_geometry, "turned-90")
    assert turned.intrinsics is None and turned.pixels.shape == (7, 5)
    with pytest.raises(CarmRegError, match="not one of: mirrored-left-right"):
        turned_xray(xray, "sideways")


@pytest.mark.parametrize("name", TURNS)
def test_a_refused_display_names_the_turn_that_registers_it(name):
    """The refusal (``outcome.refused_display``) says how to register the X-ray after all: ``--orient-xray`` with
    the orientation it matches the CT in, a name the command line takes."""
    from carmreg.cli import build_parser
    from carmreg.logic.image.appearance import Appearance
    from carmreg.logic.registration.outcome import refused_display

    a = Appearance("bone-dark", "log-display", "image", True, 0.4, 0.22, {}, "bone-dark", "PNG", "bone-dark",
                   orientation=name, orientation_scores={"as-stored": 0.2, name: 0.6})
    message = refused_display(a)
    assert f"--orient-xray {name}" in message and "GC 0.60 against 0.20" in message
    assert f'X-ray orientation "shown {name.replace("-", " ")}"' in message  # the window's and Slicer's choice
    args = build_parser().parse_args(["register", "--ct", "c", "--ct-landmarks", "l", "--xray", "x", "--no-clicks",
                                      "--out", "o", "--orient-xray", name])
    assert args.orient_xray == name


def test_turns_compose_as_one_after_the_other_into_one_of_the_eight():
    """``composed(first, then)``: the window's X-ray orientation that shows a display refused in ``then`` while shown
    ``first`` as the CT matches it. The eight orientations are closed under it (the turns of a square and their
    mirrors), and each has exactly one that undoes it (``UNDONE_BY``)."""
    image = np.arange(35).reshape(5, 7)
    for first in ORIENTATIONS:
        for then in ORIENTATIONS:
            want = ORIENTATIONS[then](ORIENTATIONS[first](image))
            np.testing.assert_array_equal(ORIENTATIONS[composed(first, then)](image), want)
        assert [then for then in ORIENTATIONS if composed(first, then) == "as-stored"] == [UNDONE_BY[first]]
    assert composed("as-stored", "mirrored-left-right") == "mirrored-left-right"
    assert composed("mirrored-left-right", "mirrored-left-right") == "as-stored"
    assert composed("turned-90", "turned-90") == "turned-180"
    assert composed("mirrored-left-right", "turned-90") == "turned-270-and-mirrored"  # the main diagonal's transpose
    np.testing.assert_array_equal(ORIENTATIONS["turned-270-and-mirrored"](image), image.T)
    np.testing.assert_array_equal(ORIENTATIONS["turned-90-and-mirrored"](image), image[::-1, ::-1].T)


@pytest.mark.parametrize("turned, matches, advised", [
    ("mirrored-left-right", "mirrored-left-right", "without --orient-xray"),  # the user's turn was not needed
    ("turned-90", "turned-90", "--orient-xray turned-180"),  # a quarter turn short: the file's half turn advised
    ("mirrored-left-right", "turned-90", "--orient-xray turned-270-and-mirrored"),  # a transpose: turned back at once
])
def test_a_display_refused_after_the_users_turn_advises_the_files_turn(turned, matches, advised):
    """The orientation a refusal finds is the registered (turned) image's; the turn it advises is the file's
    (``composed``), and the appearance's words say the file was turned."""
    from carmreg.logic.image.appearance import Appearance
    from carmreg.logic.registration.outcome import refused_display

    a = Appearance("bone-dark", "log-display", "image", True, 0.4, 0.22, {}, "bone-dark", "PNG", "bone-dark",
                   orientation=matches, orientation_scores={"as-stored": 0.2, matches: 0.6})
    message = refused_display(a, turned)
    assert f"GC 0.60 against 0.20 shown {turned.replace('-', ' ')} as asked" in message
    assert "export the image as acquired" in message
    assert advised in message
    assert a.summary(turned).endswith(f"matches the CT {matches.replace('-', ' ')} of that (the file shown "
                                      f"{turned.replace('-', ' ')} as asked) (on the DRR database)")
    stored = Appearance("bone-dark", "log-display", "image", True, 0.4, 0.22, {}, "bone-dark", "PNG", "bone-dark")
    assert "matches the CT as turned (the file shown" in stored.summary(turned)
    assert stored.summary().endswith("matches the CT as stored (on the DRR database)")
