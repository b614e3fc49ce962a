"""Place, move, name, delete and undo landmarks on the CT slice views and the X-ray view with simulated mouse
and keyboard input, and check the positions in LPS mm / detector px."""

import numpy as np
import pytest
from gui_helpers import LEFT, RIGHT, click, drag, key, ready, scene_tolerance, wheel
from qtpy import QtCore

pytestmark = pytest.mark.gui


@pytest.fixture()
def ct_window(window):
    from gui_case import make_volume

    volume, centres = make_volume()
    window.set_ct_volume(volume)
    window.set_step(1)
    for view in window.slice_views:
        ready(view)
    return window, volume, centres


def test_click_places_the_proposed_level_at_the_clicked_lps_position(ct_window):
    win, volume, centres = ct_window
    axial = win.axial
    target = centres[1]
    axial.go_to(target)
    assert axial.depth_mm == pytest.approx(target[2], abs=axial.geometry_.step_mm)
    win.ct_store.set_pending_level("T11")
    click(axial, (target[0], target[1]))
    (point,) = win.ct_store.points()
    assert point.label == "T11"
    tol = scene_tolerance(axial)
    assert abs(point.position[0] - target[0]) < tol and abs(point.position[1] - target[1]) < tol
    assert point.position[2] == pytest.approx(axial.depth_mm)
    assert win.ct_store.pending_level == "T12"  # the picker proposes the next level
    assert win.ct_panel.level_combo.currentText() == "T12"
    # the next click on the coronal view names T12, at that view's depth (anterior-posterior)
    win.coronal.go_to(centres[2])
    click(win.coronal, (centres[2][0], -centres[2][2]))
    t12 = win.ct_store.find("T12")
    assert t12.position[2] == pytest.approx(centres[2][2], abs=scene_tolerance(win.coronal))
    assert t12.position[1] == pytest.approx(centres[2][1], abs=win.coronal.geometry_.step_mm)
    assert win.ct_store.labels() == ["T11", "T12"]
    assert win.undo_stack.count() == 2


def test_drag_moves_a_point_in_one_undo_step_and_undo_redo_restore_it(ct_window):
    win, _, centres = ct_window
    axial = win.axial
    p0 = centres[0]
    axial.go_to(p0)
    click(axial, (p0[0], p0[1]))
    point = win.ct_store.points()[0]
    start = point.position.copy()
    drag(axial, (start[0], start[1]), (start[0] + 12.0, start[1] - 8.0))
    moved = win.ct_store.get(point.id).position
    tol = scene_tolerance(axial)
    assert moved[0] - start[0] == pytest.approx(12.0, abs=tol)
    assert moved[1] - start[1] == pytest.approx(-8.0, abs=tol)
    assert win.undo_stack.count() == 2  # place + one move, however many mouse-move events
    assert "Move" in win.undo_stack.undoText()
    win.act_undo.trigger()
    np.testing.assert_allclose(win.ct_store.get(point.id).position, start)
    win.act_redo.trigger()
    np.testing.assert_allclose(win.ct_store.get(point.id).position, moved)


def test_delete_key_removes_the_selected_point_and_undo_brings_it_back(ct_window):
    win, _, centres = ct_window
    win.axial.go_to(centres[0])
    click(win.axial, centres[0][:2])
    assert len(win.ct_store) == 1 and win.ct_store.selected is not None
    key(win.axial, QtCore.Qt.Key.Key_Delete)
    assert len(win.ct_store) == 0
    win.undo_stack.undo()
    assert win.ct_store.labels() == ["T12"]


def test_clicking_an_already_placed_level_moves_it_instead_of_duplicating(ct_window):
    win, _, centres = ct_window
    win.axial.go_to(centres[0])
    click(win.axial, centres[0][:2])
    win.ct_store.set_pending_level("T12")
    click(win.axial, (centres[0][0] + 20, centres[0][1]))
    assert win.ct_store.labels() == ["T12"]
    assert win.ct_store.find("T12").position[0] == pytest.approx(centres[0][0] + 20, abs=scene_tolerance(win.axial))


def test_rename_through_the_table_and_refusal_of_a_duplicate_name(ct_window):
    win, _, centres = ct_window
    for c, name in zip(centres[:2], ("T12", "L1"), strict=True):
        win.axial.go_to(c)
        win.ct_store.set_pending_level(name)
        click(win.axial, c[:2])
    combo = win.ct_panel.table.cellWidget(0, 0)
    assert combo.currentText() == "T12"
    combo.setCurrentText("T11")
    assert win.ct_store.labels() == ["T11", "L1"]
    combo = win.ct_panel.table.cellWidget(0, 0)
    combo.setCurrentText("L1")  # already used by the other point
    assert win.ct_store.labels() == ["T11", "L1"]
    assert any("already placed" in m[1] for m in win.dialogs.messages)
    win.undo_stack.undo()
    assert win.ct_store.labels() == ["T12", "L1"]


