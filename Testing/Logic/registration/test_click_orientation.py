"""The display's orientation judged where the clicks put the CT (``click_orientation``): the geometry of a turned
image first, then the rule, then a realistic case shown as acquired and shown upside down, a mirrored display
whose polarity only the mirror tells, and one the wrong polarity takes as stored; with unnamed clicks, an upside-down
display the stored image leaves unclear; without clicks, the displays judged on the image alone (a quarter turn, a
half turn the polarity in use rules out, a mirror judged after the second opinion)."""

import copy
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from appearance_cases import copied
from simulated_cases import simulated_ap_case

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, project
from carmreg.logic.image.appearance import (
    CLEAR_ORIENTATION_AT_CLICKS_GC,
    CLEAR_REFINED_GC,
    CLOSE_ORIENTATION_AT_CLICKS_GC,
    MIN_CLICKS_GC,
    REFINED_ON_MIRROR,
    REFINED_ON_MIRROR_WITHOUT_CLICKS,
    REFINED_WITH_ORIENTATION,
    REFUSE_ORIENTATION_AT_CLICKS_GC,
    REFUSE_ORIENTATION_GC,
    decide_polarity,
    displayed_without_clicks,
    refined_on_at_clicks,
    verdict_at_clicks,
)
from carmreg.logic.image.prepare import attenuation
from carmreg.logic.image.turn import ORIENTATIONS, orient_uv, turned_clicks
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray import XrayImage, load_xray
from carmreg.logic.registration import appearance_checks
from carmreg.logic.registration.appearance_checks import (
    AppearanceChecks,
    _cannot_lead_stored,
    _database_orientation,
    _leaning,
    _rivals_under_either_polarity,
    _shown_without_clicks,
    _upside_down_rivals,
    _within_reach,
)
from carmreg.logic.registration.click_orientation import (
    MIRROR,
    ClickOrientation,
    close_call,
    displayed_under_other_polarity,
    fitted_limit_mm,
    orientation_at_clicks,
    rival_orientations,
    stored_against_turned,
)
from carmreg.logic.registration.click_polarity import ClickPolarity
from carmreg.logic.registration.image_refine import RefineResult, penalty_bound
from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit, oriented_context, oriented_geometry
from carmreg.logic.registration.outcome import refused_display
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters

# camera-frame maps that turn (or mirror) the image as ORIENTATIONS does: x_cam' = C x_cam
CAMERA_TURNS = {"mirrored-left-right": np.diag([-1.0, 1.0, 1.0]), "flipped-up-down": np.diag([1.0, -1.0, 1.0]),
                "turned-180": np.diag([-1.0, -1.0, 1.0]),
                "turned-90": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                "turned-270": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                "turned-90-and-mirrored": np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                "turned-270-and-mirrored": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])}


@pytest.mark.parametrize("name", list(ORIENTATIONS))
def test_orient_uv_moves_a_pixel_where_the_array_orientation_moves_it(name):
    image = np.zeros((5, 7))
    for u, v in ((0, 0), (6, 0), (2, 3), (6, 4)):
        image[:] = 0
        image[v, u] = 1
        row, col = np.argwhere(ORIENTATIONS[name](image))[0]
        assert orient_uv(np.array([[u, v]]), name, (7, 5))[0].tolist() == [col, row]


def test_every_turn_has_its_camera_turn():
    assert set(CAMERA_TURNS) == set(ORIENTATIONS) - {"as-stored"}


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
    hidden = {**leading, "turned-180": 0.9}  # the top rival's GC bought off the clicks hides no fitted rival
    a.set_orientation_at_clicks({"scores": hidden, "fitted": {**fitted, "turned-180": False}})
    assert (a.orientation, a.orientation_clear) == ("mirrored-left-right", False)
    refused = _appearance()
    refused.set_orientation({"as-stored": 0.30, "mirrored-left-right": 0.45})  # the database: mirrored
    assert refused.orientation == "mirrored-left-right"
    refused.set_orientation_at_clicks({"scores": {**base, "mirrored-left-right": 0.40}, "fitted": fitted})
    assert (refused.orientation, refused.orientation_clear, refused.trusted) == ("as-stored", False, False)


def test_an_appearance_is_untrusted_for_good_only_where_the_contests_winner_cannot_overrule_it():
    """``AppearanceChecks.untrusted_for_good`` (the levels contest then skips the searches that serve only a
    confident verdict): a display the database judged mirrored is; one refused only by the check at the clicks on
    the stored image's leaders is not (the winner judged too may overrule it, ``with_winner``); nor is a trusted
    display, or one as stored but unclear."""
    def for_good(a) -> bool:
        return AppearanceChecks.untrusted_for_good(a)

    base = {"as-stored": 0.60, "turned-90": float("nan")}
    fitted = {"as-stored": True, "mirrored-left-right": True, "turned-90": False}
    trusted = _appearance()
    trusted.set_orientation({"as-stored": 0.45, "mirrored-left-right": 0.30})
    assert trusted.trusted and not for_good(trusted)
    database = _appearance()
    database.set_orientation({"as-stored": 0.30, "mirrored-left-right": 0.31 + REFUSE_ORIENTATION_GC})
    assert database.orientation == MIRROR and for_good(database)
    at_clicks = _appearance()
    at_clicks.set_orientation({"as-stored": 0.30, "mirrored-left-right": 0.31})
    at_clicks.set_orientation_at_clicks({"scores": {**base, MIRROR: 0.601 + REFUSE_ORIENTATION_AT_CLICKS_GC},
                                         "fitted": fitted})
    assert at_clicks.orientation == MIRROR and not at_clicks.trusted and not for_good(at_clicks)
    unclear = _appearance()
    unclear.set_orientation({"as-stored": 0.30, "mirrored-left-right": 0.31})
    assert (unclear.orientation, unclear.trusted, for_good(unclear)) == ("as-stored", False, False)
    assert not AppearanceChecks.untrusted_for_good(None)


