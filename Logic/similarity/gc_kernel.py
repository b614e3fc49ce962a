"""Gradient correlation of many moving images in one compiled pass each (``metrics.GradientCorrelation``'s
moving half, ``metrics.gc_maps``, ``metrics.gc_against_each``).

For a moving image M (flattened, rows of ``width`` pixels) and k fixed images, over the m inner pixels p of the
field (those whose 3 x 3 neighbourhood lies in it, so every neighbour below is in the image)::

    a_p = M[p + 1] - M[p - 1],      c_p = M[p + width] - M[p - width]          (2 du, 2 dv; float64)
    GC_j = 0.5 (sum_p (a_p - mean a) U_jp / |a - mean a|  +  sum_p (c_p - mean c) V_jp / |c - mean c|)

``U``, ``V`` (k, m): the fixed images' derivatives at the same pixels, each row zero-mean and unit-norm
(``metrics._zscore``). A moving image whose derivatives along an axis are constant (norm <= 1e-12) scores 0 along
it, as numpy's form did. Pixels are read in their own dtype and differenced in float64, so a float32 stack gives
what its float64 copy gives.

The derivatives are gathered once into two float64 rows, then centred, then correlated with each fixed row;
every sum in float64 in pixel order, one image per task: the same numbers on every run and any number of
threads, within ~1e-15 of the numpy form it replaces (whose pairwise sums and BLAS products rounded
differently). Why compiled: the image refinement scores its population of
12-16 DRRs of ~150 x 150 px about 900 times a registration; numpy took ~4.6 ms a population (a float64 copy, two
difference images, a gather, centring, norms and a product, each a pass over memory), this takes ~0.58 ms.
"""

from __future__ import annotations

import numba
import numpy as np

from carmreg.logic.jit import njit

SERIAL_WORK_LIMIT = 2_000_000
"""Below this many (images x inner pixels x (k + 2)) the scores are computed on the calling thread (an
optimiser's population: ~0.5 ms, less than waiting for a second core that another process may hold)."""
NORM_FLOOR = 1e-12
"""A centred derivative image of norm at most this is constant: its correlation is 0."""


@njit(inline="always")
def _image_gc(flat, index, width, fixed_u, fixed_v, out):
    """out[j] = GC of the flattened image ``flat`` with fixed image j (module docstring)."""
    m, k = index.size, fixed_u.shape[0]
    a, c = np.empty(m), np.empty(m)
    sum_u, sum_v = 0.0, 0.0
    for p in range(m):
        i = index[p]
        a[p] = np.float64(flat[i + 1]) - np.float64(flat[i - 1])
        c[p] = np.float64(flat[i + width]) - np.float64(flat[i - width])
        sum_u += a[p]
        sum_v += c[p]
    mean_u, mean_v = sum_u / m, sum_v / m
    squares_u, squares_v = 0.0, 0.0
    for p in range(m):
        a[p] -= mean_u
        c[p] -= mean_v
        squares_u += a[p] * a[p]
        squares_v += c[p] * c[p]
    norm_u, norm_v = np.sqrt(squares_u), np.sqrt(squares_v)
    for j in range(k):
        dot_u, dot_v = 0.0, 0.0
        for p in range(m):
            dot_u += a[p] * fixed_u[j, p]
            dot_v += c[p] * fixed_v[j, p]
        along_u = dot_u / norm_u if norm_u > NORM_FLOOR else 0.0
        along_v = dot_v / norm_v if norm_v > NORM_FLOOR else 0.0
        out[j] = 0.5 * (along_u + along_v)


@njit()
def _serial(moving, index, width, fixed_u, fixed_v, out):
    for b in range(moving.shape[0]):
        _image_gc(moving[b], index, width, fixed_u, fixed_v, out[b])


@njit(parallel=True)
def _parallel(moving, index, width, fixed_u, fixed_v, out):
    for b in numba.prange(moving.shape[0]):
        _image_gc(moving[b], index, width, fixed_u, fixed_v, out[b])


def gc_scores(moving: np.ndarray, index: np.ndarray, width: int, fixed_u: np.ndarray, fixed_v: np.ndarray
              ) -> np.ndarray:
    """(n, k) float64 GC of each moving image (n, h, w) (float32 or float64: ``metrics._taken_in``) with each fixed
    image whose unit derivatives at the inner pixels ``index`` (m,) (flat indices into an image of ``width``
    columns) are the rows of ``fixed_u`` and ``fixed_v`` (k, m); see the module docstring."""
    moving = np.asarray(moving)
    flat = np.ascontiguousarray(moving.reshape(len(moving), -1))
    out = np.zeros((len(flat), len(fixed_u)))
    if len(flat) == 0 or index.size == 0:
        return out
    index = np.ascontiguousarray(index, dtype=np.int64)
    fixed_u, fixed_v = np.ascontiguousarray(fixed_u), np.ascontiguousarray(fixed_v)
    kernel = _serial if len(flat) * index.size * (len(fixed_u) + 2) < SERIAL_WORK_LIMIT else _parallel
    kernel(flat, index, int(width), fixed_u, fixed_v, out)
    return out
