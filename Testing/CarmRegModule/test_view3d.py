"""The 3D view: bone surface, named points and the C-arm frustum; interactive under a display (Xvfb),
rendered offscreen through VTK without one, and a plain message when there is no OpenGL at all."""

import numpy as np
import pytest

pytestmark = [pytest.mark.gui, pytest.mark.vtk_render]


def _carm(volume):
    from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose

    geometry = CarmGeometry(CarmIntrinsics(1000.0, (0.9, 0.9), (256, 256)), tuple(volume.center_lps_mm()), 600.0)
    pose = CarmPose(20.0, 6.0, -8.0, 1.0, 0.0, 0.0)
    return geometry.source_lps_mm(pose), geometry.detector_corners_lps_mm(pose)


def _orange_pixels(rgb) -> int:
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return int(((r > 200) & (g > 120) & (g < 200) & (b < 110)).sum())


def _check_scene(view, volume, centres):
    view.set_volume(volume)
    assert view.surface() is not None and view.surface().n_points > 1000
    bounds = np.asarray(view.surface().bounds).reshape(3, 2)
    corners = volume.corners_lps_mm()
    assert np.all(bounds[:, 0] >= corners.min(0) - 1) and np.all(bounds[:, 1] <= corners.max(0) + 1)  # LPS mm
    view.set_points([("T12", centres[1]), ("L1", centres[2])], selected="T12")
    plain = view.render_image()
    assert plain is not None and plain.std() > 5
    source, detector = _carm(volume)
    view.set_carm(source, detector)
    view.show_view("Lateral")
    with_carm = view.render_image()
    assert _orange_pixels(with_carm) > _orange_pixels(plain) + 50  # the frustum edges are drawn


@pytest.mark.slow
def test_offscreen_rendering_without_a_display(qapp):
    from gui_case import make_volume

    from carmreg.views.view3d import View3D, offscreen_vtk_available

    if not offscreen_vtk_available():
        pytest.skip("VTK cannot render offscreen here (no EGL/OSMesa)")
    volume, centres = make_volume()
    view = View3D(mode="offscreen")
    view.resize(500, 400)
    try:
        _check_scene(view, volume, centres)
        pixmap = view.image_label.pixmap()
        assert pixmap is not None and not pixmap.isNull()
        before = view.render_image()
        view.rotate(40.0, 10.0)
        assert np.abs(view.render_image().astype(int) - before.astype(int)).mean() > 1.0  # drag rotates
    finally:
        view.close_plotter()


@pytest.mark.slow
def test_interactive_view_under_a_display(qapp):
    from gui_case import make_volume

    from carmreg.qt_common import is_offscreen, process_events
    from carmreg.views.view3d import View3D

    if is_offscreen():
        pytest.skip("needs a display (run under xvfb-run)")
    volume, centres = make_volume()
    view = View3D()
    assert view.mode == "interactive"
    view.resize(500, 400)
    view.show()
    process_events(100)
    try:
        _check_scene(view, volume, centres)
        view.prepare_grab()
        grabbed = view.grab()
        view.finish_grab()
        assert not grabbed.isNull() and grabbed.width() >= 400
    finally:
        view.close_plotter()


def test_without_opengl_the_view_says_so_and_the_window_still_works(window, monkeypatch):
    from gui_case import make_volume

    from carmreg.views.view3d import View3D

    monkeypatch.setenv("CARMREG_NO_VTK", "1")
    view = View3D()
    assert view.mode == "message"
    assert "3D view unavailable" in view.image_label.text()
    volume, _ = make_volume()
    view.set_volume(volume)
    assert view.render_image() is None
    window.set_ct_volume(volume)  # the window fixture has no 3D at all: the slices still work
    assert window.axial.has_image()
