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

import numpy as np


def cma_strategy(start: np.ndarray, stds, half_range, popsize: int, max_evaluations: int, seed: int,
                 tolx: float, tolfun: float = 1e-5):
    """A ``cma.CMAEvolutionStrategy`` at ``start`` (n,) with per-parameter initial steps ``stds`` (global sigma
    1), bounded to ``start +- half_range``, population ``popsize``, stopping after ``max_evaluations`` or at
    ``tolx`` / ``tolfun``; silent, no log files."""
    import cma  # imported on first use: it brings scipy.stats and matplotlib.pyplot (~0.8 s)

    x0 = np.asarray(start, float)
    half = np.asarray(half_range, float)
    return cma.CMAEvolutionStrategy(x0, 1.0, {
        "popsize": popsize, "maxfevals": max_evaluations, "CMA_stds": list(stds),
        "bounds": [list(x0 - half), list(x0 + half)], "tolfun": tolfun, "tolx": tolx,
        "seed": float("nan"), "randn": np.random.RandomState(seed).randn,
        "verbose": -9, "verb_log": 0, "verb_disp": 0})
