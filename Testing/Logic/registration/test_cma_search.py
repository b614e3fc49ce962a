"""CMA-ES seeded per search (``registration.cma_search``): cma's own seeded draws, without its global state."""

import cma
import numpy as np

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
