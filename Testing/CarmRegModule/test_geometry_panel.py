"""The C-arm geometry panel: values and their sources, device presets, hand edits, refusal of impossible values."""

import numpy as np
import pytest

pytestmark = pytest.mark.gui


def test_png_without_geometry_is_completed_by_a_preset_scaled_to_the_image(window, synthetic_case):
    window.load_xray(synthetic_case.png_path)
    panel = window.geometry_panel
    assert window.xray.intrinsics is None
    assert "X-ray geometry" in window.registration_panel.ready_label.text()
    assert panel.sdd.text() == "not set" and panel.sources["sdd_mm"].text().startswith("not set")
    keys = [p.key for p in panel.presets()]
    assert {"ii_9inch", "ii_12inch", "flat_panel_30cm"} <= set(keys)
    panel.preset_combo.setCurrentIndex(panel.preset_combo.findData("ii_9inch"))
    panel.preset_combo.activated.emit(panel.preset_combo.currentIndex())
    intr = window.xray.intrinsics
    assert intr.sdd_mm == 1000.0
    # 0.22 mm at a 1024-px readout, this image has 256 columns: 0.88 mm per pixel over the same field
    assert intr.pixel_spacing_mm == pytest.approx((0.88, 0.88))
    assert window.xray.sod_mm == 650.0
    assert panel.sources["sdd_mm"].text().startswith("preset: 9-inch image intensifier")
    assert panel.sdd.value() == 1000.0
    assert "1.54" in panel.magnification_label.text()  # 1000 / 650


def test_typing_a_value_overrides_the_file_and_reset_restores_it(window, synthetic_case):
    window.load_xray(synthetic_case.xray_path)
    panel = window.geometry_panel
    assert window.xray.intrinsics.sdd_mm == 1000.0
    assert "0018,1110" in panel.sources["sdd_mm"].text()  # from the DICOM tag
    panel.sdd.setValue(1045.0)
    panel.sdd.editingFinished.emit()
    assert window.xray.intrinsics.sdd_mm == 1045.0
    assert window.geometry_overrides == {"sdd_mm": 1045.0}
    assert panel.sources["sdd_mm"].text().startswith("entered by hand")
    panel.du.setValue(0.5)
    panel.dv.setValue(0.6)
    panel.du.editingFinished.emit()
    assert window.xray.intrinsics.pixel_spacing_mm == (0.5, 0.6)
    pp_source = panel.sources["principal_point_px"]
    assert pp_source.isVisibleTo(panel) and pp_source.text().startswith("DICOM private")
    panel.pp_centre.setChecked(False)
    panel.u0.setValue(100.0)
    panel.u0.editingFinished.emit()
    assert window.xray.intrinsics.principal_point_px == (100.0, 127.5)
    assert pp_source.text().startswith("entered by hand")
    panel.reset_button.click()
    assert window.xray.intrinsics.sdd_mm == 1000.0 and window.xray.intrinsics.pixel_spacing_mm == (0.9, 0.9)
    assert window.xray.intrinsics.principal_point_px == (127.5, 127.5)
    assert pp_source.text().startswith("DICOM private")
    assert window.is_dirty()


def test_impossible_geometry_is_refused_with_a_dialog_and_the_old_values_stay(window, synthetic_case):
    window.load_xray(synthetic_case.xray_path)
    panel = window.geometry_panel
    panel.sdd.setValue(50.0)
    panel.sdd.editingFinished.emit()
    title, message, details = window.dialogs.messages[-1]
    assert "source-to-detector distance" in message and details is None
    assert window.xray.intrinsics.sdd_mm == 1000.0
    assert panel.sdd.value() == 1000.0  # the form shows what is really in force


def test_sod_edit_changes_the_magnification_shown(window, synthetic_case):
    window.load_xray(synthetic_case.xray_path)
    panel = window.geometry_panel
    panel.sod.setValue(500.0)
    panel.sod.editingFinished.emit()
    assert window.xray.sod_mm == 500.0
    assert "2.00" in panel.magnification_label.text()


def test_a_calibrated_pincushion_is_entered_kept_by_a_preset_and_reset(window, synthetic_case):
    window.load_xray(synthetic_case.xray_path)
    panel = window.geometry_panel
    assert window.xray.intrinsics.distortion_mm == 0.0
    assert panel.sources["distortion_mm"].text().startswith("default (none)")
    panel.distortion.setValue(2.5)
    panel.distortion.editingFinished.emit()
    assert window.xray.intrinsics.distortion_mm == 2.5 and window.geometry_overrides == {"distortion_mm": 2.5}
    assert panel.sources["distortion_mm"].text().startswith("entered by hand")
    panel.apply_preset("ii_9inch")  # a device preset sets SDD, spacing and SOD; the unit's calibration stays
    assert window.xray.intrinsics.distortion_mm == 2.5 and window.xray.intrinsics.sdd_mm == 1000.0
    panel.reset_button.click()
    assert window.xray.intrinsics.distortion_mm == 0.0 and panel.distortion.value() == 0.0


def test_the_pincushion_is_measured_on_a_bead_grid_x_ray_and_set(window, tmp_path):
    """The button opens a bead-grid X-ray of the same detector and sets the Pincushion it measures."""
    from grid_images import PIXEL_MM, grid_image

    from carmreg.logic.geometry.camera import CarmIntrinsics
    from carmreg.logic.io.xray import XrayImage, write_png16

    grid = grid_image(3.0)
    patient = XrayImage(grid.astype(np.float32), CarmIntrinsics(1000.0, (PIXEL_MM, PIXEL_MM), grid.shape[::-1]),
                        600.0, True, "in memory")
    window.set_xray_image(patient, None, {})
    png = write_png16(tmp_path / "grid.png", grid.astype(np.uint16))
    window.dialogs.answers["open_file"] = [str(png)]
    window.geometry_panel.measure_button.click()
    title, message, _ = window.dialogs.messages[-1]
    assert title == "Pincushion measured" and message.startswith("Pincushion 3.00 mm at 100 mm from the centre")
    assert window.xray.intrinsics.distortion_mm == 3.0 and window.geometry_panel.distortion.value() == 3.0
    window.dialogs.answers["open_file"] = [str(tmp_path / "missing.png")]
    window.geometry_panel.measure_button.click()
    assert "missing.png: X-ray file not found" in window.dialogs.messages[-1][1]
    assert window.xray.intrinsics.distortion_mm == 3.0  # a failed measurement changes nothing
