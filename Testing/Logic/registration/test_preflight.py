"""The input rules every front door shares (``registration.preflight``): named clicks that run head-down, and clicks
(named or not) that run across the image."""

from __future__ import annotations

import numpy as np
import pytest

from carmreg.logic.errors import LandmarkError
from carmreg.logic.image.turn import orient_uv
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D
from carmreg.logic.registration.preflight import QUARTER_TURN_DEG, across, head_down, preflight

CT = Landmarks3D(["T11", "T12", "L1"], [[0.0, 0.0, 30.0], [0.0, 0.0, 0.0], [0.0, 0.0, -30.0]])
DOWN_THE_IMAGE = [[300.0, 200.0], [305.0, 300.0], [312.0, 400.0]]  # (column, row): rows grow down the image


@pytest.mark.parametrize("uv, expected", [
    (DOWN_THE_IMAGE, None),                                         # head up, as acquired
    (DOWN_THE_IMAGE[::-1], ("T11", "L1")),                          # turned 180 degrees or flipped up-down
    ([[200.0, 300.0], [300.0, 305.0], [400.0, 312.0]], None),       # a quarter turn: ``across``'s
])
def test_named_clicks_run_head_down_only_when_the_head_lies_clearly_below_the_sacrum(uv, expected):
    assert head_down(Landmarks2D(["T11", "T12", "L1"], uv)) == expected


def test_the_head_down_bound_is_120_degrees_from_the_image_down():
    """d = uv_caudal - uv_cranial at 115 and 125 degrees from +row: only the second runs head-down."""
    def at(degrees):
        d = 100.0 * np.array([np.sin(np.radians(degrees)), np.cos(np.radians(degrees))])
        return Landmarks2D(["T11", "L1"], [[300.0, 300.0], list(np.array([300.0, 300.0]) + d)])
    assert head_down(at(115.0)) is None and head_down(at(125.0)) == ("T11", "L1")


def test_preflight_refuses_head_down_names_with_the_turn_that_shows_them_head_up_and_leaves_unnamed_clicks_alone():
    refused = preflight(CT, Landmarks2D(["T11", "T12", "L1"], DOWN_THE_IMAGE[::-1]))
    assert refused.problems == [refused.problems[0]] and refused.kinds == [LandmarkError]
    assert "run head-down (T11 lies below L1 on the image)" in refused.problems[0]
    assert "--orient-xray turned-180" in refused.problems[0] and "or the names are reversed" in refused.problems[0]
    with pytest.raises(LandmarkError, match="run head-down"):
        refused.raise_first()
    assert preflight(CT, Landmarks2D([None, None, None], DOWN_THE_IMAGE[::-1])).problems == []
    assert preflight(CT, Landmarks2D(["T11", "T12", "L1"], DOWN_THE_IMAGE)).problems == []
    partly = preflight(CT, Landmarks2D(["T11", None, "L1"], DOWN_THE_IMAGE[::-1]))
    assert partly.mode == "partly_named" and "(top of the image = head)" in partly.problems[0]  # the labellings' rule


NAMES = ["T11", "T12", "L1"]
SIZE_PX = (512, 600)  # (columns, rows)


def _at(degrees: float, centre=(300.0, 300.0)) -> list:
    """Three clicks 100 px apart along a line ``degrees`` from the image's down (+row), toward +column."""
    d = np.array([np.sin(np.radians(degrees)), np.cos(np.radians(degrees))])
    return [list(np.asarray(centre) + 100.0 * k * d) for k in (-1, 0, 1)]


