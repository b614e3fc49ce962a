"""The input rules every front door shares (``registration.preflight``): named clicks that run head-down."""

from __future__ import annotations

import numpy as np
import pytest

from carmreg.logic.errors import LandmarkError
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D
from carmreg.logic.registration.preflight import head_down, preflight

CT = Landmarks3D(["T11", "T12", "L1"], [[0.0, 0.0, 30.0], [0.0, 0.0, 0.0], [0.0, 0.0, -30.0]])
DOWN_THE_IMAGE = [[300.0, 200.0], [305.0, 300.0], [312.0, 400.0]]  # (column, row): rows grow down the image


@pytest.mark.parametrize("uv, expected", [
    (DOWN_THE_IMAGE, None),                                         # head up, as acquired
    (DOWN_THE_IMAGE[::-1], ("T11", "L1")),                          # turned 180 degrees or flipped up-down
    ([[200.0, 300.0], [300.0, 305.0], [400.0, 312.0]], None),       # a quarter turn: the image's own check
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
