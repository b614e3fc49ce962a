"""Cases of the appearance benchmark registered up to the spatial stage, each on its own CT: shared by the tests of
the polarity's second opinions (``test_polarity_without_shading``, ``test_polarity_at_clicks_without_shading``) and of
the orientation at the clicks judged again on more labellings (``test_orientation_judged_again``).
"""

import sys
from pathlib import Path

import numpy as np
import pytest

from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray import load_xray
from carmreg.logic.registration.pipeline import CarmRegLogic
from carmreg.logic.registration.state import RegistrationParameters


def appearance_case_registrar(tmp_path_factory, cache_dir: str, with_clicks: bool):
    """``registered(case, variant)``: (logic, the state after the spatial stage, the case's truth) of that case and
    variant of the appearance benchmark, on the case's CT (``CaseMaker.ct_name``: every third case the second CT),
    with its unnamed clicks or none (DRR databases cached in ``cache_dir``), or its clicks named ``names`` when
    given; a case of the second CT skips the test without ../shared."""
    sys.path.insert(0, str(Path(__file__).resolve().parent / "Benchmarks"))
    import appearance as app
    import bench_appearance as bench

    maker = bench.CaseMaker(second_ct=True)
    params = RegistrationParameters(cache_dir=cache_dir)

    def registered(case: int, variant_name: str, names: list[str] | None = None):
        if case % 3 == 2 and "abdomen" not in maker.cts:
            pytest.skip("the second CT (../shared) is not here")
        (ct, _, centroids), _, _ = maker.cts[maker.ct_name(case)]
        variant = app.VARIANTS[variant_name]
        record = bench.write_variant(maker.scenes(case, {variant.detector})[variant.detector], variant, case,
                                     tmp_path_factory.mktemp(variant_name))
        detector = app.DETECTORS[variant.detector]
        xray = load_xray(record["xray"], sdd_mm=detector.sdd_mm, pixel_spacing_mm=detector.pixel_mm)
        uv_px = np.asarray(record["truth"]["clicks_uv_px"] if with_clicks else np.zeros((0, 2)), float)
        logic = CarmRegLogic()
        labels = list(names) if names is not None else [None] * len(uv_px)
        state = logic.prepare(ct, centroids, xray, Landmarks2D(labels, uv_px), params)
        for stage in ("database", "spatial"):
            logic.run_stage(state, stage)
        return logic, state, record["truth"]

    return registered