def test_trust_is_within_reach_only_where_a_winner_would_be_judged_anew():
    """``AppearanceChecks.trust_within_reach`` (since stop 59: no contest under the other polarity, and no searches
    for confidence, when it is False): report case 149's large patient, second CT, all four labellings of L1-S1
    judged at the clicks, the orientation unclear under either polarity. Each part decides once: a trusted
    appearance, a labelling not judged, a clear orientation (a judged winner found at a better pose is judged
    again), no polarity check at the clicks, a display refused for good."""
    judged = [["L1", "L2", "L3"], ["L2", "L3", "L4"], ["L3", "L4", "L5"], ["L4", "L5", "S1"]]
    fits = [SimpleNamespace(names=lambda lb, mine=mine: list(lb) == mine) for mine in judged]
    state = SimpleNamespace(click_polarity=SimpleNamespace(labels=judged), appearance=_appearance())
    unclear = state.appearance
    unclear.clear = False
    unclear.set_orientation({"as-stored": 0.087, "mirrored-left-right": 0.086, "turned-180": 0.102})
    assert not unclear.orientation_clear and not AppearanceChecks.trust_within_reach(state, fits)
    state.click_polarity.labels = judged[1:]  # L1-L3 never judged: its win would be
    assert AppearanceChecks.trust_within_reach(state, fits)
    state.click_polarity.labels = judged
    clear = copy.deepcopy(unclear)
    clear.set_orientation({"as-stored": 0.45, "mirrored-left-right": 0.30})
    assert clear.orientation_clear and not clear.trusted  # the polarity unclear
    assert AppearanceChecks.trust_within_reach(state, fits, clear)
    trusted = _appearance()
    trusted.set_orientation({"as-stored": 0.45, "mirrored-left-right": 0.30})
    assert trusted.trusted and AppearanceChecks.trust_within_reach(state, [], trusted)
    undecided = SimpleNamespace(click_polarity=state.click_polarity, appearance=None)
    assert AppearanceChecks.trust_within_reach(undecided, fits)  # no appearance checks: nothing keeps trust away
    assert not AppearanceChecks.trust_within_reach(SimpleNamespace(click_polarity=None, appearance=clear), fits)
    mirrored = copy.deepcopy(clear)
    mirrored.set_orientation({"as-stored": 0.30, "mirrored-left-right": 0.31 + REFUSE_ORIENTATION_GC})
    state.click_polarity.labels = []
    assert AppearanceChecks.untrusted_for_good(mirrored)
    assert not AppearanceChecks.trust_within_reach(state, fits, mirrored)


def _registered(similarity_mpde: dict, fits: dict) -> ClickPolarity:
    """A polarity check's evidence: {polarity: [(GC, mPDE mm) of each labelling]}, and its verdict's ``fits``."""
    registered = {p: [SimpleNamespace(similarity=g, mpde_mm=m) for g, m in done] for p, done in similarity_mpde.items()}
    scores = {p: max(f.similarity for f in done) for p, done in registered.items()}
    return ClickPolarity(scores, fits, registered, [["T10", "T11", "T12"], ["T11", "T12", "L1"]], "log-display")


def test_the_polarity_judged_on_the_mirror_too_compares_each_orientations_best_registration_under_it():
    rule = RegistrationParameters().identify.rule
    stored = _registered({"bone-dark": [(0.30, 3.0), (0.41, 2.0)], "bone-bright": [(0.35, 5.0), (0.1, 6.0)]},
                         {"bone-dark": True, "bone-bright": False})
    mirrored = _registered({"bone-dark": [(0.62, 1.8), (0.2, 4.0)], "bone-bright": [(-0.05, 5.0), (0.0, 6.0)]},
                           {"bone-dark": True, "bone-bright": False})
    evidence = stored_against_turned(stored, mirrored, MIRROR, "bone-dark", rule)
    assert evidence.scores == {"as-stored": 0.41, MIRROR: 0.62}
    assert evidence.mpde_mm == {"as-stored": 2.0, MIRROR: 1.8}
    assert evidence.fitted == {"as-stored": True, MIRROR: True}
    a = _appearance()
    a.set_orientation_at_clicks(evidence.as_dict())
    assert (a.orientation, a.trusted) == (MIRROR, False)
    # the mirror's best registration left its clicks, by its own verdict or against the stored one's mPDE
    unfitted = _registered({"bone-dark": [(0.62, 1.8)], "bone-bright": [(0.0, 1.0)]},
                           {"bone-dark": False, "bone-bright": True})
    assert not stored_against_turned(stored, unfitted, MIRROR, "bone-dark", rule).fitted[MIRROR]
    far = _registered({"bone-dark": [(0.62, rule.max_landmark_mpde_mm + 0.1)], "bone-bright": [(0.0, 9.0)]},
                      {"bone-dark": True, "bone-bright": False})
    assert not stored_against_turned(stored, far, MIRROR, "bone-dark", rule).fitted[MIRROR]


def test_a_stored_registration_that_does_not_show_the_spine_sets_no_reference_for_the_clicks_fit():
    """``fitted_limit_mm``: a rival keeps the clicks fitted within the landmark limit against the stored
    orientation's best registration, or within the rule's cap alone when that registration's GC is under
    ``MIN_CLICKS_GC`` (report case 295's half turn at stop 62: stored 0.108 at 0.83 mm, the half turn 0.832 at
    1.92 mm). Both checks at the clicks use it."""
    rule = RegistrationParameters().identify.rule
    assert fitted_limit_mm(MIN_CLICKS_GC, 0.83, rule) == pytest.approx(rule.landmark_ratio * 0.83
                                                                       + rule.landmark_slack_mm)
    assert fitted_limit_mm(MIN_CLICKS_GC - 0.01, 0.83, rule) == rule.max_landmark_mpde_mm
    stored = _registered({"bone-dark": [(0.108, 0.83), (0.06, 1.65)], "bone-bright": [(0.16, 1.79)]},
                         {"bone-dark": True, "bone-bright": True})
    turned = _registered({"bone-dark": [(0.832, 1.92), (0.62, 3.45)], "bone-bright": [(-0.07, 1.05)]},
                         {"bone-dark": True, "bone-bright": False})
    evidence = stored_against_turned(stored, turned, "turned-180", "bone-dark", rule)
    assert evidence.fitted["turned-180"] and evidence.scores == {"as-stored": 0.108, "turned-180": 0.832}
    shown = _registered({"bone-dark": [(MIN_CLICKS_GC, 0.83)], "bone-bright": [(0.16, 1.79)]},
                        {"bone-dark": True, "bone-bright": True})
    assert not stored_against_turned(shown, turned, "turned-180", "bone-dark", rule).fitted["turned-180"]


def test_turned_clicks_keep_their_names():
    clicks = Landmarks2D(["T11", None, "L1"], np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]]))
    turned = turned_clicks(clicks, MIRROR, (100, 80))
    assert turned.labels == ["T11", None, "L1"]
    assert turned.uv_px.tolist() == [[89.0, 20.0], [69.0, 40.0], [49.0, 60.0]]


