"""CMA-ES seeded per search (``registration.cma_search``): cma's own seeded draws, without its global state."""

import cma
import numpy as np
import pytest

from carmreg.logic.registration.cma_search import cma_strategy

START = np.array([0.0, 10.0, -5.0, 1.0, 0.0, 2.0])
STDS, HALF = (4.0, 1.0, 1.0, 1.0, 1.5, 1.5), (40.0, 10.0, 10.0, 6.0, 10.0, 10.0)


def _search(seed: int) -> cma.CMAEvolutionStrategy:
    return cma_strategy(START, STDS, HALF, popsize=12, max_evaluations=360, seed=seed, tolx=1e-3)


def _steps(es, n: int = 5) -> list:
    out = []
    for _ in range(n):
        population = np.asarray(es.ask())
        es.tell(list(population), list(np.sum((population - 1.0) ** 2, axis=1)))
        out.append(population)
    return out


def test_a_search_draws_what_cma_seeded_globally_draws():
    """The same populations as cma with its global seeding (``seed`` option): results of earlier versions repeat."""
    half = np.asarray(HALF)
    legacy = cma.CMAEvolutionStrategy(START, 1.0, {
        "popsize": 12, "maxfevals": 360, "seed": 7, "CMA_stds": list(STDS), "bounds": [list(START - half),
        list(START + half)], "tolfun": 1e-5, "tolx": 1e-3, "verbose": -9, "verb_log": 0, "verb_disp": 0})
    expected = _steps(legacy)
    for got, want in zip(_steps(_search(7)), expected, strict=True):
        assert np.array_equal(got, want)


def test_searches_side_by_side_and_other_users_of_numpy_random_do_not_change_a_search():
    """Two searches stepped alternately, with numpy's global random state drawn from in between, give the
    populations each gives alone (with cma's global seeding the second search would reseed the first's stream)."""
    alone = _steps(_search(3))
    a, b = _search(3), _search(4)
    interleaved = []
    for _ in range(5):
        interleaved += _steps(a, 1)
        np.random.seed(123)
        np.random.randn(50)
        _steps(b, 1)
    for got, want in zip(interleaved, alone, strict=True):
        assert np.array_equal(got, want)
    assert not np.array_equal(_steps(_search(4), 1)[0], alone[0])  # another seed, another search



_SEARCH_IN_A_FRESH_PROCESS = """
import json, sys
import numpy as np
{before}
from carmreg.logic.registration.cma_search import cma_strategy
es = cma_strategy(np.array([0.0, 10.0, -5.0, 1.0, 0.0, 2.0]), (4.0, 1.0, 1.0, 1.0, 1.5, 1.5),
                  (40.0, 10.0, 10.0, 6.0, 10.0, 10.0), popsize=12, max_evaluations=360, seed=3, tolx=1e-3)
while not es.stop():
    pop = np.asarray(es.ask())
    es.tell(list(pop), list(np.sum((pop - 1.0) ** 2, axis=1)))
loaded = [name for name in ("scipy.stats", "matplotlib.pyplot") if sys.modules.get(name) is not None]
import scipy.stats
print(json.dumps({{"best": es.result.xbest.tolist(), "evaluations": es.countevals, "loaded": loaded,
                  "tau": float(scipy.stats.kendalltau([1, 2, 3], [1, 3, 2])[0])}}))
"""


def _fresh_search(before: str = "") -> dict:
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _SEARCH_IN_A_FRESH_PROCESS.format(before=before)],
                         capture_output=True, text=True, check=True, timeout=120)
    return json.loads(out.stdout)


def test_cma_is_imported_without_the_modules_it_never_needs_here_and_searches_the_same():
    """``import_cma`` leaves scipy.stats and pyplot unimported (~0.8 s of every run); the search finds exactly what
    it finds with them imported first; scipy.stats imports normally afterwards."""
    lean = _fresh_search()
    full = _fresh_search("import scipy.stats, matplotlib.pyplot")
    assert lean["loaded"] == [] and full["loaded"] == ["scipy.stats", "matplotlib.pyplot"]
    assert lean["best"] == full["best"] and lean["evaluations"] == full["evaluations"] > 100
    assert lean["tau"] == full["tau"] == pytest.approx(1 / 3)
