"""The order unnamed clicks' labellings are registered in (``registration.labelling_order``): by the image's agreement
at each labelling's landmark pose on any shape-keeping display, not by the source depth its click spacing implies."""

import dataclasses

import numpy as np
import pytest
from appearance_cases import appearance_case_registrar

from carmreg.logic.image.prepare import attenuation
from carmreg.logic.io.landmarks import Landmarks2D, read_landmarks_2d
from carmreg.logic.io.xray import load_xray
from carmreg.logic.registration import labelling_order
from carmreg.logic.registration.labelling_fit import state_context
from carmreg.logic.registration.labelling_order import (
    LabellingOrders,
    agreement_order,
    depth_order,
    display_agreement,
    unnamed_order,
)
from carmreg.logic.registration.levels import plan_contest
from carmreg.logic.registration.pipeline import CarmRegLogic, RegistrationParameters


@pytest.fixture(scope="module")
def planned(sample_ct, sample_case_dir, drr_cache_dir):
    """(the registration's state after the database stage, a context on its X-ray converted bone dark, the unnamed
    clicks' planned labellings, the true labels): the sample case's X-ray (DICOM) with its clicks unnamed."""
    ct, _, centroids = sample_ct
    named = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    clicks = Landmarks2D([None] * len(named.labels), named.uv_px)
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, load_xray(sample_case_dir / "xray.dcm"), clicks,
                          RegistrationParameters(cache_dir=drr_cache_dir))
    logic.run_through(state, "database")
    ctx = state_context(state, attenuation(state.xray.pixels, state.mask, True, "log-display"), 0.0, 0.0, None)
    plan = plan_contest(ctx, state.ct_landmarks, clicks, state.parameters.identify)
    return state, ctx, plan.fits, list(named.labels)


def test_the_true_labelling_is_the_one_the_image_agrees_with_most(planned):
    """On the sample case every labelling of its three unnamed clicks (T10-T12) is scored at its landmark pose; the
    true one leads, by far more than the rounding of any score (0.51 against 0.28)."""
    _, ctx, fits, truth = planned
    agreement = display_agreement(ctx, fits)
    order = agreement_order(ctx, fits)
    assert fits[order[0]].labels == truth
    assert agreement[order[0]] - agreement[order[1]] > 0.1
    assert sorted(order) == list(range(len(fits))) and np.all(agreement >= 0.0) and np.all(agreement <= 1.0)


def test_the_agreement_is_the_same_whichever_polarity_the_image_was_converted_as(planned):
    """The polarity is not known when the order is made: the image inverted (its GC is the negative) gives every
    labelling the same agreement, so the same order."""
    _, ctx, fits, _ = planned
    inverted = dataclasses.replace(ctx, xray_line_integral=np.where(ctx.mask, -ctx.xray_line_integral, 0.0)
                                   .astype(np.float32))
    np.testing.assert_allclose(display_agreement(inverted, fits), display_agreement(ctx, fits), atol=1e-9)


def test_a_mirrored_display_still_leads_with_its_true_labelling(planned):
    """Shown mirrored left-right (a display setting no header records), the true labelling agrees with the image
    only mirrored: the max over displays still puts it first, so the orientation check judges it."""
    state, ctx, fits, truth = planned
    mirrored = dataclasses.replace(ctx, xray_line_integral=np.ascontiguousarray(ctx.xray_line_integral[:, ::-1]),
                                   mask=np.ascontiguousarray(ctx.mask[:, ::-1]))
    cols = ctx.xray_line_integral.shape[1]
    clicks = Landmarks2D([None] * len(fits[0].uv_px), np.column_stack([cols - 1.0 - fits[0].uv_px[:, 0],
                                                                       fits[0].uv_px[:, 1]]))
    on_mirror = plan_contest(mirrored, state.ct_landmarks, clicks, state.parameters.identify)
    assert on_mirror.fits[on_mirror.first[0]].labels == truth


def test_one_registration_orders_each_set_of_clicks_once_whatever_context_asks(planned, monkeypatch):
    """Every check of a registration (each polarity's conversion, with or without shading) takes the labellings in
    the order of the first context that asked: computed once per set of clicks, again for other clicks."""
    _, ctx, fits, _ = planned
    calls = []
    real = labelling_order.agreement_order
    monkeypatch.setattr(labelling_order, "agreement_order", lambda c, f: calls.append(1) or real(c, f))
    orders = LabellingOrders()
    first = dataclasses.replace(ctx, labelling_orders=orders)
    other = dataclasses.replace(first, xray_line_integral=np.zeros_like(ctx.xray_line_integral))  # shows nothing
    assert unnamed_order(first, fits) == unnamed_order(other, fits) == real(ctx, fits)
    assert len(calls) == 1
    moved = [dataclasses.replace(f, uv_px=f.uv_px + 1.0) for f in fits]
    unnamed_order(other, moved)
    assert len(calls) == 2


@pytest.fixture(scope="module")
def appearance_cases(tmp_path_factory, drr_cache_dir):
    """``registered(case, variant)`` with the case's unnamed clicks (``appearance_case_registrar``)."""
    return appearance_case_registrar(tmp_path_factory, drr_cache_dir, with_clicks=True)


@pytest.mark.benchmark_case
def test_a_scene_whose_click_spacing_misleads_has_its_true_labelling_judged_first(appearance_cases):
    """Report case 451 of the appearance benchmark (chest CT, intensifier PNG, T9-T11 clicked unnamed): the click
    spacing put the true labelling outside the five registered first, and the polarity check judged T5-T7 and T4-T6
    (stop 64: 14.6 s, 20.4 s for its JPEG). Ordered by the image's agreement, T9-T11 is judged first and the
    polarity is clear on it."""
    _, state, truth = appearance_cases(451, "ii-dark-log-png")
    fits = plan_contest(state_context(state, state.xray_line_integral, 0.0, 0.0, None), state.ct_landmarks,
                        state.xray_landmarks, state.parameters.identify).fits
    true = next(i for i, f in enumerate(fits) if f.names(truth["clicked"]))
    assert true not in depth_order(fits)[:5]
    assert state.click_polarity.labels[0] == list(truth["clicked"])
    assert state.appearance.polarity == "bone-dark" and state.appearance.clear
