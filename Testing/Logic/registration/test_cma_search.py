"""CarmReg's CMA-ES (``registration.cma_search``) held to ``cma``, N. Hansen's reference implementation: the same
strategy parameters, the same bound transformation, the same populations generation after generation, the same
stops; and seeded per search, without numpy's global random state."""

import json
import subprocess
import sys

import numpy as np
import pytest

cma = pytest.importorskip("cma")
from cma.transformations import BoxConstraintsLinQuadTransformation  # noqa: E402

from carmreg.logic.registration.cma_search import (  # noqa: E402
    CmaEs,
    StrategyParameters,
    box_margins,
    box_transform,
    cma_strategy,
)

START = np.array([0.0, 10.0, -5.0, 1.0, 0.0, 2.0])
STDS, HALF = (4.0, 1.0, 1.0, 1.0, 1.5, 1.5), (40.0, 10.0, 10.0, 6.0, 10.0, 10.0)
ROTATION = np.linalg.qr(np.random.RandomState(5).randn(6, 6))[0]


def _ellipsoid(x: np.ndarray) -> np.ndarray:
    """A rotated ellipsoid (condition 100) whose optimum lies off the start."""
    z = (x - np.array([30.0, 3.0, -9.0, 4.0, -6.0, 7.0])) @ ROTATION.T
    return np.sum(z**2 * np.logspace(0, 2, 6), axis=1)


def _reference(popsize, max_evaluations, stds, half, seed, tolx, tolfun=1e-5):
    half = np.asarray(half, float)
    return cma.CMAEvolutionStrategy(START, 1.0, {
        "popsize": popsize, "maxfevals": max_evaluations, "CMA_stds": list(stds),
        "bounds": [list(START - half), list(START + half)], "tolfun": tolfun, "tolx": tolx, "seed": float("nan"),
        "randn": np.random.RandomState(seed).randn, "verbose": -9, "verb_log": 0, "verb_disp": 0})


@pytest.mark.parametrize("popsize", [12, 16, 50])
def test_strategy_parameters_are_cmas(popsize):
    """Weights (active: negative for the worse half), learning rates, cumulation and damping as cma sets them."""
    ref = _reference(popsize, 1000, STDS, HALF, 1, 1e-3)
    sp = StrategyParameters(6, popsize)
    assert sp.mu == ref.sp.weights.mu
    assert np.allclose(sp.weights, np.asarray(ref.sp.weights), rtol=0, atol=1e-14)
    assert sp.weights[-1] < 0 < sp.weights[sp.mu - 1]
    for mine, theirs in ((sp.mueff, ref.sp.weights.mueff), (sp.cc, ref.sp.cc), (sp.c1, ref.sp.c1),
                         (sp.cmu, ref.sp.cmu), (sp.cs, ref.adapt_sigma.cs), (sp.damps, ref.adapt_sigma.damps)):
        assert mine == pytest.approx(theirs, rel=1e-12)


def test_box_transformation_is_cmas_inside_in_the_margins_and_far_outside():
    lower = np.array([-80.0, -20.0, -20.0, -12.0, -15.0, -15.0])
    upper = -lower + np.array([3.0, 0.0, 1.0, 0.0, 0.0, 2.0])
    theirs = BoxConstraintsLinQuadTransformation([[a, b] for a, b in zip(lower, upper, strict=True)])
    x = np.random.RandomState(0).randn(500, 6) * np.array([200.0, 50.0, 50.0, 30.0, 40.0, 40.0])
    mine = box_transform(x, lower, upper, *box_margins(lower, upper))
    assert np.array_equal(mine, np.array([theirs(row.copy()) for row in x]))
    assert np.all((mine >= lower) & (mine <= upper))
    inside = np.zeros(6) + 1.0
    assert np.array_equal(box_transform(inside, lower, upper, *box_margins(lower, upper)), inside)