def test_points_off_the_current_slice_are_dimmed_and_cannot_be_grabbed(ct_window):
    win, _, centres = ct_window
    axial = win.axial
    axial.go_to(centres[0])
    click(axial, centres[0][:2])
    assert list(axial.markers().values())[0].alpha == 1.0
    axial.set_depth(axial.depth_mm + 6.0)  # 6 mm away: still drawn, faded
    assert list(axial.markers().values())[0].alpha < 0.5
    assert axial.hit_point(axial.mapFromScene(QtCore.QPointF(*centres[0][:2]))) is None
    axial.set_depth(axial.depth_mm + 30.0)
    assert axial.markers() == {}


def test_wheel_scrolls_slices_by_the_slice_step_and_ctrl_wheel_zooms(ct_window):
    win, _, _ = ct_window
    axial = win.axial
    depth, zoom = axial.depth_mm, axial.zoom_level()
    wheel(axial, (0, 0), 3)
    assert axial.depth_mm == pytest.approx(depth + 3 * axial.geometry_.step_mm)
    wheel(axial, (0, 0), 2, QtCore.Qt.KeyboardModifier.ControlModifier)
    assert axial.zoom_level() == pytest.approx(zoom * 1.15 ** 2, rel=1e-3)
    assert axial.depth_mm == pytest.approx(depth + 3 * axial.geometry_.step_mm)


def test_right_drag_changes_window_and_level(ct_window):
    win, _, _ = ct_window
    axial = win.axial
    win.set_ct_window("Soft tissue")
    assert (axial.window, axial.level) == (400.0, 40.0)
    drag(axial, (0, 0), (20, 0), button=RIGHT)
    assert axial.window > 400.0 and axial.level == pytest.approx(40.0, abs=30)
    assert len(win.ct_store) == 0  # a right drag never places points


def test_slice_view_reads_hounsfield_units_of_the_volume(ct_window):
    win, volume, centres = ct_window
    axial = win.axial
    axial.go_to(centres[2])
    hu = axial.value_at(QtCore.QPointF(centres[2][0], centres[2][1]))
    assert hu == pytest.approx(450.0, abs=1.0)  # vertebral body
    assert axial.value_at(QtCore.QPointF(-88.0, -68.0)) == pytest.approx(-1000.0, abs=1.0)  # air corner


def test_xray_place_move_rename_delete_and_undo(xray_window):
    win = xray_window
    view = win.xray_view
    win.xray_store.set_pending_level("L1")
    click(view, (120.0, 80.0))
    click(view, (130.0, 150.0))
    assert win.xray_store.labels() == ["L1", "L2"]
    tol = scene_tolerance(view)
    l1 = win.xray_store.find("L1")
    np.testing.assert_allclose(l1.position, [120.0, 80.0], atol=tol)
    drag(view, (120.0, 80.0), (125.0, 90.0))
    np.testing.assert_allclose(win.xray_store.find("L1").position, [125.0, 90.0], atol=tol)
    win.xray_store.rename(l1.id, "T12")
    assert win.xray_store.labels() == ["T12", "L2"]
    win.xray_store.select(l1.id)
    key(view, QtCore.Qt.Key.Key_Delete)
    assert win.xray_store.labels() == ["L2"]
    for _ in range(3):
        win.undo_stack.undo()
    assert win.xray_store.labels() == ["L1", "L2"]
    np.testing.assert_allclose(win.xray_store.find("L1").position, [120.0, 80.0], atol=tol)


def test_xray_click_outside_the_image_places_nothing_and_shift_click_pans(xray_window):
    win = xray_window
    view = win.xray_view
    click(view, (-30.0, 50.0))
    assert len(win.xray_store) == 0
    before = view.mapToScene(view.viewport().rect().center())
    drag(view, (200.0, 150.0), (150.0, 150.0), button=QtCore.Qt.MouseButton.MiddleButton)
    after = view.mapToScene(view.viewport().rect().center())
    assert after.x() - before.x() == pytest.approx(50.0, abs=3 * scene_tolerance(view))
    assert len(win.xray_store) == 0


def test_place_mode_off_left_click_does_not_place(xray_window):
    win = xray_window
    win.set_place_mode(False)
    click(win.xray_view, (100.0, 100.0), LEFT)
    assert len(win.xray_store) == 0
    win.act_place.trigger()  # the P action turns it back on
    click(win.xray_view, (100.0, 100.0), LEFT)
    assert len(win.xray_store) == 1
