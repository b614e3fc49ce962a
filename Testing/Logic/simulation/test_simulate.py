"""The C-arm simulator: exact geometry (beads land where the ground truth says, with and without distortion),
exact per-level motion, photon statistics, collimation, reproducibility and the files it writes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import GeometryError, LandmarkError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.geometry.vertebrae import (
    CARMREG_VERTEBRAE,
    carmreg_label_value,
    centroids_from_labels,
    level_ordinals,
)
from carmreg.logic.geometry.volume import MuLevel, Volume, hu_to_mu
from carmreg.logic.io.landmarks import Landmarks3D, read_landmarks_2d, read_landmarks_3d
from carmreg.logic.simulation.detector import IntensifierDistortion
from carmreg.logic.simulation.options import SimulationOptions, default_geometry, sample_options
from carmreg.logic.simulation.render import refine_thick_slices, render_moved_anatomy
from carmreg.logic.simulation.scene import Kwire, LevelMotion, kwire_path_lengths, random_pose
from carmreg.logic.simulation.simulator import simulate_case, write_simulated_case

SMALL = dict(size_px=(256, 256), pixel_spacing_mm=1.0)
"""A 256 mm detector at 1 mm pixels: the 230 mm field fits, renders in a fraction of a second."""
IDEAL = dict(photons_per_pixel=0.0, detector_blur_sigma_mm=0.0, scatter_fraction=0.0, vignetting=0.0,
             n_kwires=0, table_line_integral=0.0, burn_in_text=False, display_mode="linear",
             click_sd_mm=0.0)
"""Every effect that is not geometry switched off (the display is then mid * exp(-L) / AEC reference)."""


def make_phantom(spacing=(2.0, 2.0, 2.0), shape=(80, 60, 70), background_hu=0.0, blocks=None):
    """Box of ``background_hu`` with labelled dense spheres; returns (Volume, labels, centroids)."""
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = -0.5 * (np.array(shape) - 1) * np.array(spacing)  # centred at the LPS origin
    hu = np.full(shape, background_hu, np.float32)
    labels = np.zeros(shape, np.uint8)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    lps = ijk * np.array(spacing) + affine[:3, 3]
    for name, (center, radius, value) in (blocks or {}).items():
        inside = np.linalg.norm(lps - np.array(center), axis=-1) <= radius
        hu[inside] = value
        labels[inside] = carmreg_label_value(name)
    volume = Volume(hu, affine, "phantom")
    return volume, labels, centroids_from_labels(labels, affine, CARMREG_VERTEBRAE)


BEADS = {"T10": ((0.0, 10.0, 45.0), 2.5, 3000.0), "T11": ((30.0, 0.0, 20.0), 2.5, 3000.0),
         "T12": ((0.0, 0.0, 0.0), 2.5, 3000.0), "L1": ((-30.0, -10.0, -20.0), 2.5, 3000.0),
         "L2": ((20.0, 5.0, -40.0), 2.5, 3000.0)}


@pytest.fixture(scope="module")
def beads():
    return make_phantom(spacing=(1.0, 1.0, 1.0), shape=(150, 60, 150), blocks=BEADS)


def bead_centroid(image: np.ndarray, uv: np.ndarray, radius: int = 9) -> np.ndarray:
    """Centroid of a dark blob around uv: weights = -log(I) minus a plane fitted to the window's border."""
    u0, v0 = np.round(uv).astype(int)
    vv, uu = np.mgrid[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    line = -np.log(image[vv, uu].astype(np.float64))
    border = np.ones(line.shape, bool)
    border[2:-2, 2:-2] = False
    design = np.stack([np.ones(border.sum()), uu[border], vv[border]], -1)
    plane = np.linalg.lstsq(design, line[border], rcond=None)[0]
    weight = np.clip(line - (plane[0] + plane[1] * uu + plane[2] * vv), 0.0, None)
    return np.array([(weight * uu).sum(), (weight * vv).sum()]) / weight.sum()


# ----------------------------------------------------------------------------------------------- geometry

def test_distortion_inverse_and_edge_magnitudes():
    d = IntensifierDistortion((511.5, 511.5), (0.25, 0.25), 115.0, pincushion_edge_mm=4.0,
                              s_distortion_edge_mm=2.0)
    rng = np.random.default_rng(0)
    uv = rng.uniform(60, 960, (500, 2))
    np.testing.assert_allclose(d.undistort(d.distort(uv)), uv, atol=1e-9)
    edge = np.array([511.5 + 115.0 / 0.25, 511.5])  # ideal point on the field edge, +u axis
    moved = d.distort(edge)
    radial, tangential = (moved - (511.5, 511.5)) * 0.25
    r_edge = np.hypot(radial, tangential)
    assert r_edge - 115.0 == pytest.approx(4.0, abs=1e-9)                         # pincushion at the edge
    assert np.arctan2(tangential, radial) * 115.0 == pytest.approx(2.0, abs=1e-9)  # S twist at the edge
    np.testing.assert_allclose(d.distort(np.array([511.5, 511.5])), [511.5, 511.5])
    assert IntensifierDistortion.from_dict(d.as_dict()) == d


@pytest.mark.parametrize("distortion", [False, True])
def test_beads_land_where_ground_truth_says(beads, distortion):
    volume, labels, centroids = beads
    # 0.5 mm pixels: about 3.4 px per voxel, so point-sampled voxel edges do not bias the bead centroid
    options = SimulationOptions(size_px=(512, 512), pixel_spacing_mm=0.5, **{
        **IDEAL, "pincushion_edge_mm": 6.0 if distortion else 0.0, "s_distortion_edge_mm": 4.0 if distortion else 0.0,
        "level_translation_rms_mm": 2.0,
        "soft_tissue_hu": 0.0})               # the background is water: no ghost where a bead left
    geometry = default_geometry(volume, options)
    pose = CarmPose(tx_mm=20.0, ty_mm=-8.0, tz_mm=5.0, rx_deg=6.0, ry_deg=-4.0, rz_deg=8.0)
    sim = simulate_case(volume, labels, centroids, geometry, pose, options, seed=3)
    P = geometry.projection_matrix(pose)
    moved = {n: np.linalg.norm(sim.motions[n].translation_mm) for n in BEADS}
    assert max(moved.values()) > 1.0                         # the per-level motion really moved beads
    shift = []
    for name in BEADS:
        ideal = project(P, sim.motions[name].apply(centroids.as_dict()[name])[None])[0]
        found = bead_centroid(sim.pixels, sim.uv_true_px[name], radius=16)
        assert np.linalg.norm(found - sim.uv_true_px[name]) < 0.1, name        # 0.05 mm
        shift.append(np.linalg.norm(sim.uv_true_px[name] - ideal))
        assert sim.visible[name]
    if distortion:
        assert max(shift) > 6.0                              # distortion moved the outer beads by 3 mm
    else:
        assert max(shift) < 1e-9


def test_zero_motion_equals_plain_drr_of_refined_ct():
    volume, labels, centroids = make_phantom(spacing=(1.5, 1.5, 4.0), shape=(60, 40, 30), background_hu=20.0,
                                             blocks={"T12": ((5.0, 3.0, 10.0), 18.0, 700.0),
                                                     "L1": ((-4.0, 0.0, -30.0), 18.0, 900.0)})
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (0.8, 0.8), (160, 160)), (0.0, 0.0, 0.0), 600.0)
    pose = CarmPose(tx_mm=10.0, rx_deg=5.0, rz_deg=-7.0)
    mu = hu_to_mu(volume.hu)
    still = {n: LevelMotion(n, c, np.zeros(3), np.zeros(3)) for n, c in centroids.as_dict().items()}
    split = render_moved_anatomy(mu, labels, volume.ijk_to_lps, still, 0.0208, geometry, pose, refine=True)
    whole = render_line_integrals(MuLevel(*refine_thick_slices(mu, volume.ijk_to_lps), None), geometry, pose)
    assert refine_thick_slices(mu, volume.ijk_to_lps)[0].shape == (60, 40, 90)  # 4 mm slices -> 1.33 mm
    assert whole.max() > 1.0
    np.testing.assert_allclose(split, whole, atol=2e-5 * whole.max())


