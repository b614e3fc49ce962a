"""Screenshots: image baselines of the 2D views (with a tolerance), headless export of the whole window.

Baselines live in ``Testing/CarmRegModule/baselines``; regenerate them after an intended visual change with
``CARMREG_UPDATE_BASELINES=1 pytest Testing/CarmRegModule/test_screenshots.py`` and look at them.
Views are rendered standalone at a fixed size so the window layout and fonts of the machine matter little;
the comparison allows small differences (text antialiasing) but not a moved marker or a wrong image.
"""

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytestmark = pytest.mark.gui
BASELINES = Path(__file__).resolve().parent / "baselines"
VIEW_SIZE = (520, 440)


def _grab(widget) -> np.ndarray:
    from carmreg.qt_common import process_events

    widget.resize(*VIEW_SIZE)
    widget.show()
    process_events(30)
    widget.fit()
    process_events(30)
    image = widget.grab().toImage()
    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"carmreg_grab_{os.getpid()}.png"
    image.save(str(path))
    rgb = np.asarray(Image.open(path).convert("RGB"))
    path.unlink()
    return rgb


def _compare(name: str, rgb: np.ndarray) -> None:
    """Mean absolute difference < 4/255 and < 1.5 % of pixels off by more than 60 levels."""
    BASELINES.mkdir(exist_ok=True)
    path = BASELINES / f"{name}.png"
    if os.environ.get("CARMREG_UPDATE_BASELINES") or not path.exists():
        Image.fromarray(rgb).save(path)
        if not os.environ.get("CARMREG_UPDATE_BASELINES"):
            pytest.skip(f"baseline {path.name} created; commit it")
    base = np.asarray(Image.open(path).convert("RGB"))
    assert base.shape == rgb.shape, f"{name}: size {rgb.shape} differs from the baseline {base.shape}"
    diff = np.abs(base.astype(int) - rgb.astype(int)).max(axis=2)
    mean, off = diff.mean(), (diff > 60).mean()
    if mean >= 4.0 or off >= 0.015:
        Image.fromarray(rgb).save(BASELINES / f"{name}.actual.png")
    assert mean < 4.0 and off < 0.015, f"{name}: mean diff {mean:.2f}, {100 * off:.2f} % of pixels differ"


def _store(qapp, dim):
    from qtpy import QtGui

    from carmreg.point_store import PointStore

    return PointStore("CT" if dim == 3 else "X-ray", dim, QtGui.QUndoStack())


def test_axial_slice_view_matches_its_baseline(qapp):
    from gui_case import make_volume

    from carmreg.views.slice_view import SliceView

    volume, centres = make_volume()
    store = _store(qapp, 3)
    store.add("T12", centres[1])
    store.add("L1", centres[1] + [25.0, -10.0, 0.0])
    view = SliceView("axial", store)
    view.set_volume(volume)
    view.go_to(centres[1])
    store.select(store.find("T12").id)
    rgb = _grab(view)
    _compare("axial_view", rgb)


def test_xray_view_matches_its_baseline(qapp, synthetic_case):
    from carmreg.logic.io.xray import load_xray
    from carmreg.views.xray_view import XrayView

    xray = load_xray(synthetic_case.xray_path)
    store = _store(qapp, 2)
    for label, uv in zip(synthetic_case.labels[1:4], synthetic_case.uv_px[1:4], strict=True):
        store.add(label, uv)
    view = XrayView(store)
    view.set_pixels(xray.pixels)
    rgb = _grab(view)
    _compare("xray_view", rgb)


