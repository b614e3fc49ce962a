"""Level identification: spine order of the clicks, the labellings tried, the decision rule, and the whole
levels stage on simulated cases whose true levels are known (unnamed clicks, wrong names, no clicks)."""

import numpy as np
import pytest

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, project
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.levels import (
    Hypothesis,
    _decide,
    candidate_labellings,
    central_level,
    implied_labels,
    order_along_spine,
    shifted_labels,
    spatial_peaks,
    visible_levels,
)
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters
from carmreg.logic.simulation.evaluation import evaluate
from carmreg.logic.simulation.simulator import (
    SimulationOptions,
    default_geometry,
    random_pose,
    sample_options,
    simulate_case,
)

CT_NAMES = ["T9", "T10", "T11", "T12", "L1"]


def test_clicks_are_ordered_head_first_along_the_spine_whatever_order_they_came_in():
    uv = np.array([[510.0, 700.0], [500.0, 300.0], [505.0, 500.0], [498.0, 100.0]])
    assert order_along_spine(uv).tolist() == [3, 1, 2, 0]
    tilted = np.array([[100.0, 100.0], [300.0, 140.0], [200.0, 120.0]])  # a spine lying almost along the rows
    assert order_along_spine(tilted).tolist() == [0, 2, 1]


def test_unnamed_clicks_try_every_run_of_consecutive_ct_levels_including_the_ends():
    runs, given, mode = candidate_labellings([None, None, None], CT_NAMES, max_shift=2)
    assert mode == "unnamed" and given is None
    assert [labels for _, labels in runs] == [["T9", "T10", "T11"], ["T10", "T11", "T12"], ["T11", "T12", "L1"]]


def test_named_clicks_are_checked_against_their_shifts_within_the_ct():
    runs, given, mode = candidate_labellings(["T10", "T11", "T12"], CT_NAMES, max_shift=2)
    assert mode == "named"
    assert [s for s, _ in runs] == [-1, 0, 1] and runs[given] == (0, ["T10", "T11", "T12"])
    skipping = candidate_labellings(["T9", "T11", "L1"], CT_NAMES, max_shift=2)[0]  # a skipped level keeps its gap
    assert [labels for _, labels in skipping] == [["T9", "T11", "L1"]]


def test_partly_named_clicks_fill_in_consecutive_levels_or_refuse_clearly():
    assert implied_labels([None, "T11", None], CT_NAMES) == ["T10", "T11", "T12"]
    runs, given, mode = candidate_labellings([None, "T11", None], CT_NAMES, max_shift=1)
    assert mode == "partly_named" and runs[given][1] == ["T10", "T11", "T12"]
    with pytest.raises(LandmarkError, match="do not fit consecutive vertebrae in spine order"):
        implied_labels(["T12", None, "T11"], CT_NAMES)
    with pytest.raises(LandmarkError, match="beyond the CT's labelled levels"):
        implied_labels([None, "T9", None], CT_NAMES)
    with pytest.raises(LandmarkError, match="has no CT centroid"):
        implied_labels([None, "L3", None], CT_NAMES)
    with pytest.raises(LandmarkError, match="label at least as many"):
        candidate_labellings([None] * 6, CT_NAMES, 2)


def test_shifted_labels_stop_at_the_ends_of_the_ct():
    assert shifted_labels(["T11", "T12"], 1, CT_NAMES) == ["T12", "L1"]
    assert shifted_labels(["T12", "L1"], 1, CT_NAMES) is None


def _h(labels, score):
    return Hypothesis(labels, 0, np.zeros(6), score, 1.0 - score, 1.0, refined=True)


def test_decision_confident_ambiguous_contradicted():
    a, b, c = _h(["T10"], 0.50), _h(["T11"], 0.60), _h(["T12"], 0.515)
    status, margin, winner, runner = _decide([a, b], None, 0.02)
    assert (status, winner, runner) == ("confident", a, b) and margin == pytest.approx(0.10)
    assert _decide([a, c], None, 0.02)[0] == "ambiguous"
    status, margin, winner, runner = _decide([a, b], b, 0.02)       # the surgeon named b; the image prefers a
    assert (status, winner, runner) == ("contradicted", a, a) and margin == pytest.approx(-0.10)
    assert _decide([a, c], c, 0.02)[0] == "ambiguous"
    assert _decide([a, _h(["T9"], 0.9)], a, 0.02)[0] == "confident"
    screened_only = Hypothesis(["T9"], 0, np.zeros(6), 0.1, 0.9, 1.0, refined=False)  # never wins unrefined
    assert _decide([a, b, screened_only], None, 0.02)[2] is a


def test_spatial_peaks_are_separated_local_maxima_best_first():
    ty, tz = np.arange(-10.0, 12.0, 2.0), np.arange(-40.0, 42.0, 2.0)
    yy, zz = np.meshgrid(ty, tz, indexing="ij")
    score = np.exp(-((yy - 2) ** 2 + (zz - 10) ** 2) / 20) + 0.8 * np.exp(-((yy + 4) ** 2 + (zz + 16) ** 2) / 20)
    peaks = spatial_peaks(score, ty, tz, 3)
    assert peaks[:2] == [(2.0, 10.0), (-4.0, -16.0)]


