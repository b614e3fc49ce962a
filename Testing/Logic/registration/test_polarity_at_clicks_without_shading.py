"""With clicks, the second opinion on the polarity (``appearance_checks._polarity_at_clicks_without_shading``), on
tune cases of the appearance benchmark (the second CT): a clear verdict without the image's shading that names the
other polarity is used, never clear; none is asked when the clicks' verdict is clear."""

import sys
from pathlib import Path

import numpy as np
import pytest

from carmreg.logic.image.appearance import CLEAR_CLICKS_GC, REFINED_AT_CLICKS_WITHOUT_SHADING
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray import load_xray
from carmreg.logic.registration.pipeline import CarmRegLogic
from carmreg.logic.registration.state import RegistrationParameters


@pytest.fixture(scope="module")
def tune_case(tmp_path_factory):
    """``registered(case, variant)``: (logic, the state after the spatial stage) of that tune case and variant with
    its unnamed clicks (a cache of their own); skipped without ../shared (the second CT)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "Benchmarks"))
    import appearance as app
    import bench_appearance as bench

    maker = bench.CaseMaker(second_ct=True)
    if "abdomen" not in maker.cts:
        pytest.skip("the second CT (../shared) is not here")
    (ct, _, centroids), _, _ = maker.cts["abdomen"]
    params = RegistrationParameters(cache_dir=str(tmp_path_factory.getbasetemp() / "clicks-shading-cache"))

    def registered(case: int, variant_name: str):
        variant = app.VARIANTS[variant_name]
        record = bench.write_variant(maker.scenes(case, {variant.detector})[variant.detector], variant, case,
                                     tmp_path_factory.mktemp(variant_name))
        detector = app.DETECTORS[variant.detector]
        xray = load_xray(record["xray"], sdd_mm=detector.sdd_mm, pixel_spacing_mm=detector.pixel_mm)
        uv_px = np.asarray(record["truth"]["clicks_uv_px"], float)
        logic = CarmRegLogic()
        state = logic.prepare(ct, centroids, xray, Landmarks2D([None] * len(uv_px), uv_px), params)
        for stage in ("database", "spatial"):
            logic.run_stage(state, stage)
        return logic, state, record["truth"]

    return registered


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
