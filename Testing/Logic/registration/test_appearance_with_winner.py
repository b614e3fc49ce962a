"""The levels' winner judging the X-ray's appearance again (``appearance_checks.with_winner``), on a case of the
appearance benchmark whose clicks' leading labellings were all wrong."""

import pytest
from appearance_cases import appearance_case_registrar

from carmreg.logic.registration.click_orientation import MIRROR
from carmreg.logic.registration.click_polarity import CLEAR_WITH_WINNER_GC


@pytest.fixture(scope="module")
def clicked_case(tmp_path_factory):
    """``registered(case, variant)`` with the case's unnamed clicks (``appearance_case_registrar``)."""
    return appearance_case_registrar(tmp_path_factory, "winner-cache", with_clicks=True)


@pytest.mark.slow
def test_a_refusal_at_the_clicks_on_wrong_leaders_is_overruled_by_the_levels_winner(clicked_case):
    """Report case 99 (the chest CT, T9-T11 clicked), its intensifier image correctly displayed, bone dark, log
    storage, 16-bit PNG. The clicks' spacing led with T6-T8 and T8-T10, neither right: at their poses the mirror led
    the stored image by over 0.10 GC and the display was refused (stop 32, before: ambiguous, no level named). The
    contest's winner T9-T11 is judged too: as stored it leads every rival orientation by ``CLEAR_WITH_WINNER_GC``,
    so the display is taken as stored, clearly, and the right names are confident."""
    logic, state, truth = clicked_case(99, "ii-dark-log-png")
    a = state.appearance
    assert a.orientation == MIRROR and a.polarity == "bone-dark"  # refused on the leaders' evidence
    assert truth["clicked"] not in a.orientation_at_clicks["labels"]
    logic.run_stage(state, "levels")
    ident, a = state.identification, state.appearance
    assert list(ident.winner.labels) == list(truth["clicked"])
    scores = a.orientation_at_clicks["scores"]
    assert truth["clicked"] in a.orientation_at_clicks["labels"]
    assert scores["as-stored"] - max(v for k, v in scores.items() if k != "as-stored") >= CLEAR_WITH_WINNER_GC
    assert (a.orientation, a.orientation_clear, a.trusted) == ("as-stored", True, True)
    assert ident.status == "confident"
