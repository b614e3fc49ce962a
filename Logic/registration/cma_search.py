"""The CMA-ES every search of CarmReg runs (``cma``, N. Hansen's reference implementation), seeded per search.

``cma`` seeds and draws from numpy's *global* random state by default (``np.random.seed(seed)``, then
``np.random.randn`` at every ``ask``): anything else drawing from it between two steps (a host application such
as 3D Slicer, another search in another thread) would change the search, which would then not repeat. Each
search here draws from its own ``np.random.RandomState(seed)``: the legacy global state is that same Mersenne
Twister, so a search draws exactly the numbers cma's own seeding gives - the same poses as before, bit for bit,
whatever else runs (``test_cma_search``).

Bounds are ``cma``'s own (``BoundTransform``): a search never leaves ``start +- half_range``.
"""

from __future__ import annotations

import sys
import threading
import warnings

import numpy as np

UNUSED_BY_CMA = ("scipy.stats", "matplotlib.pyplot")
"""Modules ``cma`` imports when it is imported, each inside ``try: ... except ImportError`` with a fallback, and
CarmReg never uses: ``scipy.stats`` (``kendalltau``, for pycma's surrogate models; pycma has its own) and
``matplotlib.pyplot`` (pycma's plotting; CarmReg draws on Agg canvases without pyplot). Together ~0.8 s of every
command-line run here (``python -X importtime``: scipy.stats 0.5-0.65 s, pyplot 0.25-0.3 s)."""
_import_lock = threading.Lock()


def import_cma():
    """``import cma`` without the modules of ``UNUSED_BY_CMA`` that are not imported yet: while pycma is imported
    they are marked absent (``sys.modules[name] = None``, which makes their import raise ImportError and pycma
    take its fallback), then unmarked, so that anything importing them later gets the real modules. The search
    itself is unchanged (``CMAEvolutionStrategy`` uses neither; ``test_cma_search`` checks the same poses)."""
    if "cma" in sys.modules:
        return sys.modules["cma"]
    with _import_lock, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Could not import matplotlib.pyplot")
        blocked = [name for name in UNUSED_BY_CMA if name not in sys.modules]
        for name in blocked:
            sys.modules[name] = None
        try:
            import cma
        finally:
            for name in blocked:
                if sys.modules.get(name, 0) is None:
                    del sys.modules[name]
    return cma


def cma_strategy(start: np.ndarray, stds, half_range, popsize: int, max_evaluations: int, seed: int,
                 tolx: float, tolfun: float = 1e-5):
    """A ``cma.CMAEvolutionStrategy`` at ``start`` (n,) with per-parameter initial steps ``stds`` (global sigma
    1), bounded to ``start +- half_range``, population ``popsize``, stopping after ``max_evaluations`` or at
    ``tolx`` / ``tolfun``; silent, no log files."""
    cma = import_cma()  # on first use, without the modules it would import and CarmReg never uses (~0.8 s)
    x0 = np.asarray(start, float)
    half = np.asarray(half_range, float)
    return cma.CMAEvolutionStrategy(x0, 1.0, {
        "popsize": popsize, "maxfevals": max_evaluations, "CMA_stds": list(stds),
        "bounds": [list(x0 - half), list(x0 + half)], "tolfun": tolfun, "tolx": tolx,
        "seed": float("nan"), "randn": np.random.RandomState(seed).randn,
        "verbose": -9, "verb_log": 0, "verb_disp": 0})