def _run_both(f, popsize, max_evaluations, stds, half, seed, tolx):
    """Step cma and CarmReg's search side by side; (largest difference of the poses asked for, cma's stop
    reasons, its evaluations, ours)."""
    ref, mine = _reference(popsize, max_evaluations, stds, half, seed, tolx), \
        CmaEs(START, stds, half, popsize, max_evaluations, seed, tolx)
    worst = 0.0
    while not ref.stop() and not mine.stop():
        theirs, ours = np.asarray(ref.ask()), mine.ask()
        worst = max(worst, float(np.max(np.abs(theirs - ours))))
        ref.tell(list(theirs), list(f(theirs)))
        mine.tell(f(ours))
    return worst, set(ref.stop()), ref.countevals, mine.countevals, bool(mine.stop())


@pytest.mark.parametrize("popsize, max_evaluations, stds, half", [
    (16, 800, (20.0, 4.0, 4.0, 4.0, 5.0, 5.0), (80.0, 20.0, 20.0, 12.0, 15.0, 15.0)),   # the coarse refinement's
    (50, 2000, (10.0, 3.0, 3.0, 3.0, 3.0, 3.0), (80.0, 30.0, 30.0, 15.0, 15.0, 15.0)),  # the landmark fit's
    (12, 360, STDS, HALF)])                                                              # the local refinement's
def test_a_search_asks_for_the_poses_cma_asks_for_to_rounding_and_stops_with_it(popsize, max_evaluations, stds, half):
    for seed in (1, 2):
        worst, reasons, theirs, ours, stopped = _run_both(_ellipsoid, popsize, max_evaluations, stds, half, seed,
                                                          1e-3)
        assert worst < 1e-8 and reasons == {"maxfevals"} and stopped and ours == theirs


def test_a_linear_slope_grows_the_step_to_the_bound_limit_as_cma_does():
    """On a linear function the step grows until a coordinate's spread reaches a third of its range (cma's
    ``maxstd``), where both searches cap it alike."""
    worst, reasons, theirs, ours, _ = _run_both(lambda x: x @ np.array([1.0, -2.0, 3.0, 1.0, 1.0, -1.0]), 16, 800,
                                                (20.0, 4.0, 4.0, 4.0, 5.0, 5.0),
                                                (80.0, 20.0, 20.0, 12.0, 15.0, 15.0), 3, 1e-3)
    assert worst < 1e-8 and ours == theirs


@pytest.mark.parametrize("f, reason", [
    (lambda x: np.round(np.sum((x - 3.0) ** 2, axis=1) / 1e4), "tolfun"),          # flat: one value everywhere
    (lambda x: np.sum((x - 3.0) ** 2, axis=1), "tolx"),                              # a sphere, large budget
    (lambda x: (np.sum((x - START) ** 2, axis=1) > 16.0) * 1.0, "tolflatfitness")])  # a plateau, a cliff
def test_it_stops_when_and_where_cma_stops(f, reason):
    worst, reasons, theirs, ours, stopped = _run_both(f, 12, 100_000, STDS, HALF, 4, 1e-3)
    assert reason in reasons and stopped and ours == theirs and worst < 1e-8


def _steps(es, n: int = 5) -> list:
    out = []
    for _ in range(n):
        population = es.ask()
        es.tell(np.sum((population - 1.0) ** 2, axis=1))
        out.append(population)
    return out


def _search(seed: int) -> CmaEs:
    return cma_strategy(START, STDS, HALF, popsize=12, max_evaluations=360, seed=seed, tolx=1e-3)


def test_searches_side_by_side_and_other_users_of_numpy_random_do_not_change_a_search():
    """Two searches stepped alternately, with numpy's global random state drawn from in between, give the
    populations each gives alone."""
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


def test_a_search_runs_without_cma_installed_or_imported():
    """The registration needs no ``cma``: a search in a fresh process where it cannot be imported."""
    code = ("import sys, json, numpy as np\nsys.modules['cma'] = None\n"
            "from carmreg.logic.registration.cma_search import cma_strategy\n"
            "es = cma_strategy(np.zeros(6), (4, 1, 1, 1, 1.5, 1.5), (40, 10, 10, 6, 10, 10), 12, 360, 3, 1e-3)\n"
            "while not es.stop():\n    p = es.ask(); es.tell(np.sum((p - 1.0) ** 2, axis=1))\n"
            "print(json.dumps({'evaluations': es.countevals, 'mean': es.mean.tolist()}))")
    out = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                    timeout=120).stdout)
    assert out["evaluations"] == 372 and np.allclose(out["mean"], 1.0, atol=0.05)
