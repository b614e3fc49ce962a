"""The levels contest run again under the other polarity (``AppearanceChecks.contest_under_other_polarity``): when
the polarity stayed unclear at the clicks and the contest's winner, not among the labellings it was judged on,
explains the image poorly, on a case of the appearance benchmark whose polarity had been judged on wrong labellings
only (report case 205, chest, T10-T12 clicked, the 10th most plausible of 11 labellings by click spacing), and on
one where it must change nothing but its record (report case 201's mirrored display). A winner the polarity was
judged on gets no second contest: ``test_polarity_at_clicks_without_shading`` (case 92)."""

import json

import pytest
from appearance_cases import appearance_case_registrar

from carmreg.logic.errors import CancelledError
from carmreg.logic.registration.level_confidence import ConfidenceRule


@pytest.fixture(scope="module")
def clicked_case(tmp_path_factory, drr_cache_dir):
    """``registered(case, variant)`` with the case's unnamed clicks (``appearance_case_registrar``)."""
    return appearance_case_registrar(tmp_path_factory, drr_cache_dir, with_clicks=True)


def _appearance_json(appearance) -> str:
    return json.dumps(appearance.as_dict(), sort_keys=True, default=str)


def _levels_watching_the_second_contest(logic, state, cancel: bool) -> dict:
    """The levels stage run, noting what the appearance in use, its polarity evidence, the warnings and the converted
    X-ray were as the second contest starts (its progress message; empty if it never does). ``cancel``: a cancel
    asked right then, so that the ``CancelledError`` the stage must end with comes from inside that contest."""
    kept = {}

    def progress(stage, fraction, message):
        if "the contest again as" in message:
            kept.update(appearance=_appearance_json(state.appearance), click_polarity=state.click_polarity,
                        warnings=list(state.warnings), xray=state.xray_line_integral)
            if cancel:
                logic.cancel()  # raised at the next check: inside the second contest's first registration

    logic.progress = progress
    try:
        if cancel:
            with pytest.raises(CancelledError):
                logic.run_stage(state, "levels")
        else:
            logic.run_stage(state, "levels")
    finally:
        logic.progress = None
    return kept


@pytest.mark.slow
def test_a_polarity_judged_on_wrong_labellings_is_put_right_by_the_contest_under_the_other(clicked_case):
    """Case 205's intensifier image, bone dark, log storage, 16-bit PNG, unnamed clicks: judged at the clicks on
    T4-T6 ... T8-T10 (all wrong) it is taken bone bright, unclear; the contest on the inverted image is won by T1-T3
    under the image floor (stop 41: ambiguous, the polarity wrong). Run again as bone dark, T10-T12 wins and,
    judged at the clicks too, confirms bone dark: the answer is right and confident, and both contests are
    recorded. A cancel inside the second contest first leaves the appearance, its evidence, the warnings and the
    converted X-ray as they were when it started (``_all_or_nothing``), and the stage run again then gives that
    answer."""
    logic, state, truth = clicked_case(205, "ii-dark-log-png")
    a = state.appearance
    assert (a.polarity, a.clear, a.orientation) == ("bone-bright", False, "as-stored")
    assert list(truth["clicked"]) not in [list(lb) for lb in state.click_polarity.labels]
    kept = _levels_watching_the_second_contest(logic, state, cancel=True)
    assert kept, "the second contest never started"
    assert _appearance_json(state.appearance) == kept["appearance"]
    assert state.appearance.polarity == "bone-bright" and state.xray_line_integral is kept["xray"]
    assert state.click_polarity is kept["click_polarity"] and state.warnings == kept["warnings"]
    assert "contest_under_other_polarity" not in state.appearance.scores
    logic.run_stage(state, "levels")
    a, ident = state.appearance, state.identification
    record = a.scores["contest_under_other_polarity"]
    assert record["first"]["polarity"] == "bone-bright" and record["first"]["gc"] < ConfidenceRule().min_similarity
    assert record["first"]["winner"] != list(truth["clicked"]) and record["taken"]
    assert (a.polarity, a.trusted) == ("bone-dark", True)
    assert list(ident.winner.labels) == list(truth["clicked"]) and ident.status == "confident"
    assert ident.winner.similarity > 0.6
    assert not any(w.startswith("X-ray polarity:") for w in state.warnings)


@pytest.mark.slow
def test_a_contest_under_the_other_polarity_that_does_not_confirm_it_changes_nothing_but_its_record(clicked_case):
    """Case 201's mirrored display (chest, T7-T9 clicked, unnamed): bone dark, unclear at the clicks; the contest's
    winner, T4-T6, explains the image poorly (stop 42: GC 0.34). Run again as bone bright, T11-L1 wins at about 0.16
    and bone bright is not confirmed: the first answer (ambiguous), the appearance, its evidence and the converted
    X-ray stay as they were when the second contest started, the appearance recording both contests, not taken."""
    logic, state, truth = clicked_case(201, "ii-dark-mirrored-png")
    kept = _levels_watching_the_second_contest(logic, state, cancel=False)
    assert kept, "the second contest never started"
    a, ident = state.appearance, state.identification
    record = a.scores.pop("contest_under_other_polarity")
    polarities = (record["first"]["polarity"], record["again"]["polarity"])
    assert not record["taken"] and polarities == ("bone-dark", "bone-bright")
    assert _appearance_json(a) == kept["appearance"] and (a.polarity, a.clear) == ("bone-dark", False)
    assert state.xray_line_integral is kept["xray"] and state.click_polarity is kept["click_polarity"]
    assert list(ident.winner.labels) == record["first"]["winner"] != list(truth["clicked"])
    assert ident.status == "ambiguous" and state.warnings == [*kept["warnings"], ident.message]
