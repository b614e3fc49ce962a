"""Cases of the appearance benchmark registered up to the spatial stage, each on its own CT: shared by the tests of
the polarity's second opinions (``test_polarity_without_shading``, ``test_polarity_at_clicks_without_shading``) and of
the orientation at the clicks judged again on more labellings (``test_orientation_judged_again``).
"""

import contextlib
import copy
import functools
import sys
from pathlib import Path

import pytest


@functools.cache
def _case_maker(second_ct: bool = True):
    """One ``CaseMaker`` per test process (and ``second_ct``: False draws every case on the chest CT, as the
    benchmark does without ../shared): its CTs and each case's scenes are made once, whichever module asks."""
    sys.path.insert(0, str(Path(__file__).resolve().parent / "Benchmarks"))
    import bench_appearance as bench

    return bench.CaseMaker(second_ct=second_ct)


def appearance_case_registrar(tmp_path_factory, cache_dir: str, with_clicks: bool, chest_only: bool = False):
    """``registered(case, variant)``: (logic, the state after the spatial stage, the case's truth) of that case and
    variant of the appearance benchmark, on the case's CT (``CaseMaker.ct_name``: every third case the second CT),
    with its unnamed clicks or none (DRR databases cached in ``cache_dir``), or its clicks named ``names`` when
    given; a case of the second CT skips the test without ../shared. ``chest_only``: every case's scene drawn on the
    chest CT (``CaseMaker(second_ct=False)``; nothing skipped)."""
    maker = _case_maker(not chest_only)
    import bench_appearance as bench  # on the path once the maker is made

    def registered(case: int, variant_name: str, names: list[str] | None = None):
        if not chest_only and case % 3 == 2 and "abdomen" not in maker.cts:
            pytest.skip("the second CT (../shared) is not here")
        logic, state, truth = bench.prepared_case(maker, case, variant_name, tmp_path_factory.mktemp(variant_name),
                                                  cache_dir, clicks=with_clicks, names=names)
        logic.run_through(state, "spatial")
        return logic, state, truth

    return registered


def copied(state):
    """(logic, state): a deep copy of a registration's ``state`` that runs its own stages, sharing the CT, its mu
    pyramid and the DRR database (read only), and a new logic to run them (a logic keeps no state of a
    registration). For tests that run the same registration on from one point more than once (a copy costs far
    less than the stages before it)."""
    from carmreg.logic.registration.pipeline import CarmRegLogic

    shared = {id(x): x for x in (state.ct, state.pyramid, state.database) if x is not None}
    return CarmRegLogic(), copy.deepcopy(state, shared)


@contextlib.contextmanager
def ordered_by_click_spacing():
    """Unnamed clicks' labellings taken in the order before stop 65 (``labelling_order.depth_order``: the source depth
    their click spacing implies, nearest the nominal first) instead of the image's agreement at their landmark pose
    (``labelling_order.agreement_order``). For the tests that pin what the checks do when the labellings judged first
    are all wrong ones: the scenes they were found on judged wrong leaders under that order, which the image's order
    now avoids there; the rules they pin still apply whenever the leaders are all wrong (seen, stop 65: report case
    455's large patient, whose labellings the image barely tells apart)."""
    from carmreg.logic.registration import labelling_order

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(labelling_order, "agreement_order", lambda ctx, fits: labelling_order.depth_order(fits))
        yield