@pytest.fixture(scope="module")
def mirrored_display(tmp_path_factory, drr_cache_dir):
    """The appearance benchmark's tune case 0 (chest CT, its independent simulator), an intensifier image shown
    mirrored left-right, bone dark, 16-bit PNG: (CT, its centroids, X-ray, the three clicks' (u, v) px, parameters
    with the session's DRR cache)."""
    ct, centroids, xray, truth = _benchmark_scene(0, tmp_path_factory.mktemp("mirrored-case"))
    params = RegistrationParameters(cache_dir=drr_cache_dir)
    return ct, centroids, xray, np.asarray(truth["clicks_uv_px"], float), params


def _benchmark_scene(case: int, folder: Path, variant_name: str = "ii-dark-mirrored-png", second_ct: bool = False):
    """(CT, its centroids, X-ray, truth): the appearance benchmark's scene ``case`` drawn on the chest CT (no
    ../shared needed; ``second_ct``: on the CT the benchmark draws it on, the test skipped when the second CT, in
    ../shared, is absent) as ``variant_name`` (by default the intensifier image shown mirrored left-right, bone
    dark, 16-bit PNG), written to ``folder`` and read as ``carmreg register`` reads it."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Benchmarks"))
    import appearance as app
    import bench_appearance as bench

    maker = bench.CaseMaker(second_ct=second_ct)
    if second_ct and "abdomen" not in maker.cts:
        pytest.skip("the second CT (../shared) is absent")
    variant = app.VARIANTS[variant_name]
    record = bench.write_variant(maker.scenes(case, {variant.detector})[variant.detector], variant, case, folder)
    detector = app.DETECTORS[variant.detector]
    xray = load_xray(record["xray"], sdd_mm=detector.sdd_mm, pixel_spacing_mm=detector.pixel_mm)
    (ct, _, centroids), _, _ = maker.cts[maker.ct_name(case)]
    return ct, centroids, xray, record["truth"]


def _spatial_stage(case: int, folder: Path, variant_name: str, drr_cache_dir: str, second_ct: bool = False,
                   unnamed_clicks: bool = False, with_logic: bool = False):
    """(state after the spatial stage, truth): the benchmark's scene ``case`` as ``variant_name``
    (``_benchmark_scene``) registered without clicks (``unnamed_clicks``: with the scene's clicks, unnamed) up to
    where the appearance is decided; ``with_logic``: (the logic that ran it, state, truth)."""
    ct, centroids, xray, truth = _benchmark_scene(case, folder, variant_name, second_ct)
    uv = np.asarray(truth["clicks_uv_px"], float) if unnamed_clicks else np.zeros((0, 2))
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, Landmarks2D([None] * len(uv), uv),
                          RegistrationParameters(cache_dir=drr_cache_dir))
    logic.run_through(state, "spatial")
    return (logic, state, truth) if with_logic else (state, truth)


def _appearance_found(mirrored_display, clicks: Landmarks2D):
    """The registration state after the spatial stage, where the appearance is decided."""
    ct, centroids, xray, _, params = mirrored_display
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, clicks, params)
    logic.run_through(state, "spatial")
    return state


@pytest.mark.slow
@pytest.mark.benchmark_case
@pytest.mark.usefixtures("click_spacing_order")
def test_a_mirrored_display_the_stored_image_leaves_unclear_gets_its_polarity_from_the_mirror(sample_case_dir,
                                                                                              mirrored_display):
    """The mirrored display with three unnamed clicks: where the clicks put the CT as stored, neither polarity
    shows an aligned spine (stop 18: the verdict unclear, bone bright taken). Judged on the mirror too, the
    polarity is found bone dark, and the display mirrored: refused, so no level answer can be confident."""
    uv = mirrored_display[3]
    state = _appearance_found(mirrored_display, Landmarks2D([None] * len(uv), uv))
    a = state.appearance
    as_stored = a.scores["at_clicks"]
    assert not verdict_at_clicks(as_stored["scores"], as_stored["fits"])[2]  # the stored image alone: unclear
    assert (a.polarity, a.clear, a.decided_by) == ("bone-dark", True, f"image ({REFINED_ON_MIRROR})")
    assert a.scores["on_mirror"]["scores"]["bone-dark"] >= a.scores["on_mirror"]["scores"]["bone-bright"] + 0.10
    assert (a.orientation, a.trusted) == (MIRROR, False)
    assert a.orientation_at_clicks["scores"][MIRROR] >= a.orientation_at_clicks["scores"]["as-stored"] \
        + REFUSE_ORIENTATION_AT_CLICKS_GC
    assert state.xray_line_integral is not None and state.known_gc is not None
    # refused on the mirror, which no winner can overrule: the contest skips its confidence searches, ambiguous
    assert AppearanceChecks.untrusted_for_good(state.appearance)


@pytest.mark.slow
@pytest.mark.benchmark_case
def test_without_clicks_a_mirrored_display_gets_its_polarity_from_the_mirror_and_is_refused(sample_case_dir,
                                                                                          mirrored_display):
    """The same mirrored display, no clicks. Refined on the image as stored, the polarity is unclear (stop 16's
    run: bone dark 0.455 against bone bright 0.364, under CLEAR_REFINED_GC); refined on its mirror, bone dark leads
    clearly and the mirror agrees with the image far more than the stored image does: the polarity is taken from
    the mirror, and the display refused as mirrored (no level answer can be proposed)."""
    a = _appearance_found(mirrored_display, Landmarks2D([], np.zeros((0, 2)))).appearance
    stored, mirrored = a.scores["without_clicks"]["scores"], a.scores["without_clicks_on_mirror"]["scores"]
    assert abs(stored["bone-dark"] - stored["bone-bright"]) < CLEAR_REFINED_GC  # the stored image alone: unclear
    assert mirrored["bone-dark"] >= mirrored["bone-bright"] + CLEAR_REFINED_GC
    assert (a.polarity, a.clear, a.decided_by) == ("bone-dark", True, f"image ({REFINED_ON_MIRROR_WITHOUT_CLICKS})")
    assert a.orientation_without_clicks == {"as-stored": stored["bone-dark"], MIRROR: mirrored["bone-dark"]}
    assert mirrored["bone-dark"] >= stored["bone-dark"] + REFUSE_ORIENTATION_AT_CLICKS_GC
    assert (a.orientation, a.trusted) == (MIRROR, False)
    assert a.orientation_gc() == (mirrored["bone-dark"], stored["bone-dark"])  # what the refusal's words quote
    assert "refined on the image as stored and mirrored left right" in a.summary()


def test_without_clicks_a_quarter_turn_is_a_rival_on_a_square_detector_with_square_pixels_only(monkeypatch):
    """``_shown_without_clicks`` among ``_rivals_under_either_polarity``: the database's rivals (``rival_orientations``)
    under the polarity in use, then the other's not yet named; the quarter turns among them only where the turned
    image lies on the database's pixel grid."""
    in_use = {"as-stored": 0.30, MIRROR: 0.10, "flipped-up-down": 0.20, "turned-180": 0.29, "turned-90": 0.35,
              "turned-270": 0.31, "turned-90-and-mirrored": 0.05, "turned-270-and-mirrored": 0.28}
    other = {**in_use, MIRROR: 0.32, "turned-90": 0.10, "flipped-up-down": 0.285}
    monkeypatch.setattr(appearance_checks, "_database_orientation", lambda state, bone_dark: other)
    state = SimpleNamespace(appearance=SimpleNamespace(orientation_scores=in_use, bone_dark=True))
    rivals = _rivals_under_either_polarity(state)
    assert rivals == ["turned-90", "turned-270", "turned-180", "turned-270-and-mirrored", MIRROR, "flipped-up-down"]
    assert [o for o in rivals if o in _shown_without_clicks((0.4, 0.4))] == rivals
    assert [o for o in rivals if o in _shown_without_clicks((0.4, 0.5))] == ["turned-180", MIRROR, "flipped-up-down"]


@pytest.mark.slow
@pytest.mark.benchmark_case
def test_without_clicks_a_quarter_turned_display_is_found_with_its_polarity_and_refused(sample_case_dir,
                                                                                       tmp_path_factory,
                                                                                       drr_cache_dir):
    """The appearance benchmark's tune case 504 (chest CT): its flat-panel JPEG, bone dark, shown turned a quarter
    counter-clockwise on the square detector, no clicks. Refined as stored, neither polarity shows a spine (stop 56:
    bone bright taken, unclear, the display left as stored). Refined on the quarter turns too, the image turned
    back (turned-270) agrees far more, bone dark clearly: the polarity is taken from it, and the display refused
    with the turn that undoes it."""
    state, truth = _spatial_stage(504, tmp_path_factory.mktemp("turned-case"), "fp-dark-turned90-jpeg",
                                  drr_cache_dir)
    assert truth["display_turn"] == "turned-90" and not truth["bone_bright_displayed"]
    a = state.appearance
    stored, turned = a.scores["without_clicks"]["scores"], a.scores["without_clicks_on_turned-270"]["scores"]
    assert abs(stored["bone-dark"] - stored["bone-bright"]) < CLEAR_REFINED_GC  # the stored image alone: unclear
    assert turned["bone-dark"] >= turned["bone-bright"] + CLEAR_REFINED_GC
    assert turned["bone-dark"] >= stored["bone-dark"] + REFUSE_ORIENTATION_AT_CLICKS_GC
    assert (a.polarity, a.clear, a.orientation, a.trusted) == ("bone-dark", True, "turned-270", False)
    assert a.orientation_without_clicks == {"as-stored": stored["bone-dark"], "turned-270": turned["bone-dark"]}
    assert "--orient-xray turned-270" in refused_display(a)  # the refusal names the turn that shows it head up


@pytest.mark.slow
@pytest.mark.benchmark_case
def test_without_clicks_a_display_the_database_rules_out_only_under_the_polarity_in_use_is_still_judged(
        sample_case_dir, tmp_path_factory, drr_cache_dir):
    """The appearance benchmark's tune case 502 (chest CT): its intensifier PNG, bone dark, shown turned 180
    degrees, no clicks. Refined as stored, bone bright leads, unclear, and under bone bright the database rules the
    half turn out (stop 56: the display left as stored, bone bright). Under bone dark the database's half turn
    leads: judged there too, the half turn agrees far more, bone dark clearly, and the display is refused."""
    state, truth = _spatial_stage(502, tmp_path_factory.mktemp("half-turned-case"), "ii-dark-turned180-png",
                                  drr_cache_dir)
    assert truth["display_turn"] == "turned-180" and not truth["bone_bright_displayed"]
    a = state.appearance
    stored, turned = a.scores["without_clicks"]["scores"], a.scores["without_clicks_on_turned-180"]["scores"]
    assert stored["bone-bright"] > stored["bone-dark"] > stored["bone-bright"] - CLEAR_REFINED_GC
    under_bright = _database_orientation(state, bone_dark=False)
    assert "turned-180" not in rival_orientations(under_bright)  # ruled out under the polarity first in use
    assert turned["bone-dark"] >= stored["bone-dark"] + REFUSE_ORIENTATION_AT_CLICKS_GC
    assert (a.polarity, a.orientation, a.trusted) == ("bone-dark", "turned-180", False)


@pytest.mark.slow
@pytest.mark.benchmark_case
def test_without_clicks_the_displays_are_judged_after_a_second_opinion_that_leaves_the_verdict_unclear(
        sample_case_dir, tmp_path_factory, drr_cache_dir):
    """The appearance benchmark's tune case 296 (the second CT: skipped without ../shared): its intensifier PNG,
    bone dark, shown mirrored, no clicks. Refined as stored, bone bright leads clearly, so no display is judged
    then; the second opinion without the shading does not confirm it (stop 61, the benchmark's run: 0.222 over the
    0.22, then 0.026). Judged after it, the mirror agrees far more, bone dark: the display is refused."""
    state, truth = _spatial_stage(296, tmp_path_factory.mktemp("unconfirmed-case"), "ii-dark-mirrored-png",
                                  drr_cache_dir, second_ct=True)
    assert truth["mirrored"] and not truth["bone_bright_displayed"]
    a = state.appearance
    keys = list(a.scores)
    assert keys.index("without_clicks_without_shading") < keys.index("without_clicks_on_mirror")  # judged after it
    stored, mirrored = a.scores["without_clicks"]["scores"], a.scores["without_clicks_on_mirror"]["scores"]
    assert stored["bone-bright"] >= stored["bone-dark"] + CLEAR_REFINED_GC  # clear as stored, and wrong
    assert mirrored["bone-dark"] >= stored["bone-dark"] + REFUSE_ORIENTATION_AT_CLICKS_GC
    assert (a.polarity, a.orientation, a.trusted) == ("bone-dark", MIRROR, False)


def test_with_unnamed_clicks_the_upside_down_displays_either_polarity_keeps_are_rivals(monkeypatch):
    """``_upside_down_rivals``: with unnamed clicks, the flip and the half turn the database could not rule out under
    the polarity in use or the other one (the polarity in use's first, each in its order), or only the display the
    database refuses the image for; with named clicks none (named clicks on an upside-down display run bottom to top
    and are refused before)."""
    in_use = {"as-stored": 0.52, MIRROR: 0.40, "flipped-up-down": 0.33, "turned-180": 0.48}  # both ruled out
    other = {"as-stored": 0.36, MIRROR: 0.34, "flipped-up-down": 0.35, "turned-180": 0.40}   # neither
    asked = []

    def under(state, bone_dark):
        asked.append(bone_dark)
        return other

    monkeypatch.setattr(appearance_checks, "_database_orientation", under)
    uv = np.array([[10.0, 20.0], [11.0, 40.0], [12.0, 60.0]])
    state = SimpleNamespace(appearance=SimpleNamespace(orientation_scores=in_use, bone_dark=True,
                                                       orientation="as-stored"),
                            xray_landmarks=Landmarks2D([None] * 3, uv))
    assert _upside_down_rivals(state) == ["turned-180", "flipped-up-down"] and asked == [False]
    state.appearance.orientation_scores = {**in_use, "flipped-up-down": 0.50}  # kept under the polarity in use
    assert _upside_down_rivals(state) == ["flipped-up-down", "turned-180"]
    state.appearance.orientation = "flipped-up-down"  # the database refuses the image for the flip: that one only
    assert _upside_down_rivals(state) == ["flipped-up-down"]
    state.appearance.orientation = MIRROR  # ... for another display: none
    assert _upside_down_rivals(state) == []
    state.appearance.orientation = "as-stored"
    state.xray_landmarks = Landmarks2D(["T6", "T7", "T8"], uv)
    assert _upside_down_rivals(state) == []


def _registered_at(similarity: dict, stopped: dict | None = None) -> ClickPolarity:
    """A ``ClickPolarity`` whose registrations under each polarity end at ``similarity[polarity]`` (a list), those
    of ``stopped`` ({polarity: [evaluations or None]}) stopped early."""
    def fit(gc, at):
        return LabellingFit(["T6", "T7", "T8"], 0, np.zeros((3, 3)), np.zeros((3, 2)),
                            refine=RefineResult(np.zeros(6), gc, gc, 1.0, 800, stopped_at=at))

    stopped = stopped or {}
    registered = {p: [fit(g, (stopped.get(p) or [None] * len(gcs))[k]) for k, g in enumerate(gcs)]
                  for p, gcs in similarity.items()}
    return ClickPolarity({p: max(g) for p, g in similarity.items()}, {p: True for p in similarity}, registered,
                         [["T6", "T7", "T8"]], "log-display")


def test_a_displays_registrations_stop_once_they_cannot_lead_the_stored_image_and_one_that_may_is_judged_in_full():
    """``_cannot_lead_stored``: each registration of a display stops once it cannot end
    ``REFUSE_ORIENTATION_AT_CLICKS_GC`` ahead of the stored image's best under its own polarity (the bar of
    ``early_stop.cannot_lead``, the penalty from its landmark pose and the rule's cap on the clicks);
    ``_within_reach``: a display one of whose full registrations leads by that margin is judged again in full, a
    stopped one never counts (it cannot get there)."""
    stored = _registered_at({"bone-dark": [0.30, 0.22], "bone-bright": [0.41]})
    params = RegistrationParameters()
    uv = np.array([[10.0, 20.0], [11.0, 40.0], [12.0, 60.0]])
    state = SimpleNamespace(parameters=params, xray_landmarks=Landmarks2D([None] * 3, uv))
    pose = np.array([0.0, 1.0, 2.0, 3.0, -4.0, 5.0])
    penalty = penalty_bound(params.refine_coarse, pose, 3, params.identify.rule.max_landmark_mpde_mm)
    give_up_for = _cannot_lead_stored(state, stored)
    assert give_up_for("bone-dark", pose).bar == pytest.approx(1.0 - (0.30 + REFUSE_ORIENTATION_AT_CLICKS_GC) + penalty)
    assert give_up_for("bone-bright", pose).bar == pytest.approx(1.0 - 0.51 + penalty)
    at, bright = _registered_at, "bone-bright"  # bone bright in use: a display lends bone dark only
    assert not _within_reach(at({"bone-dark": [0.39, 0.10], "bone-bright": [0.50]}), stored, bright)
    assert _within_reach(at({"bone-dark": [0.41, 0.10], "bone-bright": [0.50]}), stored, bright)  # leads by 0.11
    assert not _within_reach(at({"bone-dark": [0.10], "bone-bright": [0.60]}, {"bone-bright": [480]}), stored, bright)
    assert at({"bone-dark": [0.10]}, {"bone-dark": [480]}).as_dict()["stopped_at_evaluations"] == {"bone-dark": [480]}
    assert "stopped_at_evaluations" not in stored.as_dict()


def test_a_display_ahead_of_the_stored_image_under_either_polarity_lends_its_clear_polarity_never_clear():
    """``_leaning`` (stop 64, report case 441's mirrored display: unclear as stored, bone bright taken; on the
    mirror bone dark clearly, 0.039 ahead of the stored image's best, under the 0.10 that takes a display): a
    display's clear verdict for the polarity not in use, from a registration ahead of the stored image's best under
    either polarity, lends that polarity, never clear (only the levels' winner, judged at the clicks too, can make
    it clear); each part decides. ``_within_reach``: such a display is judged in full first (a stopped registration
    never counts)."""
    stored = _registered_at({"bone-dark": [0.387, 0.375], "bone-bright": [0.177]})
    mirror = _registered_at({"bone-dark": [0.426, 0.388], "bone-bright": [0.011]})
    dark = SimpleNamespace(clear=True, polarity="bone-dark")
    bright = SimpleNamespace(clear=True, polarity="bone-bright")
    assert _leaning(dark, mirror, stored, "bone-bright") == pytest.approx(0.426 - 0.387)
    assert _leaning(dark, mirror, stored, "bone-dark") is None  # the polarity in use already
    assert _leaning(SimpleNamespace(clear=False, polarity="bone-dark"), mirror, stored, "bone-bright") is None
    behind = _registered_at({"bone-dark": [0.380], "bone-bright": [0.011]})
    assert _leaning(dark, behind, stored, "bone-bright") is None  # not ahead of the stored image's best (0.387)
    assert _leaning(bright, _registered_at({"bone-dark": [0.1], "bone-bright": [0.39]}), stored, "bone-dark") > 0
    assert _within_reach(mirror, stored, "bone-bright") and not _within_reach(mirror, stored, "bone-dark")
    assert not _within_reach(_registered_at({"bone-dark": [0.426]}, {"bone-dark": [480]}), stored, "bone-bright")
    first = _appearance()
    first.clear, first.polarity = False, "bone-bright"
    lent = decide_polarity({"bone-dark": 0.34, "bone-bright": 0.31}, {"bone-dark": 0.426, "bone-bright": 0.011},
                           "auto", True, "PNG", refined_by=refined_on_at_clicks(MIRROR),
                           fits={"bone-dark": True, "bone-bright": True})
    lent.set_orientation({"as-stored": 0.31, MIRROR: 0.34})
    assert lent.clear and not lent.lent_by_display  # clear: not lent
    lent.leaned_on_display(first, MIRROR, 0.039)
    assert (lent.polarity, lent.clear, lent.trusted, lent.lent_by_display) == ("bone-dark", False, False, True)
    assert "found only on the image mirrored left right" in lent.note and "taken bone-bright" in lent.note
    assert not AppearanceChecks.untrusted_for_good(lent)  # a winner judged at the clicks may still settle it


@pytest.mark.slow
@pytest.mark.benchmark_case
@pytest.mark.usefixtures("click_spacing_order")
def test_with_unnamed_clicks_an_upside_down_display_left_unclear_as_stored_gets_its_polarity_from_the_turn(
        sample_case_dir, tmp_path_factory, drr_cache_dir):
    """The appearance benchmark's tune case 294 (chest CT): its intensifier PNG, bone dark, shown turned 180 degrees,
    three unnamed clicks. As stored the clicks fit either polarity's registrations poorly and the verdict is unclear
    (stop 61's code: bone bright, wrong; the contest under the other polarity, 41 s, ambiguous). Judged on the half
    turn with the clicks turned with it, bone dark leads clearly and the turned display leads the stored image under
    it: the polarity is taken from the turn, and the display refused for good (no winner can overrule it)."""
    state, truth = _spatial_stage(294, tmp_path_factory.mktemp("half-turn-unclear"), "ii-dark-turned180-png",
                                  drr_cache_dir, unnamed_clicks=True)
    assert truth["display_turn"] == "turned-180" and not truth["bone_bright_displayed"]
    a = state.appearance
    as_stored, turned = a.scores["at_clicks"], a.scores["on_turned-180"]
    assert not verdict_at_clicks(as_stored["scores"], as_stored["fits"])[2]  # the stored image alone: unclear
    seen, _, clear = verdict_at_clicks(turned["scores"], turned["fits"])
    assert (seen, clear) == ("bone-dark", True)
    assert (a.polarity, a.clear, a.decided_by) == ("bone-dark", True, f"image ({refined_on_at_clicks('turned-180')})")
    scores = a.orientation_at_clicks["scores"]
    assert scores["turned-180"] >= scores["as-stored"] + REFUSE_ORIENTATION_AT_CLICKS_GC
    assert (a.orientation, a.trusted) == ("turned-180", False) and AppearanceChecks.untrusted_for_good(a)
    assert "--orient-xray turned-180" in refused_display(a)
    assert "stopped_at_evaluations" not in turned  # within reach: judged again in full, its verdict on full ones


@pytest.mark.slow
@pytest.mark.benchmark_case
@pytest.mark.usefixtures("click_spacing_order")
def test_with_unnamed_clicks_a_mirrored_display_ahead_by_less_than_the_refusal_lends_its_polarity(
        sample_case_dir, tmp_path_factory, drr_cache_dir):
    """The appearance benchmark's report case 441 (chest CT; stop 63's one polarity miss, no threshold chosen on
    it): its intensifier PNG, bone dark, shown mirrored, three unnamed clicks. As stored bone dark leads off the
    clicks and bone bright keeps them, and the second opinion cannot tell: unclear, bone bright taken. On the mirror
    bone dark leads clearly and the mirror is ahead of the stored image under either polarity, by less than the
    0.10 that takes a display: the mirror lends its polarity, never clear. The levels contest then runs on the
    stored image as bone dark, with no contest under bone bright (``worth_other_polarity``): its winner, judged at
    the clicks too, does not make the appearance trusted, and the answer is ambiguous."""
    logic, state, truth = _spatial_stage(441, tmp_path_factory.mktemp("mirror-lends"), "ii-dark-mirrored-png",
                                         drr_cache_dir, unnamed_clicks=True, with_logic=True)
    assert truth["mirrored"] and not truth["bone_bright_displayed"]
    a = state.appearance
    as_stored, mirror = a.scores["at_clicks"], a.scores["on_mirror"]
    assert not verdict_at_clicks(as_stored["scores"], as_stored["fits"])[2]  # the stored image alone: unclear
    assert verdict_at_clicks(mirror["scores"], mirror["fits"])[::2] == ("bone-dark", True)
    ahead = mirror["scores"]["bone-dark"] - max(as_stored["scores"].values())
    assert 0 < ahead < REFUSE_ORIENTATION_AT_CLICKS_GC
    assert (a.polarity, a.clear, a.orientation) == ("bone-dark", False, "as-stored") and a.lent_by_display
    assert a.decided_by == f"image ({REFINED_ON_MIRROR})" and "found only on the image mirrored" in a.note
    assert "stopped_at_evaluations" not in mirror  # it lends on full registrations
    logic.run_stage(state, "levels")
    assert state.identification.status == "ambiguous" and not state.appearance.trusted
    assert "contest_under_other_polarity" not in state.appearance.scores


def test_without_clicks_the_display_is_the_rival_leading_the_stored_image_under_its_own_polarity():
    """``displayed_without_clicks``, each part deciding (stop 56's turned displays: case 503's half turn refined 0.617
    bone dark against 0.327 as stored): each rival is judged under the polarity leading on it, against the stored
    image under that polarity; the best lead refuses at ``REFUSE_ORIENTATION_AT_CLICKS_GC``."""
    stored = {"bone-dark": 0.327, "bone-bright": 0.403}
    half_turn = {"bone-dark": 0.617, "bone-bright": 0.449}
    assert displayed_without_clicks(stored, {MIRROR: {"bone-dark": 0.313, "bone-bright": 0.426},
                                             "turned-180": half_turn}) == (
        "turned-180", {"as-stored": 0.327, "turned-180": 0.617})
    # judged under its own leading polarity: bone bright leads on the flip, 0.49 - 0.403 (not 0.49 - 0.327)
    flip = {"bone-dark": 0.40, "bone-bright": 0.49}
    assert displayed_without_clicks(stored, {"flipped-up-down": flip}) is None
    refuse = REFUSE_ORIENTATION_AT_CLICKS_GC
    for lead, taken in ((refuse + 1e-9, True), (refuse - 0.001, False)):
        shown = displayed_without_clicks(stored, {"flipped-up-down": {"bone-dark": 0.40, "bone-bright": 0.403 + lead}})
        assert (shown is not None and shown[0] == "flipped-up-down") == taken
    # the best lead decides, whichever rival comes first; none judged, none taken
    mirror = {"bone-dark": 0.327 + REFUSE_ORIENTATION_AT_CLICKS_GC + 0.01, "bone-bright": 0.2}
    assert displayed_without_clicks(stored, {MIRROR: mirror, "turned-180": half_turn})[0] == "turned-180"
    assert displayed_without_clicks(stored, {"turned-180": half_turn, MIRROR: mirror})[0] == "turned-180"
    assert displayed_without_clicks(stored, {}) is None


@pytest.fixture(scope="module")
def case(sample_ct):
    """A realistic simulated AP case of the sample CT (bone dark, 512 px), T10 in the middle, named clicks."""
    return simulated_ap_case(sample_ct, 2468, "T10", 5)


def _after_spatial(sample_ct, pixels, uv_px, labels, geometry, drr_cache_dir):
    """(logic, state): the pipeline run to the polarity at the clicks (the spatial stage) on ``pixels``."""
    ct, _, centroids = sample_ct
    xray = XrayImage(pixels.astype(np.float32).copy(), geometry.intrinsics, geometry.sod_mm, True, "test")
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, Landmarks2D(list(labels), uv_px),
                          RegistrationParameters(cache_dir=drr_cache_dir))
    logic.run_through(state, "spatial")
    return logic, state