def test_central_and_visible_levels_follow_the_projection():
    intr = CarmIntrinsics(1000.0, (1.0, 1.0), (200, 200))
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0)
    z = np.array([60.0, 30.0, 0.0, -30.0, -120.0])  # LPS +z superior; the last one falls outside the field
    ct = Landmarks3D(CT_NAMES, np.c_[np.zeros(5), np.zeros(5), z])
    pose = np.zeros(6)
    assert central_level(geometry, pose, ct) == "T11"
    uv = project(geometry.projection_matrix(pose), ct.points_lps_mm)
    assert np.all(np.diff(uv[:, 1]) > 0)  # head at the top: rows grow toward the feet
    mask = np.ones((200, 200), bool)
    assert visible_levels(geometry, pose, ct, mask) == ["T9", "T10", "T11", "T12"]
    mask[:100] = False
    assert visible_levels(geometry, pose, ct, mask) == ["T11", "T12"]


# ----------------------------------------------------------------------------------------------- end to end

@pytest.fixture(scope="module")
def sample(sample_ct):
    return sample_ct


@pytest.fixture(scope="module")
def simulated(sample):
    ct, labels, centroids = sample
    rng = np.random.default_rng(1234)
    options = sample_options(rng, SimulationOptions(size_px=(512, 512), pixel_spacing_mm=0.5))
    geometry = default_geometry(ct, options)
    pose = random_pose(rng, options, centroids, "T6", geometry=geometry)
    sim = simulate_case(ct, labels, centroids, geometry, pose, options, seed=7)
    xray = XrayImage(sim.pixels.astype(np.float32), geometry.intrinsics, geometry.sod_mm, True, "sim")
    return sim, xray


def _register(sample, simulated, clicks, tmp_path):
    ct, _, centroids = sample
    sim, xray = simulated
    result = CarmRegLogic().register(ct, centroids, xray, clicks, RegistrationParameters(cache_dir=str(tmp_path)))
    fitted = {lv["label"] for lv in result.levels if lv["fitted"]}
    return result, evaluate(result.projection_matrix, centroids.as_dict(), sim.ground_truth(), fitted)


@pytest.mark.slow
def test_unnamed_clicks_get_their_true_names_with_a_clear_margin(sample, simulated, tmp_path):
    sim, _ = simulated
    shuffled = [2, 0, 1]  # the click order must not matter
    clicks = Landmarks2D([None] * 3, sim.clicks.uv_px[shuffled])
    result, score = _register(sample, simulated, clicks, tmp_path)
    check = result.level_check
    assert check["mode"] == "unnamed" and check["status"] == "confident", check["message"]
    assert check["click_indices"] == [0, 1, 2]
    assert check["assigned_labels"] == [sim.clicks.labels[i] for i in shuffled]
    assert check["margin"] >= 0.02 and check["runner_up_labels"] != check["winner_labels"]
    assert result.ok and score["all_named_correctly"]
    assert np.median(score["unfitted_pde_pose_mm"]) < 3.0, score["levels"]


@pytest.mark.slow
def test_names_one_level_off_are_never_reported_confident(sample, simulated, tmp_path):
    sim, _ = simulated
    wrong = Landmarks2D(shifted_labels(sim.clicks.labels, 1, sample[2].labels), sim.clicks.uv_px)
    result, _ = _register(sample, simulated, wrong, tmp_path)
    check = result.level_check
    assert check["mode"] == "named" and check["status"] in ("contradicted", "ambiguous"), check
    assert check["winner_labels"] == list(sim.clicks.labels)
    if check["status"] == "contradicted":
        assert not result.ok and any("CONTRADICTED" in w for w in result.warnings)


@pytest.mark.slow
def test_without_clicks_the_image_alone_names_the_levels_in_view(sample, simulated, tmp_path):
    result, score = _register(sample, simulated, Landmarks2D([], np.zeros((0, 2))), tmp_path)
    check = result.level_check
    assert check["mode"] == "image_only" and check["assigned_labels"] == []
    assert set(simulated[0].clicks.labels) <= set(check["visible_labels"])
    assert score["all_named_correctly"], score["levels"]
    assert np.median(score["unfitted_pde_pose_mm"]) < 3.0
    assert [s.name for s in result.stages if s.extra.get("skipped")] == ["depth", "fine"]


def test_partly_named_clicks_that_cannot_be_consecutive_are_refused_before_any_work(sample):
    from carmreg.logic.geometry.camera import CarmIntrinsics
    from carmreg.logic.registration.pipeline import CarmRegLogic

    ct, _, centroids = sample
    ramp = np.tile(np.linspace(100.0, 200.0, 200, dtype=np.float32), (200, 1))  # structured: passes the content check
    xray = XrayImage(ramp, CarmIntrinsics(1000.0, (1.0, 1.0), (200, 200)), 600.0, True, "xr")
    clicks = Landmarks2D(["T12", None, "T11"], np.array([[100.0, 40.0], [100.0, 90.0], [100.0, 140.0]]))
    with pytest.raises(LandmarkError, match="do not fit consecutive vertebrae in spine order"):
        CarmRegLogic().prepare(ct, centroids, xray, clicks)
    state = CarmRegLogic().prepare(ct, centroids, xray, Landmarks2D(["T11", None, "L1"], clicks.uv_px))
    assert state.pairs is None  # identified in the levels stage


def test_overlay_banner_states_mode_status_margin_and_runner_up():
    from carmreg.logic.report.result_files import STATUS_RGB, level_banner

    text, rgb = level_banner({"mode": "unnamed", "status": "confident", "margin": 0.121,
                              "runner_up_labels": ["T11", "T12", "L1"]})
    assert text == "Levels from unnamed clicks: CONFIDENT (margin +0.121 over T11-L1)"
    assert rgb == STATUS_RGB["confident"]
    text, rgb = level_banner({"mode": "image_only", "status": "proposed", "margin": float("inf"),
                              "runner_up_labels": None})
    assert text == "Levels from image alone (no clicks): PROPOSED" and rgb == STATUS_RGB["proposed"]
    assert level_banner(None) is None
