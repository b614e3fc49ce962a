"""The display's orientation judged where the clicks put the CT (``click_orientation``): the geometry of a turned
image first, then the rule, then a realistic case shown as acquired and shown upside down."""

import numpy as np
import pytest
from simulated_cases import simulated_ap_case

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, project
from carmreg.logic.image.appearance import (
    CLEAR_ORIENTATION_AT_CLICKS_GC,
    ORIENTATIONS,
    REFUSE_ORIENTATION_AT_CLICKS_GC,
    decide_polarity,
    orient_uv,
)
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.click_orientation import (
    orientation_at_clicks,
    oriented_context,
    oriented_geometry,
    rival_orientations,
)
from carmreg.logic.registration.labelling_fit import FitContext
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters

# camera-frame maps that turn (or mirror) the image as ORIENTATIONS does: x_cam' = C x_cam
CAMERA_TURNS = {"mirrored-left-right": np.diag([-1.0, 1.0, 1.0]), "flipped-up-down": np.diag([1.0, -1.0, 1.0]),
                "turned-180": np.diag([-1.0, -1.0, 1.0]),
                "turned-90": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                "turned-270": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])}


@pytest.mark.parametrize("name", list(ORIENTATIONS))
def test_orient_uv_moves_a_pixel_where_the_array_orientation_moves_it(name):
    image = np.zeros((5, 7))
    for u, v in ((0, 0), (6, 0), (2, 3), (6, 4)):
        image[:] = 0
        image[v, u] = 1
        row, col = np.argwhere(ORIENTATIONS[name](image))[0]
        assert orient_uv(np.array([[u, v]]), name, (7, 5))[0].tolist() == [col, row]


@pytest.mark.parametrize("name", list(CAMERA_TURNS))
def test_the_turned_geometry_projects_where_the_turned_image_shows_a_point(name):
    """Non-square pixels and an off-centre principal point: projecting with the turned geometry and the camera
    frame turned the same way lands exactly on the turned projection (a turn of the display is a turn of the
    camera about its principal ray, a mirror its reflection)."""
    geometry = CarmGeometry(CarmIntrinsics(1000.0, (0.3, 0.4), (700, 500), (340.0, 260.0)), (0.0, 40.0, 0.0), 600.0)
    points_lps_mm = np.array([[10.0, 30.0, 50.0], [-20.0, 60.0, -40.0], [5.0, 45.0, 0.0]])
    pose = np.array([20.0, 5.0, -3.0, 2.0, 3.0, 4.0])
    rotation, t = geometry.extrinsics(pose)
    turned = oriented_geometry(geometry, name)
    P = turned.intrinsics.K @ CAMERA_TURNS[name] @ np.hstack([rotation, t[:, None]])
    expected = orient_uv(project(geometry.projection_matrix(pose), points_lps_mm), name, (700, 500))
    assert project(P, points_lps_mm) == pytest.approx(expected, abs=1e-9)


def test_the_rivals_are_what_the_database_could_not_rule_out_and_the_mirror():
    scores = {"as-stored": 0.30, "mirrored-left-right": 0.10, "flipped-up-down": 0.29, "turned-180": 0.36,
              "turned-90": 0.20}
    assert rival_orientations(scores) == ["turned-180", "flipped-up-down", "mirrored-left-right"]


def _appearance():
    return decide_polarity({"bone-dark": 0.5, "bone-bright": 0.2}, None, "auto", True, "PNG", None)


def test_the_rule_at_the_clicks_each_part_deciding():
    a = _appearance()
    a.set_orientation({"as-stored": 0.3, "mirrored-left-right": 0.31})
    assert not a.orientation_clear  # the database alone: unclear
    base = {"as-stored": 0.60, "turned-90": float("nan")}  # nan: the clicks could not be fitted turned
    fitted = {"as-stored": True, "mirrored-left-right": True, "turned-90": False}
    a.set_orientation_at_clicks({"scores": {**base, "mirrored-left-right": 0.599 - CLEAR_ORIENTATION_AT_CLICKS_GC},
                                 "fitted": fitted})
    assert (a.orientation, a.orientation_clear, a.trusted) == ("as-stored", True, True)
    assert a.orientation_decided_by == "image (at the clicks' poses)"
    a.set_orientation_at_clicks({"scores": {**base, "mirrored-left-right": 0.601 - CLEAR_ORIENTATION_AT_CLICKS_GC},
                                 "fitted": fitted})
    assert (a.orientation, a.orientation_clear, a.trusted) == ("as-stored", False, False)  # too close
    leading = {**base, "mirrored-left-right": 0.601 + REFUSE_ORIENTATION_AT_CLICKS_GC}
    a.set_orientation_at_clicks({"scores": leading, "fitted": fitted})
    assert (a.orientation, a.trusted) == ("mirrored-left-right", False)
    assert a.orientation_gc() == pytest.approx((0.601 + REFUSE_ORIENTATION_AT_CLICKS_GC, 0.60))
    a.set_orientation_at_clicks({"scores": leading, "fitted": {**fitted, "mirrored-left-right": False}})
    assert (a.orientation, a.orientation_clear) == ("as-stored", False)  # its GC bought off the clicks: unclear
    a.set_orientation_at_clicks({"scores": base, "fitted": fitted})
    assert (a.orientation, a.orientation_clear) == ("as-stored", True)  # no rival could even fit the clicks
    refused = _appearance()
    refused.set_orientation({"as-stored": 0.30, "mirrored-left-right": 0.45})  # the database: mirrored
    assert refused.orientation == "mirrored-left-right"
    refused.set_orientation_at_clicks({"scores": {**base, "mirrored-left-right": 0.40}, "fitted": fitted})
    assert (refused.orientation, refused.orientation_clear, refused.trusted) == ("as-stored", False, False)