@pytest.fixture(scope="module")
def as_acquired(sample_ct, case, drr_cache_dir):
    """``_after_spatial`` of the case as acquired, its named clicks (read only: a test that runs on copies it)."""
    sim, geometry = case
    return _after_spatial(sample_ct, sim.pixels, sim.clicks.uv_px, sim.clicks.labels, geometry, drr_cache_dir)


def _judged(state, rivals, names_follow_clicks=True):
    """Judge ``rivals`` at the clicks' poses of ``state`` (after the spatial stage; nothing in it changes)."""
    p, a = state.parameters, state.appearance
    ctx = FitContext(state.pyramid.level(p.refine_coarse.mu_spacing_mm), state.geometry, state.xray_line_integral,
                     state.mask, 0.0, 0.0, p.fine, p.refine_coarse, p.magnification_range, p.depth_far_mm,
                     p.depth_step_mm)
    contexts = {o: oriented_context(ctx, o) for o in rivals}
    return orientation_at_clicks(contexts, state.click_polarity.registered[a.polarity], state.xray.size_px,
                                 p.identify.rule, names_follow_clicks=names_follow_clicks)


@pytest.mark.slow
def test_at_the_clicks_poses_a_display_as_acquired_leads_and_an_upside_down_one_is_told(sample_ct, case,
                                                                                       as_acquired, drr_cache_dir):
    """As acquired, the stored display leads at the clicks' poses and the turn cannot fit the named clicks. Turned
    180 degrees, the named clicks run head-down and are refused before any stage (``preflight.head_down``); unnamed,
    the turn is registered and leads by the refusal's margin."""
    sim, geometry = case
    labels, uv = sim.clicks.labels, sim.clicks.uv_px
    shown = _judged(as_acquired[1], ("mirrored-left-right", "turned-180"))
    assert shown.scores["as-stored"] >= max(shown.scores["mirrored-left-right"],
                                            np.nan_to_num(shown.scores["turned-180"], nan=-1.0)) \
        + CLEAR_ORIENTATION_AT_CLICKS_GC
    assert not shown.fitted["turned-180"]  # named clicks upside down: no C-arm pose puts T9 below T11

    turned_uv = orient_uv(uv, "turned-180", (512, 512))
    with pytest.raises(LandmarkError, match="named X-ray clicks run head-down .* --orient-xray turned-180"):
        _after_spatial(sample_ct, sim.pixels[::-1, ::-1], turned_uv, labels, geometry, drr_cache_dir)  # named
    _, turned = _after_spatial(sample_ct, sim.pixels[::-1, ::-1], turned_uv, [None] * len(labels), geometry,
                               drr_cache_dir)
    upside_down = _judged(turned, ("mirrored-left-right", "turned-180"), names_follow_clicks=False)
    assert upside_down.fitted["turned-180"]
    assert upside_down.scores["turned-180"] >= upside_down.scores["as-stored"] + REFUSE_ORIENTATION_AT_CLICKS_GC


