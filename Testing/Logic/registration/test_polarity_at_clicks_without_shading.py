"""With clicks, the second opinion on the polarity (``appearance_checks._polarity_at_clicks_without_shading``), on
cases of the appearance benchmark (the second CT): a clear verdict without the image's shading that names the
other polarity is used, never clear; one that agrees with a polarity still unclear has the mirror judged without
the shading too (``_polarity_on_displays``); none is asked when the clicks' verdict is clear by ``CHECKED_CLICKS_GC``
or the file states its polarity, and a clear verdict by less is asked too. Case 92 also shows that a winner the
polarity was judged on gets no second contest under the other polarity (stop 42,
``AppearanceChecks.worth_other_polarity``)."""

import pytest
from appearance_cases import appearance_case_registrar

from carmreg.logic.image.appearance import (
    CHECKED_CLICKS_GC,
    CLEAR_CLICKS_GC,
    MIN_CLICKS_GC,
    REFINED_AT_CLICKS_WITHOUT_SHADING,
)

pytestmark = pytest.mark.benchmark_case  # the tier of benchmark cases (pyproject.toml, scripts/test.sh)


@pytest.fixture(scope="module")
def registered(tmp_path_factory, drr_cache_dir):
    """``registered(case, variant)``: (logic, the state after the spatial stage, truth) with its unnamed clicks."""
    return appearance_case_registrar(tmp_path_factory, drr_cache_dir, with_clicks=True)


@pytest.mark.slow
@pytest.mark.usefixtures("click_spacing_order")
def test_a_large_patient_taken_bone_dark_at_the_clicks_is_put_right_without_its_shading_but_never_clear(registered):
    """Case 92's large patient (the second CT), stored bone bright in a 16-bit TIFF, three unnamed clicks. Stop 31:
    at the clicks bone dark by an unclear 0.032 (0.356 against 0.324); without the shading above 20 mm bone bright,
    0.523 against 0.167. Its polarity is used, not clear, and the levels stage registers on the image as stored
    converted bone bright: the right labelling wins (it had been L1-L3, bone dark), ambiguous."""
    logic, state, truth = registered(92, "fp-bright-large-tiff")
    a = state.appearance
    first = a.scores["at_clicks"]["scores"]
    second = a.scores["at_clicks_without_shading"]["scores"]
    assert first["bone-bright"] < first["bone-dark"] < first["bone-bright"] + CLEAR_CLICKS_GC  # wrong, unclear
    assert second["bone-bright"] >= second["bone-dark"] + CLEAR_CLICKS_GC  # right, clearly
    assert (a.polarity, a.clear, a.decided_by) == ("bone-bright", False, f"image ({REFINED_AT_CLICKS_WITHOUT_SHADING})")
    assert "found only from the image without its shading above 20 mm" in a.note and not a.trusted
    assert any(w.startswith("X-ray polarity: bone-bright, found only") for w in state.warnings)
    logic.run_stage(state, "levels")
    ident = state.identification
    assert ident.winner.labels == list(truth["clicked"])
    assert ident.status == "ambiguous" and any("appearance" in r for r in ident.reasons)
    # under the 0.40 floor (about 0.32), but the polarity was judged at the clicks on this very labelling and left
    # unclear: no second contest under the other polarity (stop 42; run anyway, a wrong labelling, L1-L3, won there
    # above the floor at about 0.44 and bone dark was not confirmed, 5 s spent for nothing)
    assert ident.winner.labels in [list(lb) for lb in state.click_polarity.labels]
    assert "contest_under_other_polarity" not in a.scores and state.appearance is a