@pytest.fixture(scope="module")
def case(sample_ct):
    """A realistic simulated AP case of the sample CT (bone dark, 512 px), T10 in the middle, named clicks."""
    return simulated_ap_case(sample_ct, 2468, "T10", 5)


def _judged(sample_ct, pixels, uv_px, labels, geometry, tmp_path_factory, rivals):
    """Run the pipeline to the polarity at the clicks, then judge ``rivals`` at the clicks' poses."""
    ct, _, centroids = sample_ct
    xray = XrayImage(pixels.astype(np.float32).copy(), geometry.intrinsics, geometry.sod_mm, True, "test")
    p = RegistrationParameters(cache_dir=str(tmp_path_factory.getbasetemp() / "orientation-cache"))
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, Landmarks2D(list(labels), uv_px), p)
    for stage in ("database", "spatial"):
        logic.run_stage(state, stage)
    a = state.appearance
    ctx = FitContext(state.pyramid.level(p.refine_coarse.mu_spacing_mm), state.geometry, state.xray_line_integral,
                     state.mask, 0.0, 0.0, p.fine, p.refine_coarse, p.magnification_range, p.depth_far_mm,
                     p.depth_step_mm)
    contexts = {o: oriented_context(ctx, o) for o in rivals}
    return orientation_at_clicks(contexts, state.click_polarity.registered[a.polarity], xray.size_px,
                                 p.identify.rule, names_follow_clicks=True)


@pytest.mark.slow
def test_at_the_clicks_poses_a_display_as_acquired_leads_and_an_upside_down_one_is_told(sample_ct, case,
                                                                                       tmp_path_factory):
    sim, geometry = case
    labels, uv = sim.clicks.labels, sim.clicks.uv_px
    shown = _judged(sample_ct, sim.pixels, uv, labels, geometry, tmp_path_factory,
                    ("mirrored-left-right", "turned-180"))
    assert shown.scores["as-stored"] >= max(shown.scores["mirrored-left-right"],
                                            np.nan_to_num(shown.scores["turned-180"], nan=-1.0)) \
        + CLEAR_ORIENTATION_AT_CLICKS_GC
    assert not shown.fitted["turned-180"]  # named clicks upside down: no C-arm pose puts T9 below T11

    upside_down = _judged(sample_ct, sim.pixels[::-1, ::-1], orient_uv(uv, "turned-180", (512, 512)), labels,
                          geometry, tmp_path_factory, ("mirrored-left-right", "turned-180"))
    assert upside_down.fitted["turned-180"]
    assert upside_down.scores["turned-180"] >= upside_down.scores["as-stored"] + REFUSE_ORIENTATION_AT_CLICKS_GC


@pytest.mark.slow
def test_judging_the_orientation_again_on_the_same_image_registers_nothing_again(sample_ct, case, tmp_path_factory,
                                                                                 monkeypatch):
    """The levels stage judges the orientation again with its winner added: the labellings the spatial stage already
    registered on each rival are reused (a registration is seeded: the same inputs give the same fit), so the
    second judgement, with nothing added, registers nothing and finds the same evidence."""
    import carmreg.logic.registration.click_orientation as click_orientation

    sim, geometry = case
    ct, _, centroids = sample_ct
    xray = XrayImage(sim.pixels.astype(np.float32).copy(), geometry.intrinsics, geometry.sod_mm, True, "test")
    p = RegistrationParameters(cache_dir=str(tmp_path_factory.getbasetemp() / "orientation-cache"))
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, Landmarks2D(list(sim.clicks.labels), sim.clicks.uv_px), p)
    for stage in ("database", "spatial"):
        logic.run_stage(state, stage)
    a = state.appearance
    first = dict(a.orientation_at_clicks)
    memo = state.turned_fits[(a.polarity, a.storage)]
    assert len(memo) == len(first["labels"]) * (len(first["scores"]) - 1)  # every judged labelling, every rival
    calls = []
    real = click_orientation._registered_turned
    monkeypatch.setattr(click_orientation, "_registered_turned", lambda *args: calls.append(args) or real(*args))
    logic._orientation_at_clicks(state, "spatial")
    assert calls == []
    assert repr(a.orientation_at_clicks) == repr(first)  # nan (an orientation nothing could be fitted on) too

    logic.run_stage(state, "database")  # a re-run of the spatial stage starts afresh
    assert state.turned_fits == {}
