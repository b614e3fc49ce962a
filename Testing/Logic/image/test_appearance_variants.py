"""The appearance benchmark's own X-ray chain (Testing/Benchmarks/appearance.py) on a small synthetic scene:
polarity really inverted, JPEG really 8-bit, the mirrored display really a left-right flip (image and truth),
the intensifier distortion inverted exactly, and every stored file read back by CarmReg's own X-ray reader.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Benchmarks"))

import appearance as app  # noqa: E402

from carmreg.logic.geometry.camera import CarmGeometry, CarmPose, project  # noqa: E402
from carmreg.logic.image.turn import ORIENTATIONS, UNDONE_BY  # noqa: E402
from carmreg.logic.io.xray import load_xray  # noqa: E402

BONE = (slice(30, 50), slice(44, 52))     # rows, columns of one bone block
SOFT = (slice(30, 50), slice(60, 68))     # soft tissue beside it


def scene(kind: str = "fp") -> app.Scene:
    """A 96 x 80 px scene (columns != rows, so a flip is not a transpose): an elliptical body and a column of
    three bone blocks (line integrals), its field, and the truth of three points under a real geometry."""
    det = app.Detector(kind, 1000.0, (96, 80), 1.2, field_diameter_mm=90.0)
    rows, cols = 80, 96
    vv, uu = np.mgrid[0:rows, 0:cols].astype(float)
    r2 = ((uu - 47.5) / 46.0) ** 2 + ((vv - 39.5) / 60.0) ** 2
    l_water = (4.0 * np.sqrt(np.clip(1.0 - r2, 0.0, None))).astype(np.float32)
    l_bone = np.zeros((rows, cols), np.float32)
    for top in (8, 30, 52):
        l_bone[top:top + 20, 44:52] = 0.8
    field_img, desc = app.collimation(np.random.default_rng(0), det)
    geometry = CarmGeometry(det.intrinsics(), (0.0, 0.0, 0.0), det.sod_mm)
    pose = CarmPose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    points = {"T11": np.array([-10.0, 0.0, 20.0]), "T12": np.array([-8.0, 0.0, 0.0]), "L1": np.array([-6.0, 0, -20])}
    uv = {lb: project(geometry.projection_matrix(pose), p[None])[0] for lb, p in points.items()}
    return app.Scene("synthetic", det, geometry, pose, l_water, l_bone, field_img, uv, dict.fromkeys(uv, True),
                     list(uv), np.array(list(uv.values())), {"field": desc})


def look(**changes) -> app.Look:
    return dataclasses.replace(app.Look(photons=3000.0, spr=0.3, heel=0.0), **changes)


def rendered(sc: app.Scene, lk: app.Look, seed: int = 1) -> np.ndarray:
    return app.render(sc, lk, np.random.default_rng(seed))


@pytest.mark.parametrize("storage", ["log", "linear", "display"])
def test_bone_bright_is_the_inverted_bone_dark_image(storage):
    sc = scene("fp")
    dark = rendered(sc, look(storage=storage, bone_bright=False)).astype(float)
    bright = rendered(sc, look(storage=storage, bone_bright=True)).astype(float)
    dark_step = dark[SOFT].mean() - dark[BONE].mean()
    assert dark_step > 0.1 * dark[SOFT].mean()  # bone darker than the soft tissue beside it
    assert bright[BONE].mean() - bright[SOFT].mean() > 0.5 * dark_step  # and brighter once inverted
    inside = (sc.field > 0.5) & (dark < dark.max()) & (bright < bright.max())
    assert np.corrcoef(dark[inside], bright[inside])[0, 1] < -0.99


def test_bone_contrast_falls_with_tube_voltage_and_a_large_patient():
    sc = scene("fp")
    contrast = {}
    for name, lk in (("60 kV", look(kv=60.0)), ("120 kV", look(kv=120.0)),
                     ("large", look(kv=120.0, extra_water_mm=150.0, spr=4.0))):
        img = rendered(sc, dataclasses.replace(lk, storage="linear")).astype(float)
        contrast[name] = 1.0 - img[BONE].mean() / img[SOFT].mean()
    assert contrast["60 kV"] > 1.3 * contrast["120 kV"] > 1.3 * contrast["large"] > 0


def test_jpeg_is_8_bit_and_png_tiff_16_bit(tmp_path):
    sc = scene("ii")
    jpeg = app.write_xray(tmp_path / "x", rendered(sc, look(storage="display", file="jpeg8")), sc.detector,
                          look(storage="display", file="jpeg8", jpeg_quality=80))
    with Image.open(jpeg) as im:
        assert (im.format, im.mode) == ("JPEG", "L")
        assert np.asarray(im).dtype == np.uint8
    for kind in ("png16", "tiff16"):
        lk = look(file=kind)
        path = app.write_xray(tmp_path / kind, rendered(sc, lk), sc.detector, lk)
        with Image.open(path) as im:
            assert np.asarray(im).dtype in (np.uint16, np.dtype(">u2"), np.int32) and np.asarray(im).max() > 255


def test_mirrored_display_is_a_left_right_flip_of_image_and_truth():
    sc = scene("ii")
    plain = rendered(sc, look())
    flipped = rendered(sc, look(mirrored=True))
    text = (plain == plain.max()) | (flipped == flipped.max())  # burnt-in text is not flipped
    keep = ~(text | text[:, ::-1])
    assert keep.mean() > 0.9
    np.testing.assert_array_equal(flipped[keep], plain[:, ::-1][keep])
    truth, mirrored = app.truth_dict(sc, False), app.truth_dict(sc, True)
    cols = sc.detector.size_px[0]
    for lb in sc.uv_true_px:
        u, v = truth["levels"][lb]["uv_true_px"]
        assert mirrored["levels"][lb]["uv_true_px"] == pytest.approx([cols - 1 - u, v])
        point = {"T11": [-10.0, 0.0, 20.0], "T12": [-8.0, 0.0, 0.0], "L1": [-6.0, 0.0, -20.0]}[lb]
        uv_flipped = project(np.array(mirrored["projection_matrix"]), np.array([point]))[0]
        assert uv_flipped == pytest.approx([cols - 1 - u, v])


def test_pincushion_inverse_is_exact_and_pushes_the_edge_outwards():
    det = app.DETECTORS["ii"]
    warp = app.draw_pincushion(np.random.default_rng(3), det)
    uv = np.random.default_rng(4).uniform(0, det.size_px[0] - 1, (200, 2))
    np.testing.assert_allclose(warp.undistort(warp.distort(uv)), uv, atol=1e-6)
    edge = np.array([[warp.center_px[0] + 100.0 / det.pixel_mm, warp.center_px[1]]])
    shift_mm = (warp.distort(edge)[0, 0] - edge[0, 0]) * det.pixel_mm
    assert 0.5 < shift_mm < 7.0


@pytest.mark.parametrize("kind, bright", [("png16", False), ("tiff16", True), ("dcm-sign", False),
                                          ("dcm-nosign", True), ("dcm-mono1", True), ("jpeg8", False)])
def test_stored_files_load_through_the_product_reader(tmp_path, kind, bright):
    sc = scene("fp")
    storage = {"dcm-mono1": "linear", "jpeg8": "display"}.get(kind, "log")
    lk = look(file=kind, bone_bright=bright, storage=storage, modality="DX" if kind == "dcm-mono1" else "RF")
    pixels = rendered(sc, lk)
    path = app.write_xray(tmp_path / "xray", pixels, sc.detector, lk)
    x = load_xray(path, **({} if kind.startswith("dcm") else {"sdd_mm": 1000.0, "pixel_spacing_mm": 1.2}))
    assert x.size_px == (96, 80)
    assert x.intrinsics.sdd_mm == pytest.approx(1000.0)
    assert x.intrinsics.pixel_spacing_mm == pytest.approx((1.2, 1.2))
    if kind == "dcm-mono1":  # MONOCHROME1 storing linear intensity (LIN, +1): kept as stored, bone dark
        np.testing.assert_array_equal(x.pixels, pixels.astype(np.float32))
        assert x.bone_dark is True and "note_linear_intensity" in x.meta
    elif kind == "jpeg8":
        assert np.abs(x.pixels - pixels.astype(np.float32)).mean() < 6.0  # lossy
    else:
        np.testing.assert_array_equal(x.pixels, pixels.astype(np.float32))
    if kind == "dcm-sign":
        assert x.bone_dark is True and "1041" in x.sources["bone_dark"]
    shown = x.pixels
    assert (shown[BONE].mean() > shown[SOFT].mean()) == (bright and kind != "dcm-mono1")  # mono1: kept, dark


@pytest.mark.parametrize("display_turn", ["turned-180", "flipped-up-down", "turned-90"])
def test_a_turned_display_turns_image_truth_and_clicks_by_one_pixel_map(display_turn):
    """The benchmark's turned displays: the stored pixels, the true P and the clicks all go through
    ``display_map``'s F, so the turned truth projects each level where the turned image shows the acquired pixel."""
    sc = scene("ii")
    plain = rendered(sc, look())
    turned = rendered(sc, look(display_turn=display_turn))
    F, (cols, rows) = app.display_map(sc.detector.size_px, False, display_turn)
    assert turned.shape == (rows, cols)
    text = (plain == plain.max())  # burnt-in text is written after the turn: compare pixels away from it
    acquired_v, acquired_u = np.nonzero(~text)
    shown_u, shown_v = np.rint(app.displayed_uv(np.stack([acquired_u, acquired_v], 1), F)).astype(int).T
    keep = turned[shown_v, shown_u] != turned.max()
    assert keep.mean() > 0.9
    np.testing.assert_array_equal(turned[shown_v[keep], shown_u[keep]], plain[acquired_v[keep], acquired_u[keep]])
    truth, shown = app.truth_dict(sc, False), app.truth_dict(sc, False, display_turn)
    assert shown["intrinsics"]["size_px"] == [cols, rows] and shown["display_turn"] == display_turn
    for lb in sc.uv_true_px:
        expected = app.displayed_uv(np.array(truth["levels"][lb]["uv_true_px"]), F)
        assert shown["levels"][lb]["uv_true_px"] == pytest.approx(expected.tolist())
        point = {"T11": [-10.0, 0.0, 20.0], "T12": [-8.0, 0.0, 0.0], "L1": [-6.0, 0.0, -20.0]}[lb]
        uv_plain = project(np.array(truth["projection_matrix"]), np.array([point]))
        uv_shown = project(np.array(shown["projection_matrix"]), np.array([point]))[0]
        assert uv_shown == pytest.approx(app.displayed_uv(uv_plain, F)[0])
    np.testing.assert_allclose(shown["clicks_uv_px"], app.displayed_uv(np.array(truth["clicks_uv_px"]), F))
    # the benchmark's turn is CarmReg's turn of the same name, so ``turn.UNDONE_BY`` names the one that undoes it
    probe = np.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(app.turn_display(probe, display_turn), ORIENTATIONS[display_turn](probe))
    np.testing.assert_array_equal(ORIENTATIONS[UNDONE_BY[display_turn]](app.turn_display(probe, display_turn)), probe)