def test_overlay_view_matches_its_baseline(qapp, synthetic_case):
    from carmreg.logic.io.xray import load_xray
    from carmreg.views.overlay_view import OverlayView

    xray = load_xray(synthetic_case.xray_path)
    fitted = {"T12", "L1", "L2"}
    levels = [{"label": lb, "uv_px": list(uv + [1.0, -0.5]), "fitted": lb in fitted,
               "pde_mm": 0.9 if lb in fitted else None} for lb, uv in zip(synthetic_case.labels,
                                                                         synthetic_case.uv_px, strict=True)]
    clicks = dict(zip(synthetic_case.labels[1:4], synthetic_case.uv_px[1:4], strict=True))
    drr = xray.pixels.max() - xray.pixels  # stands in for the DRR line integral (bone bright)
    view = OverlayView()
    view.set_result(xray.pixels, xray.bone_dark, drr, levels, clicks, "mPDE 0.90 mm")
    assert view.level_names() == list(synthetic_case.labels)
    rgb = _grab(view)
    _compare("overlay_view", rgb)


@pytest.mark.slow
def test_export_screenshots_headless_writes_window_and_views(qapp, synthetic_case, tmp_path, monkeypatch):
    """``export_screenshots`` with the sample case replaced by the synthetic one (fast, always available)."""
    from gui_case import FAST_PARAMETERS

    import carmreg.logic.resources
    from carmreg import app

    paths = {"ct": synthetic_case.ct_path, "xray": synthetic_case.xray_path,
             "ct_landmarks": synthetic_case.ct_landmarks_path, "xray_landmarks": synthetic_case.xray_landmarks_path,
             "ground_truth": tmp_path / "none.json"}
    monkeypatch.setattr(carmreg.logic.resources, "sample_case", lambda: paths)
    out = app.export_screenshots(tmp_path / "shots", views=("window", "window_ct", "xray", "overlay"),
                                 size=(1400, 900), parameters=FAST_PARAMETERS)
    assert [p.name for p in out] == ["carmreg_window.png", "carmreg_window_ct.png", "carmreg_xray.png",
                                     "carmreg_overlay.png"]
    window = np.asarray(Image.open(out[0]).convert("RGB"))
    assert window.shape[:2] == (900, 1400)
    overlay = np.asarray(Image.open(out[3]).convert("RGB"))
    # the overlay is not blank: the amber DRR and green fitted markers are in it
    assert overlay.std() > 20
    assert ((overlay[..., 1] > 150) & (overlay[..., 0] < 120) & (overlay[..., 2] < 140)).sum() > 30
    with pytest.raises(Exception, match="unknown screenshot view"):
        app.export_screenshots(tmp_path / "x", views=("nonsense",))


def test_screenshots_of_a_png_register_with_the_geometry_given_and_say_so_without(qapp, synthetic_case, tmp_path):
    """A PNG X-ray has no geometry: without it the views show no result and a note says why (the command line
    prints it as a warning); with ``geometry`` (``--sdd-mm``, ``--pixel-spacing-mm``) they are registered."""
    from gui_case import FAST_PARAMETERS

    from carmreg import app

    inputs = {"ct": synthetic_case.ct_path, "xray": synthetic_case.png_path,
              "ct_landmarks": synthetic_case.ct_landmarks_path, "xray_landmarks": synthetic_case.xray_landmarks_path}
    notes: list = []
    app.export_screenshots(tmp_path / "bare", views=("overlay",), parameters=FAST_PARAMETERS, inputs=inputs,
                           notes=notes)
    assert len(notes) == 1 and notes[0].startswith("not registered, the views show no result: Not ready: the "
                                                   "X-ray geometry is incomplete")
    notes.clear()
    geometry = {"sdd_mm": synthetic_case.sdd_mm, "pixel_spacing_mm": (synthetic_case.pixel_spacing_mm,) * 2}
    (path,) = app.export_screenshots(tmp_path / "given", views=("overlay",), parameters=FAST_PARAMETERS,
                                     inputs={**inputs, "geometry": geometry}, notes=notes)
    overlay = np.asarray(Image.open(path).convert("RGB"))
    assert notes == []
    assert ((overlay[..., 1] > 150) & (overlay[..., 0] < 120) & (overlay[..., 2] < 140)).sum() > 30  # fitted
