"""With clicks, the second opinion on the polarity (``appearance_checks._polarity_at_clicks_without_shading``), on
tune cases of the appearance benchmark (the second CT): a clear verdict without the image's shading that names the
other polarity is used, never clear; none is asked when the clicks' verdict is clear."""

import pytest
from appearance_cases import appearance_case_registrar

from carmreg.logic.image.appearance import CLEAR_CLICKS_GC, REFINED_AT_CLICKS_WITHOUT_SHADING


@pytest.fixture(scope="module")
def tune_case(tmp_path_factory):
    """``registered(case, variant)``: (logic, the state after the spatial stage, truth) with its unnamed clicks."""
    return appearance_case_registrar(tmp_path_factory, "clicks-shading-cache", with_clicks=True)


@pytest.mark.slow
def test_a_large_patient_taken_bone_dark_at_the_clicks_is_put_right_without_its_shading_but_never_clear(tune_case):
    """Case 92's large patient (the second CT), stored bone bright in a 16-bit TIFF, three unnamed clicks. Stop 31:
    at the clicks bone dark by an unclear 0.032 (0.356 against 0.324); without the shading above 20 mm bone bright,
    0.523 against 0.167. Its polarity is used, not clear, and the levels stage registers on the image as stored
    converted bone bright: the right labelling wins (it had been L1-L3, bone dark), ambiguous."""
    logic, state, truth = tune_case(92, "fp-bright-large-tiff")
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


@pytest.mark.slow
def test_no_second_opinion_is_asked_when_the_clicks_tell_the_polarity_clearly(tune_case):
    """Case 86's flat panel, stored bone dark as linear intensity (DICOM): clear at the clicks, nothing more asked."""
    _, state, _ = tune_case(86, "fp-dark-linear-dcm")
    a = state.appearance
    assert (a.polarity, a.clear) == ("bone-dark", True) and "at_clicks_without_shading" not in a.scores
