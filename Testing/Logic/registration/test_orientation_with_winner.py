"""A trusted display orientation judged again at the clicks with the contest's winner when the orientation check
had not judged it (``appearance_checks._orientation_with_winner``), on cases of the appearance benchmark (the chest
CT; unnamed clicks)."""

import pytest
from appearance_cases import appearance_case_registrar

import carmreg.logic.registration.click_orientation as click_orientation
from carmreg.logic.image.appearance import REFUSE_ORIENTATION_AT_CLICKS_GC
from carmreg.logic.registration.click_orientation import MIRROR


@pytest.fixture(scope="module")
def clicked_case(tmp_path_factory):
    """``registered(case, variant)`` with the case's unnamed clicks (``appearance_case_registrar``)."""
    return appearance_case_registrar(tmp_path_factory, "with-winner-cache", with_clicks=True)


def _judged(a) -> list:
    return [list(lb) for lb in a.orientation_at_clicks["labels"]]


@pytest.mark.slow
def test_a_correct_display_judged_on_wrong_leaders_stays_trusted_with_the_winner_judged_too(clicked_case):
    """Report case 109's intensifier image, bone dark, log storage, 16-bit PNG, T7-T9 clicked: the orientation was
    judged on T5-T7 and T8-T10 (stored 0.70, the mirror 0.44). The contest's winner T7-T9 is judged too: about
    0.87 as stored, still clear; the answer is confident and right."""
    logic, state, truth = clicked_case(109, "ii-dark-log-png")
    a = state.appearance
    assert a.trusted and truth["clicked"] not in _judged(a)
    before = dict(a.orientation_at_clicks["scores"])
    logic.run_stage(state, "levels")
    a, ident = state.appearance, state.identification
    assert list(ident.winner.labels) == list(truth["clicked"]) and ident.status == "confident"
    assert _judged(a)[-1] == list(truth["clicked"]) and a.trusted
    scores = a.orientation_at_clicks["scores"]
    assert scores["as-stored"] > before["as-stored"] + 0.1 and scores["as-stored"] - scores[MIRROR] > 0.3


@pytest.mark.slow
def test_a_mirrored_display_clear_as_stored_on_wrong_leaders_is_refused_once_the_right_winner_is_judged(
        clicked_case, monkeypatch):
    """Report case 99's mirrored display (T9-T11 clicked), without stop 32's close call: on its leaders T6-T8 and
    T8-T10 alone the stored image leads, 0.425 against 0.359 turned and 0.325 mirrored, clear. Were the contest's
    winner T9-T11, judging it too puts the mirror about 0.82 ahead: refused, not trusted, so no confident name."""
    monkeypatch.setattr(click_orientation, "CLOSE_ORIENTATION_AT_CLICKS_GC", 0.0)
    logic, state, truth = clicked_case(99, "ii-dark-mirrored-png")
    a = state.appearance
    assert a.trusted and truth["clicked"] not in _judged(a)
    logic.run_stage(state, "levels")
    assert state.identification.status != "confident"
    right = next(f for f in state.identification.fits if list(f.labels) == list(truth["clicked"]))
    assert not logic._appearance.with_winner(state, right)
    a = state.appearance
    scores = a.orientation_at_clicks["scores"]
    assert _judged(a)[-1] == list(truth["clicked"])
    assert scores[MIRROR] - scores["as-stored"] >= REFUSE_ORIENTATION_AT_CLICKS_GC
    assert a.orientation == MIRROR and not a.trusted
