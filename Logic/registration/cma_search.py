"""The CMA-ES every search of CarmReg runs: active CMA-ES with cumulative step-size adaptation, bounded by a
smooth transformation, seeded per search, vectorised over the population (beyond the paper's "CMA-ES": the same
algorithm and strategy parameters as ``cma``, N. Hansen's reference implementation, without its bookkeeping).

Why not ``cma`` itself: its ``ask`` and ``tell`` cost ~1 ms each per generation here (per-solution archives and
bound transforms in Python): 2 ms x 40-50 generations per search, ~20 % of a registration whose DRRs take the
rest (measured on the hardest benchmark run: 4.7 s of 24.5 s). This one costs ~0.3 ms per generation (0.7 s).
``test_cma_search`` holds it to ``cma``: the same strategy parameters, the same bound transformation, and, stepped
side by side on the same random draws, the same poses asked for generation after generation (to ~1e-12) and the
same stop.

The algorithm (Hansen, "The CMA Evolution Strategy: A Tutorial", 2016; n parameters, population lambda)::

    sample    z_k ~ N(0, I),  y_k = B D z_k,  x_k = m + sigma * s * y_k          (genotype, k = 1..lambda)
              evaluate f at T(x_k), T the box transformation below (phenotype)
    select    sort by f; w_i recombination weights (positive for the best mu, negative for the rest: active CMA)
    mean      m' = sum_{i<=mu} w_i x_{i:lambda}
    paths     p_s = (1 - c_s) p_s + sqrt(c_s (2 - c_s) mu_eff) C^-1/2 (m' - m) / (s sigma)
              h = |p_s|^2 / (1 - (1 - c_s)^(2 g)) / n - 1 < 1 + 4 / (n + 1)
              p_c = (1 - c_c) p_c + h sqrt(c_c (2 - c_c) mu_eff) (m' - m) / (s sigma)
    covariance  with y_i = (x_{i:lambda} - m) / (s sigma), weights c1a = c1 (1 - (1 - h^2) c_c (2 - c_c)) for p_c
              and c_mu w_i for y_i (negative ones times n / |C^-1/2 y_i|^2):
              C = (1 - c1a - c_mu sum w) C + c1 p_c p_c^T + sum_i c_mu w_i' y_i y_i^T
    step      sigma *= exp(clip((|p_s| / E|N(0, I)| - 1) c_s / d_s, -1, 1))
    limits    a coordinate whose standard deviation sigma s_i sqrt(C_ii) exceeds a third of its bound range
              has its scale s_i reduced to that

``s`` are the initial standard deviations per parameter (``stds``; mm and degrees), sigma starts at 1.
The bounds ``start +- half_range`` are kept by ``cma``'s transformation T: the identity inside the box except a
margin, quadratic in the margin, mirrored and periodic outside (``box_transform``), so every pose asked for is in
the box while the search itself is unbounded.

Stops (as ``cma``'s, with its defaults): after ``max_evaluations`` (the first generation to reach it); ``tolx``
(every coordinate's sigma s_i sqrt(C_ii) and sigma s_i p_c,i below it); ``tolfun`` (the range of this
generation's values and of the best values of the last 10 + 30 n / lambda generations below it, or the latter
below 1e-12); a flat fitness (the best value equal to the 75th percentile two generations running); a step
grown 1000-fold.

Each search draws its samples from its own ``np.random.RandomState(seed)`` (``randn(lambda, n)`` per generation),
never from numpy's global state: the same inputs give the same poses bit for bit, whatever else runs (a host
application such as 3D Slicer, another search in another thread).
"""

from __future__ import annotations

import math

import numpy as np

TOLFUN_HISTORY_BASE = 10
"""Best values kept for ``tolfun``: 10 + 30 n / lambda generations (``cma``'s)."""
MAXSTD_OF_RANGE = 1.0 / 3.0
"""Largest standard deviation of a coordinate, as a fraction of its bound range (``cma``'s ``maxstd_boundrange``)."""
TOLFUNHIST = 1e-12
"""Stop when the best values of the last 10+ generations span less than this (``cma``'s ``tolfunhist``)."""
TOLFACUPX = 1e3
"""Stop when a coordinate's standard deviation has grown this much over its start (``cma``'s ``tolfacupx``)."""