def test_level_motion_moves_projected_vertebra_as_predicted():
    # background = soft tissue exactly, so L - L(background) is the vertebra alone
    volume, labels, centroids = make_phantom(spacing=(1.0, 1.0, 1.0), shape=(90, 60, 90), background_hu=40.0,
                                             blocks={"T12": ((3.0, 2.0, -4.0), 15.0, 900.0)})
    mu = hu_to_mu(volume.hu)
    mu_soft = float(hu_to_mu(np.float32(40.0)))
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (0.5, 0.5), (200, 200)), (0.0, 0.0, 0.0), 600.0)
    pose = CarmPose(ry_deg=4.0)
    c = centroids.as_dict()["T12"]
    base = render_line_integrals(MuLevel(np.full_like(mu, mu_soft), volume.ijk_to_lps, None), geometry, pose)
    P = geometry.projection_matrix(pose)

    def image_centroid(motion):
        img = render_moved_anatomy(mu, labels, volume.ijk_to_lps, {"T12": motion}, mu_soft, geometry, pose)
        w = np.clip(img - base, 0, None)
        vv, uu = np.mgrid[0:w.shape[0], 0:w.shape[1]]
        return np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum()

    still = image_centroid(LevelMotion("T12", c, np.zeros(3), np.zeros(3)))
    moved_motion = LevelMotion("T12", c, np.array([3.0, -2.0, 4.0]), np.array([3.0, 1.5, -2.5]))
    moved = image_centroid(moved_motion)
    predicted = project(P, moved_motion.apply(c)[None])[0] - project(P, c[None])[0]
    assert np.linalg.norm(predicted) > 8.0                   # about 4 mm at the detector
    np.testing.assert_allclose(moved - still, predicted, atol=0.05)


