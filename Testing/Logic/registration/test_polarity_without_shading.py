"""Without clicks, the second opinion on the polarity (``appearance_checks._polarity_without_shading``), on tune cases
of the appearance benchmark (the second CT): where it disagrees with the first verdict it is used, never clear; where it
agrees, nothing changes."""

import pytest
from second_ct_cases import second_ct_registrar

from carmreg.logic.image.appearance import CLEAR_REFINED_GC, REFINED_WITHOUT_SHADING, WITHOUT_SHADING_MM


@pytest.fixture(scope="module")
def tune_case(tmp_path_factory):
    """``registered(case, variant)``: (logic, the state after the spatial stage, truth) without clicks."""
    return second_ct_registrar(tmp_path_factory, "shading-cache", with_clicks=False)


@pytest.mark.slow
def test_a_wrong_unclear_verdict_is_put_right_by_the_image_without_its_shading_but_never_clear(tune_case):
    """Case 32 (a view tilted 9.3 and 7.8 degrees out of the image plane), its intensifier image, bone dark, log
    storage, 16-bit PNG. Stop 29: the first verdict bone bright, 0.413 against 0.355; the second opinion bone dark,
    0.763 against 0.314. Its polarity is used, not clear: no level answer can be proposed on it."""
    logic, state, _ = tune_case(32, "ii-dark-log-png")
    a = state.appearance
    first, second = a.scores["without_clicks"]["scores"], a.scores["without_clicks_without_shading"]["scores"]
    assert first["bone-bright"] > first["bone-dark"] > first["bone-bright"] - CLEAR_REFINED_GC  # wrong, unclear
    assert second["bone-dark"] >= second["bone-bright"] + CLEAR_REFINED_GC  # right, by far
    assert (a.polarity, a.clear, a.decided_by) == ("bone-dark", False, f"image ({REFINED_WITHOUT_SHADING})")
    assert "found only from the image without its shading above 20 mm" in a.note and not a.trusted
    assert a.scores["without_clicks_without_shading"]["without_shading_mm"] == WITHOUT_SHADING_MM
    assert any(w.startswith("X-ray polarity: bone-dark, found only") for w in state.warnings)
    assert state.known_gc is not None  # bone dark: the spatial stage's map is the plain image's, as computed
    # the levels stage compares the images the same way, reusing the second opinion's bone-dark refinements
    checked = state.image_polarity
    assert checked.without_shading_mm == WITHOUT_SHADING_MM
    reused = {id(f.refine) for _, f in checked.pairs("bone-dark")}
    logic.run_stage(state, "levels")
    ident = state.identification
    assert len(reused) == 3 and reused & {id(f.refine) for f in ident.fits}  # copies share the refinement
    assert ident.status == "ambiguous" and any("appearance" in r for r in ident.reasons)  # never proposed


@pytest.mark.slow
def test_a_second_opinion_that_agrees_changes_nothing(tune_case):
    """Case 26's large patient, stored bone bright (stop 29: the first verdict bone dark, 0.572 against 0.362,
    unclear; the second opinion bone dark too, 0.375 against 0.293): recorded, the appearance as it was."""
    _, state, _ = tune_case(26, "fp-bright-large-tiff")
    a = state.appearance
    second = a.scores["without_clicks_without_shading"]["scores"]
    assert second["bone-dark"] > second["bone-bright"]
    assert (a.polarity, a.clear, a.decided_by) == ("bone-dark", False, "image (refined)")
    assert state.image_polarity.without_shading_mm == 0.0