@pytest.mark.slow
def test_judging_the_orientation_again_on_the_same_image_registers_nothing_again(as_acquired, monkeypatch):
    """The levels stage judges the orientation again with its winner added: the labellings the spatial stage already
    registered on each rival are reused (a registration is seeded: the same inputs give the same fit), so the
    second judgement, with nothing added, registers nothing and finds the same evidence."""
    import carmreg.logic.registration.click_orientation as click_orientation

    logic, state = copied(as_acquired[1])
    a = state.appearance
    first = dict(a.orientation_at_clicks)
    memo = state.turned_fits[(a.polarity, a.storage)]
    assert len(memo) == len(first["labels"]) * (len(first["scores"]) - 1)  # every judged labelling, every rival
    calls = []
    real = click_orientation._registered_turned
    monkeypatch.setattr(click_orientation, "_registered_turned", lambda *args: calls.append(args) or real(*args))
    logic._appearance._orientation_at_clicks(state, "spatial")
    assert calls == []
    assert repr(a.orientation_at_clicks) == repr(first)  # nan (an orientation nothing could be fitted on) too

    logic.run_stage(state, "database")  # a re-run of the spatial stage starts afresh
    assert state.turned_fits == {}


def test_only_a_refusal_at_the_clicks_on_the_stored_images_verdict_may_be_judged_again_with_the_levels_winner():
    """``AppearanceChecks._refused_at_clicks``: report case 99's intensifier image (correctly displayed, T9-T11
    clicked) was refused at the clicks on its leaders T6-T8 and T8-T10 (as stored 0.318, mirrored 0.425); the
    levels' winner may overrule that refusal, never the database's nor the mirror's polarity verdict."""
    fitted = {"as-stored": True, MIRROR: True, "flipped-up-down": True}
    at_clicks = {"scores": {"as-stored": 0.318, MIRROR: 0.425, "flipped-up-down": 0.379}, "fitted": fitted}
    a = _appearance()
    a.set_orientation({"as-stored": 0.409, MIRROR: 0.444, "flipped-up-down": 0.465})  # the database: unclear
    assert not AppearanceChecks._refused_at_clicks(a)  # taken as stored: nothing refused
    a.set_orientation_at_clicks(at_clicks)
    assert a.orientation == MIRROR and AppearanceChecks._refused_at_clicks(a)
    by_database = _appearance()
    by_database.set_orientation({"as-stored": 0.30, MIRROR: 0.30 + REFUSE_ORIENTATION_GC})
    by_database.set_orientation_at_clicks(at_clicks)
    assert by_database.orientation == MIRROR and not AppearanceChecks._refused_at_clicks(by_database)
    on_mirror = _appearance()
    on_mirror.set_orientation({"as-stored": 0.409, MIRROR: 0.444})
    on_mirror.set_orientation_at_clicks(at_clicks)
    on_mirror.decided_by = f"image ({REFINED_ON_MIRROR})"
    assert not AppearanceChecks._refused_at_clicks(on_mirror)