def test_kwire_chord_lengths():
    wire = Kwire("T12", np.array([-50.0, 0.0, 0.0]), np.array([50.0, 0.0, 0.0]), 2.0)
    source = np.array([0.0, -600.0, 0.0])
    pixels = np.array([[0.0, 400.0, 0.0], [0.0, 400.0, 0.6 * 1000 / 600], [80.0 * 1000 / 600, 400.0, 0.0],
                       [0.0, 400.0, 3.0]])
    chord = kwire_path_lengths(wire, source, pixels)
    assert chord[0] == pytest.approx(2.0, abs=1e-9)                            # through the axis
    assert chord[1] == pytest.approx(2 * np.sqrt(1 - 0.6**2), abs=1e-6)        # 0.6 mm off the axis
    assert chord[2] == 0.0 and chord[3] == 0.0                                 # past the end / beside


# ----------------------------------------------------------------------------------------------- intensity

def test_photon_noise_is_poisson():
    volume = Volume(np.full((20, 20, 20), -1000, np.int16), np.diag([5.0, 5.0, 5.0, 1.0]), "air")
    options = SimulationOptions(**SMALL, **{**IDEAL, "photons_per_pixel": 400.0}, pincushion_edge_mm=0.0,
                                s_distortion_edge_mm=0.0, n_clicks=0)
    sim = simulate_case(volume, None, Landmarks3D([], np.zeros((0, 3))), default_geometry(volume, options),
                        CarmPose(), options, seed=1)
    counts = sim.pixels[78:178, 78:178].astype(np.float64) / 65535.0 / options.display_mid_grey * 400.0
    assert counts.mean() == pytest.approx(400.0, rel=0.01)
    assert counts.var() / counts.mean() == pytest.approx(1.0, abs=0.06)   # variance = mean
    assert abs(np.corrcoef(counts[:, :-1].ravel(), counts[:, 1:].ravel())[0, 1]) < 0.03  # white


def test_circular_field_dark_outside_and_text_in_corners(beads):
    volume, labels, centroids = beads
    options = SimulationOptions(**SMALL)
    sim = simulate_case(volume, labels, centroids, default_geometry(volume, options), CarmPose(), options, 2)
    vv, uu = np.mgrid[0:256, 0:256]
    r_mm = np.hypot(uu - 127.5, vv - 127.5)
    outside, inside = r_mm > 115.0 + 2.0, r_mm < 100.0
    text = sim.pixels == 60000
    assert text[:40, :].any() and text[-40:, :].any()        # burnt-in text in the black corners
    assert np.all(sim.pixels[outside & ~text] == 0)
    assert not text[r_mm < 115.0].any()
    assert np.median(sim.pixels[inside]) > 15000


