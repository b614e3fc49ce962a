"""The image agreement the confidence rule judges (``agreement``): the GC of a labelling's pose on the equalised
X-ray, measured once per refinement, recovering what a processed display hides from the converted image."""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage
from simulated_cases import simulated_ap_case

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.volume import MuPyramid
from carmreg.logic.image.field import field_mask
from carmreg.logic.image.prepare import EQUALISED, attenuation
from carmreg.logic.registration.agreement import measure_agreement
from carmreg.logic.registration.fine import FineParameters
from carmreg.logic.registration.image_refine import RefineParameters, RefineResult
from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit, coarse_refine_parameters


def _fit_at(pose: np.ndarray, similarity: float) -> LabellingFit:
    fit = LabellingFit(["T10"], 0, np.zeros((0, 3)), np.zeros((0, 2)))
    fit.refine = RefineResult(np.asarray(pose, float), 0.0, similarity, float("nan"), 1, objective_end=0.5)
    return fit


def _processed_display(pixels: np.ndarray, mask: np.ndarray, pixel_mm: float) -> np.ndarray:
    """A fluoroscopy display of a linear bone-dark image, as the appearance benchmark's processed display makes it
    (written here again): log, dynamic-range compression (0.5 x a 20 mm low-pass taken off), unsharp mask (1.0 at
    3 mm), a 1-99 % window, gamma 1.5, 8 bits."""
    y = -attenuation(pixels, mask, True, "linear-intensity").astype(np.float64)
    y = np.where(mask, y, np.median(y[mask]))
    y -= 0.5 * ndimage.gaussian_filter(y, 20.0 / pixel_mm)
    y += 1.0 * (y - ndimage.gaussian_filter(y, 3.0 / pixel_mm))
    lo, hi = np.percentile(y[mask], [1, 99])
    return np.round(255.0 * np.clip((y - lo) / (hi - lo), 0.0, 1.0) ** 1.5) * mask


def test_a_processed_display_agrees_better_on_its_equalised_image_at_the_true_pose_only(sample_ct):
    """CarmReg's simulated AP case shown as a processed fluoroscopy display: at the true pose the equalised image
    agrees more than the image converted as a log display; one level down the spine (25 mm) it stays far lower."""
    sim, geometry = simulated_ap_case(sample_ct, 1234, "T6", 7)
    pixels = sim.pixels.astype(np.float64)
    mask = field_mask(pixels)
    stored = _processed_display(pixels, mask, geometry.intrinsics.pixel_spacing_mm[0])
    params = coarse_refine_parameters()
    ctx = FitContext(MuPyramid(sample_ct[0]).level(params.mu_spacing_mm), geometry,
                     attenuation(stored, mask, True, "log-display"), mask, 0.0, 0.0, FineParameters(), params,
                     xray_equalised=attenuation(stored, mask, True, EQUALISED))
    truth = sim.pose.as_array()
    converted = _fit_at(truth, 0.0)
    ctx_plain = dataclasses.replace(ctx, xray_equalised=ctx.xray_line_integral)  # the converted image, for its GC
    measure_agreement(ctx_plain, [converted])
    right, off = _fit_at(truth, converted.refine.equalised_similarity), _fit_at(truth + [0, 0, 25.0, 0, 0, 0], 0.0)
    measure_agreement(ctx, [right, off])
    assert right.refine.equalised_similarity > right.similarity + 0.03
    assert right.agreement == pytest.approx(right.refine.equalised_similarity)
    assert off.refine.equalised_similarity < right.refine.equalised_similarity - 0.15
    measured = right.refine.equalised_similarity
    right.refine = RefineResult(truth, 0.0, 0.9, float("nan"), 1, objective_end=0.4)  # a new refinement
    assert right.agreement == pytest.approx(0.9)  # not measured yet: its own GC
    measure_agreement(ctx, [right])
    assert right.refine.equalised_similarity == pytest.approx(measured)
    assert right.agreement == pytest.approx(0.9)  # the better of the two


def test_without_an_equalised_image_the_agreement_is_the_converted_gc(tiny_db_inputs):
    level, geometry, _, _, _ = tiny_db_inputs
    image = render_line_integrals(level, geometry, np.zeros(6))
    ctx = FitContext(level, geometry, image, field_mask(image + 1.0), 0.0, 0.0, FineParameters(), RefineParameters())
    fit = _fit_at(np.zeros(6), 0.33)
    measure_agreement(ctx, [fit])
    assert np.isnan(fit.refine.equalised_similarity) and fit.agreement == pytest.approx(0.33)


def test_the_equalised_conversion_is_the_rank_image_the_right_way_up():
    pixels = np.array([[10.0, 30.0], [20.0, 40.0]])
    mask = np.array([[True, True], [True, False]])
    bright = attenuation(pixels, mask, False, EQUALISED)
    dark = attenuation(pixels, mask, True, EQUALISED)
    np.testing.assert_allclose(bright, [[0.0, 1.0], [0.5, 0.0]])
    np.testing.assert_allclose(dark, [[1.0, 0.0], [0.5, 0.0]])