def test_a_close_call_is_a_lead_either_way_under_the_limit_among_fittable_rivals():
    """``close_call``: report case 99's two displays judged on wrong leaders (clear as stored by 0.066, refused by
    0.107) are close calls; a lead of 0.15 or more either way is not; rivals that could not fit the clicks (nan,
    None) do not count."""
    assert close_call({"as-stored": 0.425, MIRROR: 0.325, "turned-180": 0.359})
    assert close_call({"as-stored": 0.318, MIRROR: 0.425, "flipped-up-down": 0.379})
    assert not close_call({"as-stored": 0.60, MIRROR: 0.60 - CLOSE_ORIENTATION_AT_CLICKS_GC})
    assert not close_call({"as-stored": 0.30, MIRROR: 0.30 + CLOSE_ORIENTATION_AT_CLICKS_GC + 0.001})
    assert not close_call({"as-stored": 0.40, MIRROR: float("nan"), "turned-90": None})


def test_a_display_is_taken_from_the_other_polarity_only_by_a_fitted_rival_leading_the_taken_gc_clearly():
    """``displayed_under_other_polarity``, each part deciding: a fitted rival leading the stored image's GC under the
    polarity taken by ``REFUSE_ORIENTATION_AT_CLICKS_GC`` is the display (stop 53's case 353: the mirror as bone dark
    0.865, the stored image as bone bright 0.348); a lead just under it, an unfitted rival or one the clicks could
    not be fitted on (nan) is not; the stored image's own GC under the other polarity never counts."""
    def judged(scores: dict, fitted: dict) -> ClickOrientation:
        return ClickOrientation([["T8", "T9", "T10"]], scores, {o: 2.0 for o in scores}, fitted)

    fitted = {"as-stored": True, MIRROR: True, "turned-270": False}
    case353 = judged({"as-stored": 0.233, MIRROR: 0.865, "turned-270": float("nan")}, fitted)
    assert displayed_under_other_polarity(case353, 0.348) == MIRROR
    just_under = judged({"as-stored": 0.233, MIRROR: 0.348 + REFUSE_ORIENTATION_AT_CLICKS_GC - 0.001}, fitted)
    assert displayed_under_other_polarity(just_under, 0.348) is None
    assert displayed_under_other_polarity(judged({"as-stored": 0.2, MIRROR: 0.9}, {**fitted, MIRROR: False}),
                                          0.348) is None
    assert displayed_under_other_polarity(judged({"as-stored": 0.9, MIRROR: float("nan")}, fitted), 0.348) is None