@pytest.mark.slow
def test_no_second_opinion_is_asked_of_a_clear_verdict_on_a_file_stating_its_polarity(registered):
    """Case 86's flat panel, stored bone dark as linear intensity, a DICOM file stating its polarity: clear at the
    clicks by 0.207 (stop 35), under ``CHECKED_CLICKS_GC``, and nothing more asked: the file's word and the image's
    clear verdict agree."""
    _, state, _ = registered(86, "fp-dark-linear-dcm")
    a = state.appearance
    assert (a.polarity, a.clear) == ("bone-dark", True) and "at_clicks_without_shading" not in a.scores
    assert state.xray.polarity_stated and a.clarity_gc < CHECKED_CLICKS_GC


@pytest.mark.slow
def test_a_large_patient_clear_at_the_clicks_by_a_small_lead_is_checked_without_its_shading(registered):
    """Report case 155's large patient (the second CT, L4-S1 clicked and named), stored bone bright in a 16-bit TIFF.
    Stop 35: at the clicks bone dark *clearly*, 0.318 against 0.184 with the clicks fitted (a lead of 0.133, short
    of ``CHECKED_CLICKS_GC``); its names stayed ambiguous only because the image agreed by 0.38 < 0.40. Without the
    shading above 20 mm bone bright, 0.649 against 0.166: that polarity is used, never clear, and the levels stage
    proposes no confident answer on it."""
    logic, state, truth = registered(155, "fp-bright-large-tiff", names=["L4", "L5", "S1"])
    assert list(truth["clicked"]) == ["L4", "L5", "S1"]
    a = state.appearance
    first = a.scores["at_clicks"]["scores"]
    second = a.scores["at_clicks_without_shading"]["scores"]
    assert first["bone-dark"] >= MIN_CLICKS_GC and a.scores["at_clicks"]["fits"]["bone-dark"]
    assert first["bone-bright"] + CLEAR_CLICKS_GC <= first["bone-dark"] < first["bone-bright"] + CHECKED_CLICKS_GC
    assert second["bone-bright"] >= second["bone-dark"] + CLEAR_CLICKS_GC  # right, clearly
    assert (a.polarity, a.clear, a.decided_by) == ("bone-bright", False, f"image ({REFINED_AT_CLICKS_WITHOUT_SHADING})")
    assert "the image clearly leaned bone-dark by 0.13" in a.note
    logic.run_stage(state, "levels")
    assert state.identification.status != "confident"


@pytest.mark.slow
def test_a_large_patient_named_one_level_off_is_not_taken_mirrored_on_its_shading(registered):
    """Report case 125's large patient (the second CT, L3-L5 clicked), stored bone bright in a 16-bit TIFF, the
    clicks named one level off (L4, L5, S1). Stop 33: at the clicks bone bright by an unclear 0.047; on the mirror,
    judged with the shading, bone dark by 0.27 and the mirror 0.12 ahead of the image as stored: taken bone dark and
    mirrored (the polarity wrong). Since stop 35 the leader's neighbour L2-L4 is judged at the clicks too: bone dark
    by an unclear 0.043 (0.329 against 0.286). Without the shading bone bright by 0.39, clearly: that polarity is
    used and the mirror judged without the shading too; the image stays as stored, bone bright, never clear; the
    wrong names are never confident."""
    logic, state, truth = registered(125, "fp-bright-large-tiff", names=["L4", "L5", "S1"])
    assert list(truth["clicked"]) == ["L3", "L4", "L5"]
    a = state.appearance
    first = a.scores["at_clicks"]["scores"]
    second = a.scores["at_clicks_without_shading"]["scores"]
    assert first["bone-bright"] < first["bone-dark"] < first["bone-bright"] + CLEAR_CLICKS_GC  # wrong, unclear
    assert second["bone-bright"] >= second["bone-dark"] + CLEAR_CLICKS_GC  # right, clearly
    assert (a.polarity, a.clear, a.orientation) == ("bone-bright", False, "as-stored")
    assert "on_mirror" in a.scores and a.decided_by == f"image ({REFINED_AT_CLICKS_WITHOUT_SHADING})"
    logic.run_stage(state, "levels")
    assert state.identification.status != "confident"