def test_same_seed_same_image_other_seed_other_noise(beads):
    volume, labels, centroids = beads
    options = SimulationOptions(**SMALL, n_kwires=1)
    geometry = default_geometry(volume, options)
    a = simulate_case(volume, labels, centroids, geometry, CarmPose(), options, seed=5)
    b = simulate_case(volume, labels, centroids, geometry, CarmPose(), options, seed=5)
    c = simulate_case(volume, labels, centroids, geometry, CarmPose(), options, seed=6)
    np.testing.assert_array_equal(a.pixels, b.pixels)
    assert np.mean(a.pixels != c.pixels) > 0.3
    assert a.ground_truth() == b.ground_truth()


# ----------------------------------------------------------------------------------------------- pose and truth

def test_random_pose_stays_in_its_ranges(beads):
    volume, _, centroids = beads
    options = SimulationOptions(**SMALL)
    geometry = default_geometry(volume, options)
    rng = np.random.default_rng(11)
    points = centroids.sorted()
    ordinal = level_ordinals(points.labels)
    idx = np.array([ordinal[n] for n in points.labels])
    for _ in range(100):
        pose = random_pose(rng, options, centroids, "T12", geometry=geometry)
        p = pose.as_array()
        assert np.all(np.abs(p[3:]) <= 10.0) and abs(p[0]) <= 50.0
        aim_z = geometry.isocenter_lps_mm[2] + pose.tz_mm
        lo, hi = sorted(np.interp([ordinal["T12"] - 2.0, ordinal["T12"] + 2.0], idx, points.points_lps_mm[:, 2]))
        assert lo - 1e-9 <= aim_z <= hi + 1e-9


def test_ground_truth_is_self_consistent_and_json(beads, tmp_path):
    volume, labels, centroids = beads
    options = SimulationOptions(**SMALL, level_offset_levels=0.5, lateral_range_mm=5.0)
    geometry = default_geometry(volume, options)
    pose = random_pose(np.random.default_rng(4), options, centroids, "T12", geometry=geometry)
    sim = simulate_case(volume, labels, centroids, geometry, pose, options, seed=4)
    truth = json.loads(json.dumps(sim.ground_truth(), allow_nan=False))
    P = np.array(truth["projection_matrix"])
    np.testing.assert_allclose(P, geometry.projection_matrix(pose))
    distortion = IntensifierDistortion.from_dict(truth["distortion"])
    for level in truth["levels"].values():
        c = np.array(level["centroid_lps_mm"])
        np.testing.assert_allclose(level["uv_projected_px"], project(P, c[None])[0], atol=1e-9)
        moved = np.array(level["motion_matrix_lps"]) @ np.append(c, 1.0)
        np.testing.assert_allclose(level["uv_true_px"], distortion.distort(project(P, moved[None, :3])[0]),
                                   atol=1e-9)
    clicks = truth["clicks_uv_px"]
    assert len(clicks) == 3
    ordinal = level_ordinals(clicks)
    assert np.diff([ordinal[n] for n in clicks]).tolist() == [1, 1]
    sd_px = options.click_sd_mm / options.pixel_spacing_mm
    for name, uv in clicks.items():
        assert truth["levels"][name]["visible"]
        assert np.linalg.norm(np.subtract(uv, truth["levels"][name]["uv_true_px"])) < 5 * sd_px

    from carmreg.logic.io.xray import load_xray

    paths = write_simulated_case(tmp_path, sim)
    xray = load_xray(paths["xray"])
    assert xray.intrinsics.sdd_mm == pytest.approx(1000.0)
    np.testing.assert_allclose(xray.intrinsics.pixel_spacing_mm, (1.0, 1.0))
    np.testing.assert_array_equal(xray.pixels, sim.pixels.astype(np.float32))
    assert xray.bone_dark
    np.testing.assert_array_equal(load_xray(paths["xray_png"]).pixels, xray.pixels)
    read = read_landmarks_2d(paths["xray_landmarks"])
    np.testing.assert_allclose(read.uv_px, sim.clicks.uv_px)
    assert read_landmarks_3d(paths["ct_landmarks"]).labels == centroids.sorted().labels
    assert json.loads(paths["ground_truth"].read_text())["pose"] == pose.as_dict()


