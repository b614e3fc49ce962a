"""The X-ray's appearance is found from the image, not assumed: exposed field without a polarity, polarity and
storage against the DRR database (bone dark, bone bright, an 8-bit JPEG with gamma and edge enhancement read
through the real loader), orientation (a mirrored display is refused, never named with confidence)."""

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from carmreg.logic.image.appearance import decide_polarity, rank_image
from carmreg.logic.image.field import field_mask
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray import XrayImage, load_xray
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters
from carmreg.logic.simulation.options import SimulationOptions, default_geometry, sample_options
from carmreg.logic.simulation.scene import random_pose
from carmreg.logic.simulation.simulator import simulate_case


def test_rank_image_is_the_same_for_any_increasing_storage():
    rng = np.random.default_rng(0)
    linear = rng.random((40, 50)) + 0.01
    mask = np.ones(linear.shape, bool)
    mask[:5] = False
    for stored in (np.log(linear), linear ** 0.45, np.round(linear * 255)):
        same = rank_image(stored, mask)
        if np.unique(stored[mask]).size == mask.sum():  # no ties: identical ranks
            np.testing.assert_array_equal(same, rank_image(linear, mask))
        assert np.corrcoef(same[mask], rank_image(linear, mask)[mask])[0, 1] > 0.999
    assert rank_image(-linear, mask)[mask] == pytest.approx(1.0 - rank_image(linear, mask)[mask], abs=1e-6)
    assert not rank_image(linear, mask)[~mask].any()


def test_field_is_found_whichever_way_bone_is_shown():
    """A circular field with texture, black outside: the field of the image and of its inverse (still black
    outside) agree, and each leaves out the black corners."""
    rows, cols = np.mgrid[:200, :220]
    disc = (rows - 100) ** 2 + (cols - 110) ** 2 < 90 ** 2
    texture = 0.4 + 0.3 * ndimage.gaussian_filter(np.random.default_rng(1).random((200, 220)), 3) * 10
    dark = np.where(disc, texture, 0.0)
    bright = np.where(disc, 1.5 - texture, 0.0)
    a, b = field_mask(dark), field_mask(bright)
    assert (a & b).sum() / (a | b).sum() > 0.97
    assert not a[:10, :10].any() and not b[-10:, -10:].any() and a[100, 110] and b[100, 110]
    assert 0.8 < a.sum() / disc.sum() < 1.0  # eroded by ~2 % of its size, no more


def test_the_users_polarity_wins_but_a_clear_contradiction_is_not_trusted():
    scores = {"bone-dark": 0.50, "bone-bright": 0.20}
    auto = decide_polarity(scores, None, "auto", False, "header", None)
    assert (auto.polarity, auto.decided_by, auto.clear) == ("bone-dark", "image", True)
    user = decide_polarity(scores, None, "bone-bright", True, "header", None)
    assert (user.polarity, user.decided_by, user.clear) == ("bone-bright", "user", False)
    assert "looks bone-dark" in user.note
    close = decide_polarity({"bone-dark": 0.30, "bone-bright": 0.28}, None, "auto", True, "header", None)
    assert not close.clear and close.clarity_gc == pytest.approx(0.02)
    refined = decide_polarity({"bone-dark": 0.30, "bone-bright": 0.28}, {"bone-dark": 0.3, "bone-bright": 0.6},
                              "auto", True, "header", None)
    assert (refined.polarity, refined.decided_by, refined.clear) == ("bone-bright", "image (refined)", True)


def test_a_file_that_states_its_polarity_and_an_image_that_disagrees_are_a_conflict_never_trusted():
    """DICOM PixelIntensityRelationshipSign is evidence: agreeing settles a close call; disagreeing (even by a clear
    GC gap, as a mis-found field gave on a linear flat-panel image) keeps the file's word and is not trusted."""
    source = "DICOM (0028,1041) PixelIntensityRelationshipSign"
    clear_bright = {"bone-dark": 0.28, "bone-bright": 0.38}
    conflict = decide_polarity(clear_bright, None, "auto", True, source, None, header_explicit=True)
    assert (conflict.polarity, conflict.clear, conflict.trusted) == ("bone-dark", False, False)
    assert conflict.image_polarity == "bone-bright" and "image looks bone-bright" in conflict.note
    assert decide_polarity(clear_bright, None, "auto", True, "default for modality RF", None).polarity == "bone-bright"
    close_dark = {"bone-dark": 0.30, "bone-bright": 0.28}
    agreed = decide_polarity(close_dark, None, "auto", True, source, None, header_explicit=True)
    assert (agreed.polarity, agreed.clear) == ("bone-dark", True) and "the image agrees" in agreed.note
    assert not decide_polarity(close_dark, None, "auto", True, source, None).clear  # not stated: the image alone
    user = decide_polarity(clear_bright, None, "bone-bright", True, source, None, header_explicit=True)
    assert (user.polarity, user.decided_by, user.clear) == ("bone-bright", "user", True)  # the user's word rules