@pytest.fixture(scope="module")
def mirrored_names_one_level_off(tmp_path_factory, drr_cache_dir):
    """Stop 53's unseen appearance-benchmark scene 353 (chest CT, the independent simulator): an intensifier image
    shown mirrored left-right, bone dark, 16-bit PNG, T9-T11 clicked and named one level off (T8-T10). As stored, bone
    bright leads at the clicks by 0.115 (clear) and finds the display as stored clearly; as bone dark the mirror
    reaches GC 0.86 with the clicks fitted."""
    ct, centroids, xray, truth = _benchmark_scene(353, tmp_path_factory.mktemp("mirrored-353"))
    assert truth["clicked"] == ["T9", "T10", "T11"]
    clicks = Landmarks2D(["T8", "T9", "T10"], np.asarray(truth["clicks_uv_px"], float))
    return ct, centroids, xray, clicks, RegistrationParameters(cache_dir=drr_cache_dir)


@pytest.mark.slow
@pytest.mark.benchmark_case
def test_a_mirrored_display_taken_as_stored_under_the_wrong_polarity_is_found_under_the_other(
        mirrored_names_one_level_off):
    """The first verdict at the clicks is clear for the wrong polarity by less than ``CHECKED_CLICKS_GC`` and the
    second opinion without the shading does not confirm it; under it the display looks as stored. Judged under the
    other polarity too, the mirror leads the stored image's GC by far more than ``REFUSE_ORIENTATION_AT_CLICKS_GC``
    with the clicks fitted: the image is taken bone dark and mirrored, refused, so no level answer can be
    confident (stop 53 named it one level off, ambiguous only by its margin)."""
    ct, centroids, xray, clicks, params = mirrored_names_one_level_off
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, clicks, params)
    logic.run_through(state, "spatial")
    a = state.appearance
    first = a.scores["at_clicks"]["scores"]
    assert first["bone-bright"] - first["bone-dark"] >= 0.10  # the first verdict: bone bright, clearly
    other = a.scores["other_polarity_at_clicks"]
    assert other["fitted"][MIRROR] and other["scores"][MIRROR] >= first["bone-bright"] + 0.3
    assert (a.polarity, a.orientation, a.clear, a.trusted) == ("bone-dark", MIRROR, False, False)
    assert a.decided_by == f"image ({REFINED_WITH_ORIENTATION})"
    assert np.allclose(state.xray_line_integral, attenuation(xray.pixels, state.mask, True, a.storage))
    assert "displayed mirrored left right" in a.note