def test_options_switch_effects_off_and_ct_click_noise(beads):
    volume, labels, centroids = beads
    base = SimulationOptions(**SMALL, **IDEAL, level_rotation_sd_deg=0.0, level_translation_rms_mm=0.0,
                             pincushion_edge_mm=0.0, s_distortion_edge_mm=0.0)
    geometry = default_geometry(volume, base)
    sim = simulate_case(volume, labels, centroids, geometry, CarmPose(), base, seed=0)
    for name in BEADS:
        np.testing.assert_allclose(sim.uv_true_px[name], sim.uv_projected_px[name], atol=1e-9)
    np.testing.assert_allclose(sim.ct_landmarks.points_lps_mm, centroids.sorted().points_lps_mm)
    noisy = simulate_case(volume, labels, centroids, geometry, CarmPose(),
                          dataclasses.replace(base, ct_click_sd_mm=2.0), seed=0)
    err = np.linalg.norm(noisy.ct_landmarks.points_lps_mm - centroids.sorted().points_lps_mm, axis=1)
    assert 0.5 < err.mean() < 6.0


def test_sample_options_draw_from_the_literature_ranges():
    rng = np.random.default_rng(0)
    for _ in range(50):
        o = sample_options(rng)
        assert 0.76 <= o.bone_contrast_factor <= 1.7 and 0.05 <= o.scatter_fraction <= 0.15
        assert 1e3 <= o.photons_per_pixel <= 1e4 and 0.1 <= o.vignetting <= 0.3
        assert 2.0 <= o.pincushion_edge_mm <= 8.0 and 1.0 <= o.s_distortion_edge_mm <= 5.0
        assert o.n_kwires in (1, 2)
    assert 50 <= sample_options(rng, live_frame=True).photons_per_pixel <= 500


def test_bad_inputs_raise_actionable_errors(beads):
    volume, labels, centroids = beads
    options = SimulationOptions(**SMALL)
    geometry = default_geometry(volume, options)
    with pytest.raises(GeometryError, match="not on the CT grid"):
        simulate_case(volume, labels[:-1], centroids, geometry, CarmPose(), options)
    far = Landmarks3D(["T12"], [[0.0, 0.0, 900.0]])
    with pytest.raises(LandmarkError, match="outside the CT volume"):
        simulate_case(volume, labels, far, geometry, CarmPose(), options)
    with pytest.raises(LandmarkError, match="no CT centroid"):
        simulate_case(volume, labels, centroids, geometry, CarmPose(),
                      dataclasses.replace(options, click_levels=("T12", "L1", "L5")))


def test_run_cli_on_user_files_with_totalsegmentator_labels(beads, tmp_path, capsys):
    import argparse

    from carmreg.cli_simulate import run_cli
    from carmreg.logic.geometry.vertebrae import TOTALSEGMENTATOR_V2_VERTEBRAE
    from carmreg.logic.io.volumes import write_volume_nrrd

    volume, labels, centroids = beads
    to_ts = {carmreg_label_value(n): v for v, n in TOTALSEGMENTATOR_V2_VERTEBRAE.items()}
    ts_labels = np.vectorize(lambda x: to_ts.get(int(x), 0))(labels).astype(np.uint8)  # T12 -> 32, L1 -> 31
    write_volume_nrrd(tmp_path / "ct.nrrd", Volume(volume.hu.astype(np.int16), volume.ijk_to_lps))
    write_volume_nrrd(tmp_path / "seg.nrrd", Volume(ts_labels, volume.ijk_to_lps))
    args = argparse.Namespace(ct=str(tmp_path / "ct.nrrd"), vertebrae=str(tmp_path / "seg.nrrd"), ct_landmarks=None,
                              out=str(tmp_path / "out"), seed=2, level="T12", size_px=256)
    assert run_cli(args) == 0
    truth = json.loads((tmp_path / "out" / "ground_truth.json").read_text())
    assert sorted(truth["levels"]) == sorted(BEADS)
    assert len(truth["clicks_uv_px"]) == 3 and "clicked" in capsys.readouterr().out
    bad = argparse.Namespace(**{**vars(args), "vertebrae": None})
    with pytest.raises(LandmarkError, match="--ct-landmarks"):
        run_cli(bad)