def test_only_a_clear_polarity_and_a_clear_lead_of_the_stored_orientation_are_trusted():
    """A mirrored display of a near-symmetric view can lead as stored by a hair: no confident answer on it."""
    from carmreg.logic.image.appearance import trusted_appearance

    assert trusted_appearance(True, "as-stored", True)
    assert not trusted_appearance(True, "as-stored", False)          # stored leads by < CLEAR_ORIENTATION_GC
    assert not trusted_appearance(True, "mirrored-left-right", True)  # another orientation matches best
    assert not trusted_appearance(False, "as-stored", True)           # the polarity is unclear or in conflict
    a = decide_polarity({"bone-dark": 0.50, "bone-bright": 0.20}, None, "auto", True, "PNG", None)
    a.set_orientation({"as-stored": 0.40, "mirrored-left-right": 0.39, "flipped-up-down": 0.2, "turned-180": 0.2})
    assert a.orientation == "as-stored" and not a.orientation_clear and not a.trusted


@pytest.fixture(scope="module")
def case(sample_ct):
    """One realistic simulated AP case (512 px, bone dark as stored) of the sample CT, T8 in the middle."""
    ct, labels, centroids = sample_ct
    rng = np.random.default_rng(4321)
    options = sample_options(rng, SimulationOptions(size_px=(512, 512), pixel_spacing_mm=0.5))
    geometry = default_geometry(ct, options)
    pose = random_pose(rng, options, centroids, "T8", geometry=geometry)
    sim = simulate_case(ct, labels, centroids, geometry, pose, options, seed=11)
    return sim, geometry


def _appearance(sample_ct, xray, tmp_path_factory):
    ct, _, centroids = sample_ct
    logic = CarmRegLogic()
    params = RegistrationParameters(cache_dir=str(tmp_path_factory.getbasetemp() / "appearance-cache"))
    state = logic.prepare(ct, centroids, xray, Landmarks2D([], np.zeros((0, 2))), params)
    for stage in ("database", "spatial"):
        logic.run_stage(state, stage)
    return state.appearance


def _inverted_in_field(pixels: np.ndarray) -> np.ndarray:
    field = field_mask(pixels)
    hi = np.percentile(pixels[field], 99.5)
    return np.where(pixels > 0, np.clip(hi - pixels, 0, None), 0.0)


@pytest.mark.slow
def test_polarity_is_found_for_bone_dark_bone_bright_and_an_8_bit_jpeg(sample_ct, case, tmp_path, tmp_path_factory):
    sim, geometry = case
    pixels = sim.pixels.astype(np.float64)
    dark = XrayImage(pixels.astype(np.float32), geometry.intrinsics, geometry.sod_mm, False, "dark")  # header wrong
    a = _appearance(sample_ct, dark, tmp_path_factory)
    assert (a.polarity, a.decided_by, a.clear, a.orientation) == ("bone-dark", "image", True, "as-stored")
    assert a.header_polarity == "bone-bright" and a.clarity_gc >= 0.05

    bright_png = tmp_path / "bright.png"
    Image.fromarray(np.round(_inverted_in_field(pixels) / pixels.max() * 65535).astype(np.uint16)).save(bright_png)
    bright = load_xray(bright_png, sdd_mm=geometry.intrinsics.sdd_mm,
                       pixel_spacing_mm=geometry.intrinsics.pixel_spacing_mm)
    assert bright.bone_dark  # what a PNG "says": nothing, so the old default
    b = _appearance(sample_ct, bright, tmp_path_factory)
    assert (b.polarity, b.clear, b.storage) == ("bone-bright", True, "log-display")

    x = pixels / pixels.max()
    gamma = x ** 0.6
    sharpened = np.clip(gamma + 0.8 * (gamma - ndimage.gaussian_filter(gamma, 3)), 0, 1)
    jpeg = tmp_path / "fluoro.jpg"
    Image.fromarray(np.round(sharpened * 255).astype(np.uint8)).save(jpeg, quality=85)
    jpg = load_xray(jpeg, sdd_mm=geometry.intrinsics.sdd_mm, pixel_spacing_mm=geometry.intrinsics.pixel_spacing_mm)
    c = _appearance(sample_ct, jpg, tmp_path_factory)
    assert (c.polarity, c.clear) == ("bone-dark", True)


@pytest.mark.slow
def test_a_mirrored_display_is_refused_and_never_named_with_confidence(sample_ct, case, tmp_path_factory):
    ct, _, centroids = sample_ct
    sim, geometry = case
    cols = sim.pixels.shape[1]
    mirrored = XrayImage(sim.pixels[:, ::-1].astype(np.float32).copy(), geometry.intrinsics, geometry.sod_mm, True,
                         "mirrored")
    uv = sim.clicks.uv_px.copy()
    uv[:, 0] = cols - 1 - uv[:, 0]
    params = RegistrationParameters(cache_dir=str(tmp_path_factory.getbasetemp() / "appearance-cache"))
    result = CarmRegLogic().register(ct, centroids, mirrored, Landmarks2D([None] * len(uv), uv), params)
    assert result.appearance.orientation != "as-stored" or not result.appearance.orientation_clear
    assert result.level_check.status != "confident"
    if result.appearance.orientation != "as-stored":
        assert not result.ok and any("mirrored or rotated" in w for w in result.warnings)