def box_margins(lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Widths of the quadratic margins inside the box (``cma``'s ``linquad_margin_width``): at each bound b,
    min(range / 2, max(1, |b|) / 20)."""
    half = (upper - lower) / 2.0
    return (np.minimum(half, np.maximum(1.0, np.abs(lower)) / 20.0),
            np.minimum(half, np.maximum(1.0, np.abs(upper)) / 20.0))


def box_transform(x: np.ndarray, lower: np.ndarray, upper: np.ndarray, al: np.ndarray, au: np.ndarray
                  ) -> np.ndarray:
    """Genotype -> phenotype inside [lower, upper] (``cma``'s ``BoxConstraintsLinQuadTransformation``), for an
    (n,) vector or (k, n) rows: shifted by whole periods into [lb - 2 al - r/2, ub + 2 au + r/2] (period
    2 (r + al + au), r = ub - lb), mirrored at lb - al and ub + au, then quadratic in the margins::

        lb + (y - (lb - al))^2 / (4 al)   for y < lb + al,     ub - (y - (ub + au))^2 / (4 au)   for y > ub - au
    """
    y = np.array(x, dtype=float, copy=True)
    lb, ub = np.broadcast_to(lower, y.shape), np.broadcast_to(upper, y.shape)
    al, au = np.broadcast_to(al, y.shape), np.broadcast_to(au, y.shape)
    r = ub - lb
    idx = (y < lb - 2 * al - r / 2.0) | (y > ub + 2 * au + r / 2.0)
    if idx.any():
        period = 2 * (r[idx] + al[idx] + au[idx])
        start = lb[idx] - 2 * al[idx] - r[idx] / 2.0
        y[idx] -= period * ((y[idx] - start) // period)
    idx = y > ub + au
    y[idx] -= 2 * (y[idx] - ub[idx] - au[idx])
    idx = y < lb - al
    y[idx] += 2 * (lb[idx] - al[idx] - y[idx])
    idx = y < lb + al
    y[idx] = lb[idx] + (y[idx] - (lb[idx] - al[idx])) ** 2 / 4 / al[idx]
    idx = y > ub - au
    y[idx] = ub[idx] - (y[idx] - (ub[idx] + au[idx])) ** 2 / 4 / au[idx]
    return y


class StrategyParameters:
    """Weights and learning rates for n parameters and population lambda (``cma``'s defaults, hence its notation):
    log-linear weights w_i = ln((lambda + 1) / 2) - ln i, the positive ones summing to 1 (mu_eff = 1 / sum w+^2),
    the negative ones scaled to sum to -min(1 + c1 / c_mu, 1 + 2 mu_eff- / (mu_eff + 2), (1 - c1 - c_mu) / (n c_mu))
    (no decay of C; positive definite); c_c = (4 + mu_eff / n) / (n + 4 + 2 mu_eff / n),
    c1 = 2 / ((n + 1.3)^2 + mu_eff), c_mu = min(1 - c1, 2 (mu_eff - 1.75 + 1 / mu_eff) / ((n + 2)^2 + mu_eff)),
    c_s = min(1/2, (mu_eff + 2) / (n + mu_eff + 3)),
    d_s = 1 + 2 max(0, d_n sqrt((mu_eff - 1) / (n + 1)) - 1) + c_s with d_n = max(1, 3 (1 - 2^(-n / 9)))."""

    def __init__(self, n: int, popsize: int):
        raw = math.log((popsize + 1) / 2.0) - np.log(np.arange(1, popsize + 1))
        positive, negative = raw[raw > 0], raw[raw < 0]
        self.n, self.popsize, self.mu = n, popsize, len(positive)
        self.mueff = float(positive.sum() ** 2 / np.sum(positive**2))
        self.cc = (4 + self.mueff / n) / (n + 4 + 2 * self.mueff / n)
        self.c1 = 2.0 / ((n + 1.3) ** 2 + self.mueff)
        self.cmu = min(1 - self.c1, 2 * (0.25 + self.mueff + 1 / self.mueff - 2) / ((n + 2) ** 2 + self.mueff))
        self.cs = min(0.5, (self.mueff + 2) / (n + self.mueff + 3))
        inner = max(1.0, 3.0 * (1 - 0.5 ** (n / 9.0)))
        self.damps = 1.0 + 2 * max(0.0, inner * math.sqrt((self.mueff - 1) / (n + 1)) - 1) + self.cs
        weights = np.zeros(popsize)
        weights[: self.mu] = positive / positive.sum()
        if len(negative):
            mueff_minus = negative.sum() ** 2 / np.sum(negative**2)
            total = min(1 + self.c1 / self.cmu, 1 + 2 * mueff_minus / (self.mueff + 2),
                        (1 - self.c1 - self.cmu) / (n * self.cmu))
            weights[popsize - len(negative):] = negative / abs(negative.sum()) * total
        self.weights = weights
        self.chi_n = math.sqrt(2) * math.exp(math.lgamma((n + 1) / 2) - math.lgamma(n / 2))  # E|N(0, I_n)|


class CmaEs:
    """One bounded, seeded CMA-ES search (module docstring): ``ask`` -> (lambda, n) poses, ``tell`` their values,
    until ``stop``. ``countevals`` counts the values told; ``mean`` is the distribution's mean (phenotype)."""

    def __init__(self, start, stds, half_range, popsize: int, max_evaluations: int, seed: int, tolx: float,
                 tolfun: float = 1e-5):
        x0 = np.asarray(start, float)
        half = np.broadcast_to(np.asarray(half_range, float), x0.shape)
        n = len(x0)
        self.sp = StrategyParameters(n, int(popsize))
        self.lower, self.upper = x0 - half, x0 + half
        self.al, self.au = box_margins(self.lower, self.upper)
        self.maxstd = (self.upper - self.lower) * MAXSTD_OF_RANGE
        self.max_evaluations, self.tolx, self.tolfun = max_evaluations, tolx, tolfun
        self._randn = np.random.RandomState(seed).randn
        self._mean = x0.copy()                   # genotype; T(x0) = x0 at the box's centre
        self.scale = np.asarray(stds, float).copy()
        self._scale0 = self.scale.copy()
        self.sigma = 1.0
        self.C = np.diag(np.exp(1e-4 / n * np.arange(n)))  # distinct eigenvalues, as ``cma`` starts
        self.B, self.D = np.eye(n), np.sqrt(np.diag(self.C))
        self.pc, self.ps = np.zeros(n), np.zeros(n)
        self.countiter = self.countevals = 0
        self._fitness: np.ndarray | None = None  # this generation's values, sorted
        self._history: list[float] = []          # best value per generation, newest first
        self._flat = 0
        self._geno: np.ndarray | None = None
        self._decomposed = True

    @property
    def mean(self) -> np.ndarray:
        return box_transform(self._mean, self.lower, self.upper, self.al, self.au)

    @property
    def stds(self) -> np.ndarray:
        """(n,) the distribution's standard deviation along each coordinate (genotype, the units of the pose)."""
        return self.sigma * self.scale * np.sqrt(np.diag(self.C))

    def ask(self) -> np.ndarray:
        """(lambda, n) candidate poses inside the bounds."""
        if not self._decomposed:
            self.C = (self.C + self.C.T) / 2
            eigenvalues, self.B = np.linalg.eigh(self.C)
            self.D = np.sqrt(eigenvalues)
            self._decomposed = True
        z = self._randn(self.sp.popsize, self.sp.n)
        y = (z * self.D) @ self.B.T
        self._geno = self._mean + self.sigma * (self.scale * y)
        return box_transform(self._geno, self.lower, self.upper, self.al, self.au)

    def tell(self, values) -> None:
        """Update the distribution from the values of the poses of the last ``ask`` (module docstring)."""
        f = np.asarray(values, float)
        sp, n = self.sp, self.sp.n
        order = np.argsort(f)
        self.countiter += 1
        self.countevals += len(f)
        self._record(f[order])
        pop = self._geno[order]
        old = self._mean
        self._mean = sp.weights[: sp.mu] @ pop[: sp.mu]
        step = (self._mean - old) / self.scale
        inv_root = (self.B / self.D) @ self.B.T  # C^-1/2
        self.ps = (1 - sp.cs) * self.ps + math.sqrt(sp.cs * (2 - sp.cs) * sp.mueff) / self.sigma * (inv_root @ step)
        hsig = np.sum(self.ps**2) / (1 - (1 - sp.cs) ** (2 * self.countiter)) / n - 1 < 1 + 4.0 / (n + 1)
        c1a = sp.c1 * (1 - (1 - hsig) * sp.cc * (2 - sp.cc))
        self.pc = (1 - sp.cc) * self.pc + hsig * math.sqrt(sp.cc * (2 - sp.cc) * sp.mueff) / self.sigma * step
        y = (pop - old) / (self.sigma * self.scale)
        weights = sp.cmu * sp.weights
        self.C *= 1 - c1a - weights.sum()
        negative = weights < 0
        if negative.any():
            lengths = np.linalg.norm(y[negative] @ inv_root, axis=1)  # Mahalanobis norms (C symmetric)
            weights = weights.copy()
            weights[negative] *= n / (lengths + 1e-9) ** 2
        self.C += sp.c1 * np.outer(self.pc, self.pc) + (weights * y.T) @ y
        self._decomposed = False
        self.sigma *= math.exp(min(1.0, max(-1.0, (np.linalg.norm(self.ps) / sp.chi_n - 1) * sp.cs / sp.damps)))
        self._limit_stds()

    def _record(self, sorted_values: np.ndarray) -> None:
        """The histories the stops read."""
        self._fitness = sorted_values
        self._history.insert(0, float(sorted_values[0]))
        if len(self._history) > TOLFUN_HISTORY_BASE + 30 * self.sp.n / self.sp.popsize:
            self._history.pop()
        if sorted_values[0] < sorted_values[int(0.75 * len(sorted_values))]:
            self._flat = 0
        else:
            self._flat += 1

    def _limit_stds(self) -> None:
        """Coordinates whose standard deviation exceeds a third of their bound range are scaled down to it."""
        stds = self.stds
        slack = math.exp(1e-4) if self.countiter <= 2 else 1.0
        over = stds > self.maxstd * slack
        if over.any():
            self.scale[over] *= self.maxstd[over] / stds[over]

    def stop(self) -> bool:
        """Whether the search has ended (module docstring)."""
        if self.countiter == 0:
            return False
        if self.countevals - 1 >= self.max_evaluations:
            return True
        stds = self.stds
        if np.all(stds < self.tolx) and np.all(self.sigma * self.scale * self.pc < self.tolx):
            return True
        if np.any(stds > self._scale0 * TOLFACUPX):
            return True
        fit, hist = self._fitness, self._history
        if fit[-1] - fit[0] < self.tolfun and max(hist) - min(hist) < self.tolfun:
            return True
        if len(hist) > 9 and max(hist) - min(hist) < TOLFUNHIST:
            return True
        return self._flat > 1


def cma_strategy(start: np.ndarray, stds, half_range, popsize: int, max_evaluations: int, seed: int,
                 tolx: float, tolfun: float = 1e-5) -> CmaEs:
    """A search at ``start`` (n,) with per-parameter initial steps ``stds`` (global sigma 1), bounded to
    ``start +- half_range``, population ``popsize``, stopping after ``max_evaluations`` or at ``tolx`` /
    ``tolfun``."""
    return CmaEs(start, stds, half_range, popsize, max_evaluations, seed, tolx, tolfun)