@pytest.mark.parametrize("stored_as, turn_back", [("turned-90", "turned-270"), ("turned-270", "turned-90")])
def test_named_clicks_of_a_display_turned_a_quarter_are_refused_with_the_turn_that_shows_them_head_up(
        stored_as, turn_back):
    """The clicks of an acquisition shown head up, as a display turned a quarter stores them: refused before any stage,
    naming the turn that undoes it; that turn brings them back where the acquisition shows them."""
    stored = orient_uv(np.array(DOWN_THE_IMAGE), stored_as, SIZE_PX)
    found = across(CT, Landmarks2D(NAMES, stored))
    assert found is not None and found.turn == turn_back and found.levels == ("T11", "L1")
    shuffled = across(CT, Landmarks2D(NAMES[::-1], stored[::-1]))  # the same clicks listed sacrum first
    assert (shuffled.turn, shuffled.levels) == (turn_back, ("T11", "L1"))
    assert found.angle_deg > 80.0
    np.testing.assert_allclose(orient_uv(stored, turn_back, SIZE_PX[::-1]), DOWN_THE_IMAGE)
    problem = preflight(CT, Landmarks2D(NAMES, stored)).problems
    assert len(problem) == 1 and problem[0].startswith("the X-ray clicks run across the image (")
    assert f"--orient-xray {turn_back}" in problem[0] and "degrees from the course T11-L1 takes in the CT" in problem[0]


def test_unnamed_clicks_across_the_image_are_refused_naming_both_quarter_turns():
    stored = orient_uv(np.array(DOWN_THE_IMAGE), "turned-90", SIZE_PX)
    found = across(CT, Landmarks2D([None] * 3, stored))
    assert found is not None and found.turn is None
    problem = preflight(CT, Landmarks2D([None] * 3, stored)).problems
    assert len(problem) == 1 and "--orient-xray turned-90 or turned-270" in problem[0]
    assert "so that the head is at the top" in problem[0]


def test_the_quarter_turn_bound_is_45_degrees_from_the_course_of_the_ct_levels():
    """Clicks 44 and 46 degrees from the course of straight CT levels, leaning either way: only at 46 they run
    across."""
    assert QUARTER_TURN_DEG == 45.0
    for named in (NAMES, [None] * 3):
        for sign in (1.0, -1.0):
            assert across(CT, Landmarks2D(named, _at(sign * 44.0))) is None
            found = across(CT, Landmarks2D(named, _at(sign * 46.0)))
            assert found is not None and found.angle_deg == pytest.approx(46.0, abs=1e-6)


def test_clicks_along_a_bent_spine_are_judged_against_that_spine_mirrored_either_way():
    """A scoliotic run leaning 55 degrees in the CT, clicked leaning 55 degrees either way (the display mirrored or
    not): along its course, not across; the same clicks against a straight CT run across it. Unnamed clicks meet
    every run of adjacent CT levels and are judged against the nearest."""
    lean = np.radians(55.0)
    bent = Landmarks3D(["T10", "T11", "T12", "L1"], [[-30.0 * np.sin(lean) * k, 0.0, -30.0 * np.cos(lean) * k]
                                                     for k in range(4)])
    for sign in (1.0, -1.0):
        uv = [[300.0 + sign * 100.0 * np.sin(lean) * k, 200.0 + 100.0 * np.cos(lean) * k] for k in range(3)]
        assert across(bent, Landmarks2D(["T11", "T12", "L1"], uv)) is None
        assert across(bent, Landmarks2D([None] * 3, uv)) is None
        assert across(CT, Landmarks2D(NAMES, uv)) is not None


def test_clicks_that_do_not_lie_along_a_line_are_not_judged():
    """Three clicks at the corners of an equilateral triangle have no axis: the image's own checks judge them."""
    triangle = [[300.0, 200.0], [400.0, 200.0], [350.0, 200.0 + 50.0 * np.sqrt(3.0)]]
    assert across(CT, Landmarks2D([None] * 3, triangle)) is None


def test_clicks_off_the_image_are_left_to_the_check_that_names_them():
    """A click typed off the image (a sign lost) makes the clicks run across; given the image's size, preflight leaves
    them to ``check_landmarks``, whose message names the click."""
    off = [[-40.0, 20.0], *DOWN_THE_IMAGE[1:]]
    assert across(CT, Landmarks2D(NAMES, off)) is not None
    assert preflight(CT, Landmarks2D(NAMES, off), xray_size_px=SIZE_PX).problems == []
    assert preflight(CT, Landmarks2D(NAMES, off)).problems[0].startswith("the X-ray clicks run across the image")
