"""Fast CPU DRR engine: exact ray-voxel traversal (Siddon / Amanatides-Woo), parallel over rays.

Physics (method paper Eq. 2): for the ray from the source to the centre of detector pixel (u, v),
``L(u, v) = sum_i mu_i l_i`` where ``l_i`` is the true length in mm of the ray inside voxel i (voxels are
boxes of the CT grid; ``mu`` constant in each), and the detected intensity is ``I = I0 exp(-L)``. This
module returns ``L`` (dimensionless line integral); ``intensity_from_line_integral`` gives I.

Geometry: the ray is traced in continuous voxel-index space (voxel centres at integer ijk, voxel i spans
[i - 0.5, i + 0.5]); an affine map preserves the ray parameter, so a parameter step ``da`` along the ray
from source (a = 0) to pixel (a = 1) is ``da * |pixel - source|`` mm whatever the spacing or obliquity.
Output images are float32, indexed ``image[row, column]``.

Speed (the numbers are exact; only the order of work changes):

- memory layout: the attenuation volume is traversed in a transposed copy whose contiguous (last) axis is
  the one the rays cross most often (the index axis closest to the beam direction), and whose middle axis
  follows the detector columns, so consecutive voxels of a ray and neighbouring rays of an image row share
  cache lines. The copy is made once per (level, layout) and cached (``clear_layout_cache`` frees it);
  MuLevel arrays are treated as immutable.
- traversal: one running flat offset, the beam axis tested first (the common case) against one precomputed
  limit, four beam-axis crossings per iteration when no other crossing intervenes, per-axis crossing
  counters instead of bounds checks, float64 ray parameters and sums, float32 voxels.
- empty space is not skipped: exact zero-run skipping along the beam axis was measured and saved nothing
  here (the extra table lookup per step cost as much as the skipped steps; CT air is noisy, not zero).
- parallel over image rows of every image of a batch (numba prange); small jobs (a 64^2 DRR of the 4 mm
  level) run on the calling thread. Kernels are compiled once and cached on disk (``carmreg.logic.jit.njit``;
  the first use in a fresh environment compiles for about 7-15 s, later processes load them in about 0.5 s;
  with no writable cache folder they are compiled in memory in every process).
"""

from __future__ import annotations

import threading
import weakref

import numba
import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.jit import njit

_BIG = 1e30
SERIAL_WORK_LIMIT = 2_000_000
"""Below this many (pixels x grid size) a render stays on the calling thread: a ~1 ms job otherwise waits for
the second core whenever another process holds it (measured: 64^2 at 4 mm, median 8 ms parallel vs 1.4 ms)."""


@njit(fastmath=True, inline="always")
def _clip_axis(s, d, n, t_in, t_out):
    """Intersect the ray parameter interval with the slab [-0.5, n - 0.5] of one index axis."""
    if abs(d) < 1e-12:
        if s < -0.5 or s > n - 0.5:
            return 1.0, 0.0
        return t_in, t_out
    ta = (-0.5 - s) / d
    tb = (n - 0.5 - s) / d
    if ta > tb:
        ta, tb = tb, ta
    return max(t_in, ta), min(t_out, tb)


@njit(fastmath=True, inline="always")
def _axis_start(s, d, t, n):
    """Voxel index at ray parameter t, step sign, parameter of the next boundary, parameter per voxel."""
    i = min(max(int(np.floor(s + t * d + 0.5)), 0), n - 1)
    if d > 1e-12:
        return i, 1, ((i + 0.5) - s) / d, 1.0 / d
    if d < -1e-12:
        return i, -1, ((i - 0.5) - s) / d, -1.0 / d
    return i, 1, _BIG, _BIG


@njit(fastmath=True, inline="always")
def _trace(flat, n0, n1, n2, s0, s1, s2, d0, d1, d2):
    """Integral of mu over the ray parameter along s -> s + d (ijk units of a C-ordered (n0, n1, n2) grid).

    Returns sum_i mu_i * (parameter interval inside voxel i); multiply by |d| in mm for the line integral.
    Axis 2 should be the axis the ray crosses most often: its crossing is tested first, and runs of four
    such crossings are taken at once (segment lengths dtk, the same sum up to rounding, ~1e-7 relative).
    Indices are kept inside the grid by per-axis crossing counters (no bounds checks; unsigned indexing
    skips numba's negative-index wraparound).
    """
    t_in, t_out = _clip_axis(s0, d0, n0, 0.0, 1.0)
    t_in, t_out = _clip_axis(s1, d1, n1, t_in, t_out)
    t_in, t_out = _clip_axis(s2, d2, n2, t_in, t_out)
    if t_in >= t_out:
        return 0.0
    tm = t_in + 1e-7 * (t_out - t_in)  # the entry voxel, nudged inside
    i, si, ti, dti = _axis_start(s0, d0, tm, n0)
    j, sj, tj, dtj = _axis_start(s1, d1, tm, n1)
    k, sk, tk, dtk = _axis_start(s2, d2, tm, n2)
    ci = n0 - 1 - i if si > 0 else i  # crossings left before leaving the grid along each axis
    cj = n1 - 1 - j if sj > 0 else j
    ck = n2 - 1 - k if sk > 0 else k
    step_i = si * n1 * n2
    step_j = sj * n2
    off = (i * n1 + j) * n2 + k  # flat index of the current voxel, always inside the grid
    t = t_in
    acc = 0.0
    lim = min(ti, tj, t_out)  # next event other than a beam-axis crossing
    dtk3 = 3.0 * dtk
    while True:
        if tk < lim:  # crossing along the contiguous (beam) axis: the common case
            if ck >= 4 and tk + dtk3 < lim:  # four in a row: the three middle voxels are crossed fully
                acc += flat[np.uint64(off)] * (tk - t) + dtk * (
                    flat[np.uint64(off + sk)] + flat[np.uint64(off + 2 * sk)] + flat[np.uint64(off + 3 * sk)])
                t = tk + dtk3
                tk = t + dtk
                ck -= 4
                off += 4 * sk
                continue
            acc += flat[np.uint64(off)] * (tk - t)
            t = tk
            tk += dtk
            if ck == 0:
                return acc
            ck -= 1
            off += sk
            continue
        if lim >= t_out:  # no crossing before the exit: last segment
            return acc + flat[np.uint64(off)] * (t_out - t)
        if ti <= tj:
            acc += flat[np.uint64(off)] * (ti - t)
            t = ti
            ti += dti
            if ci == 0:
                return acc
            ci -= 1
            off += step_i
        else:
            acc += flat[np.uint64(off)] * (tj - t)
            t = tj
            tj += dtj
            if cj == 0:
                return acc
            cj -= 1
            off += step_j
        lim = min(ti, tj, t_out)


@njit(fastmath=True, inline="always")
def _render_row(flat, shape, src_ijk, det0_ijk, du_ijk, dv_ijk, cam_u_mm, cam_v_mm, sdd_mm, k_per_mm2, centre_px,
                spans, out, b, v):
    """Row v of image b, columns spans[v, 0] <= u < spans[v, 1] (see _render_batch)."""
    n0, n1, n2 = shape
    s0, s1, s2 = src_ijk[b, 0], src_ijk[b, 1], src_ijk[b, 2]
    cv = cam_v_mm[v]
    for u in range(spans[v, 0], spans[v, 1]):
        p0 = det0_ijk[b, 0] + u * du_ijk[b, 0] + v * dv_ijk[b, 0]
        p1 = det0_ijk[b, 1] + u * du_ijk[b, 1] + v * dv_ijk[b, 1]
        p2 = det0_ijk[b, 2] + u * du_ijk[b, 2] + v * dv_ijk[b, 2]
        cu = cam_u_mm[u]
        if k_per_mm2 != 0.0:  # radial distortion: the pixel's ray goes to the ideal point d' (1 - k |d'|^2)
            shrink = k_per_mm2 * (cu * cu + cv * cv)
            ru, rv = (u - centre_px[0]) * shrink, (v - centre_px[1]) * shrink
            p0 -= ru * du_ijk[b, 0] + rv * dv_ijk[b, 0]
            p1 -= ru * du_ijk[b, 1] + rv * dv_ijk[b, 1]
            p2 -= ru * du_ijk[b, 2] + rv * dv_ijk[b, 2]
            length = np.sqrt((cu * cu + cv * cv) * (1.0 - shrink) ** 2 + sdd_mm * sdd_mm)
        else:
            length = np.sqrt(cu * cu + cv * cv + sdd_mm * sdd_mm)
        out[b, v, u] = length * _trace(flat, n0, n1, n2, s0, s1, s2, p0 - s0, p1 - s1, p2 - s2)


@njit(parallel=True, fastmath=True)
def _render_batch(mu, src_ijk, det0_ijk, du_ijk, dv_ijk, cam_u_mm, cam_v_mm, sdd_mm, k_per_mm2, centre_px, spans,
                  out):
    """out[b, v, u] = line integral for image b; per-image vectors in the (permuted) ijk units of ``mu``.

    The ray of pixel (u, v) runs from ``src_ijk[b]`` to ``det0_ijk[b] + u du_ijk[b] + v dv_ijk[b]`` and its
    length in mm is sqrt(cam_u_mm[u]^2 + cam_v_mm[v]^2 + sdd_mm^2); with ``k_per_mm2`` != 0 it runs to the
    ideal point of the pixel instead (``geometry.distortion``, about ``centre_px``, the principal point). Only
    the columns of ``spans`` (rows, 2) are traced; ``out`` keeps its values elsewhere. Parallel over image rows.
    """
    nb, rows = out.shape[0], out.shape[1]
    flat = mu.ravel()
    for task in numba.prange(nb * rows):
        _render_row(flat, mu.shape, src_ijk, det0_ijk, du_ijk, dv_ijk, cam_u_mm, cam_v_mm, sdd_mm, k_per_mm2,
                    centre_px, spans, out, task // rows, task % rows)


@njit(fastmath=True)
def _render_serial(mu, src_ijk, det0_ijk, du_ijk, dv_ijk, cam_u_mm, cam_v_mm, sdd_mm, k_per_mm2, centre_px, spans,
                   out):
    """_render_batch on the calling thread (small jobs: no wait for a busy second core)."""
    nb, rows = out.shape[0], out.shape[1]
    flat = mu.ravel()
    for task in range(nb * rows):
        _render_row(flat, mu.shape, src_ijk, det0_ijk, du_ijk, dv_ijk, cam_u_mm, cam_v_mm, sdd_mm, k_per_mm2,
                    centre_px, spans, out, task // rows, task % rows)


@njit(parallel=True)
def _copy_strided(view, out):
    """out[...] = view[...] for a 3-D strided view into a C-ordered array (the same numbers: a copy, with a cast
    to ``out``'s dtype rounding as numpy's does). numpy copies a transposed volume element by element in
    the worst order for the cache (0.5-0.6 s for a 360 x 269 x 133 CT here); this runs over the first output
    axis in parallel with the last one contiguous (25-45 ms)."""
    n0, n1, n2 = view.shape
    for i in numba.prange(n0):
        for j in range(n1):
            for k in range(n2):
                out[i, j, k] = view[i, j, k]


_layout_cache: dict[tuple[int, tuple[int, int, int]], tuple[weakref.ref, np.ndarray]] = {}
_layout_lock = threading.Lock()
_LAYOUT_CACHE_SIZE = 4


def clear_layout_cache() -> None:
    """Free the cached transposed volumes (they are rebuilt on the next render)."""
    with _layout_lock:
        _layout_cache.clear()


def transposed_mu(mu: np.ndarray, perm: tuple[int, int, int]) -> np.ndarray:
    """C-contiguous float32 ``mu.transpose(perm)``, cached per (array object, perm); no copy when possible.

    The cache holds at most a few arrays and drops an entry as soon as its source array is freed.
    """
    if perm == (0, 1, 2) and mu.dtype == np.float32 and mu.flags.c_contiguous:
        return mu
    key = (id(mu), perm)
    with _layout_lock:
        hit = _layout_cache.get(key)
        if hit is not None and hit[0]() is mu:
            _layout_cache[key] = _layout_cache.pop(key)  # most recently used last
            return hit[1]
    view = np.transpose(mu, perm)
    copy = np.empty(view.shape, np.float32)
    _copy_strided(view, copy)
    with _layout_lock:
        for stale in [k for k, (ref, _) in _layout_cache.items() if ref() is None]:
            del _layout_cache[stale]
        while len(_layout_cache) >= _LAYOUT_CACHE_SIZE:
            del _layout_cache[next(iter(_layout_cache))]
        # drop the copy as soon as its source array is freed
        _layout_cache[key] = (weakref.ref(mu, lambda _ref, key=key: _layout_cache.pop(key, None)), copy)
    return copy


def choose_layout(beam_ijk: np.ndarray, column_ijk: np.ndarray) -> tuple[int, int, int]:
    """Axis order for the traversal copy: beam axis last (contiguous), detector-column axis in the middle.

    beam_ijk: (b, 3) source -> detector-centre vectors in voxel units; column_ijk: (b, 3) one detector column
    step in voxel units. The axis with the largest summed |beam| component is crossed most often.
    """
    beam = np.abs(beam_ijk).sum(axis=0)
    last = int(np.argmax(beam))
    rest = [a for a in range(3) if a != last]
    cols = np.abs(column_ijk).sum(axis=0)
    middle = max(rest, key=lambda a: cols[a])
    first = next(a for a in rest if a != middle)
    return (first, middle, last)


def _ray_setup(level: MuLevel, geometry: CarmGeometry, poses: np.ndarray, intr: CarmIntrinsics):
    """Per-image source, pixel (0, 0) and per-pixel steps, all in the level's continuous ijk."""
    rotation, t = geometry.extrinsics(poses)                     # (b, 3, 3), (b, 3)
    lps_to_ijk = np.linalg.inv(level.ijk_to_lps)
    A, a = lps_to_ijk[:3, :3], lps_to_ijk[:3, 3]
    (du, dv), (u0, v0) = intr.pixel_spacing_mm, intr.principal_point_px
    cam_to_lps = np.swapaxes(rotation, -1, -2)                   # R^T
    source_lps = -np.einsum("bij,bj->bi", cam_to_lps, t)
    det0_cam = np.array([-u0 * du, -v0 * dv, intr.sdd_mm])
    det0_lps = np.einsum("bij,j->bi", cam_to_lps, det0_cam) + source_lps
    step_u_lps = cam_to_lps[:, :, 0] * du
    step_v_lps = cam_to_lps[:, :, 1] * dv
    cols, rows = intr.size_px
    cam_u = ((np.arange(cols) - u0) * du).astype(np.float64)
    cam_v = ((np.arange(rows) - v0) * dv).astype(np.float64)
    axis_ijk = cam_to_lps[:, :, 2] @ A.T                         # principal axis direction in ijk
    return (source_lps @ A.T + a, det0_lps @ A.T + a, step_u_lps @ A.T, step_v_lps @ A.T, cam_u, cam_v,
            axis_ijk)


def row_spans(mask: np.ndarray, margin_px: int = 1) -> np.ndarray:
    """(rows, 2) int64 [first, last + 1) columns per row of ``mask`` (rows, cols) grown by ``margin_px``
    columns and rows (so central differences inside the mask see rendered neighbours); (0, 0) for rows
    with nothing to render."""
    from scipy import ndimage

    grown = ndimage.binary_dilation(mask, iterations=margin_px) if margin_px > 0 else np.asarray(mask, bool)
    spans = np.zeros((grown.shape[0], 2), np.int64)
    rows = np.flatnonzero(grown.any(axis=1))
    spans[rows, 0] = np.argmax(grown[rows], axis=1)
    spans[rows, 1] = grown.shape[1] - np.argmax(grown[rows, ::-1], axis=1)
    return spans


def render_line_integrals(level: MuLevel, geometry: CarmGeometry, poses,
                          intrinsics: CarmIntrinsics | None = None, spans: np.ndarray | None = None) -> np.ndarray:
    """Line integrals L (float32) for one pose -> (rows, cols), or poses (b, 6) -> (b, rows, cols).

    ``intrinsics`` overrides the geometry's detector (e.g. a binned one for the coarse stage). ``spans``
    (``row_spans`` of a region, e.g. the exposed field) limits the traced pixels to it; the others are 0.
    A detector with radial distortion (``CarmIntrinsics.distortion_mm``) is rendered through it: each pixel's
    ray goes to its ideal point (``geometry.distortion``); without, the rays are traced exactly as always.
    """
    intr = intrinsics or geometry.intrinsics
    single = isinstance(poses, CarmPose) or np.asarray(poses).ndim == 1
    p = np.atleast_2d(poses.as_array() if isinstance(poses, CarmPose) else np.asarray(poses, float))
    src, det0, su, sv, cam_u, cam_v, axis = _ray_setup(level, geometry, p, intr)
    perm = choose_layout(axis, su)
    mu = transposed_mu(level.mu_per_mm, perm)
    order = list(perm)
    cols, rows = intr.size_px
    if spans is None:
        spans = np.tile(np.array([0, cols], np.int64), (rows, 1))
        out = np.empty((len(p), rows, cols), dtype=np.float32)
    else:
        spans = np.ascontiguousarray(np.clip(spans, 0, cols), dtype=np.int64)
        out = np.zeros((len(p), rows, cols), dtype=np.float32)
    centre = np.asarray(intr.principal_point_px, np.float64)
    kernel = _render_serial if out.size * sum(mu.shape) < SERIAL_WORK_LIMIT else _render_batch
    kernel(mu, np.ascontiguousarray(src[:, order]), np.ascontiguousarray(det0[:, order]),
           np.ascontiguousarray(su[:, order]), np.ascontiguousarray(sv[:, order]),
           cam_u, cam_v, float(intr.sdd_mm), float(intr.distortion.k_per_mm2), centre, spans, out)
    return out[0] if single else out


def intensity_from_line_integral(line_integral: np.ndarray, i0: float = 1.0) -> np.ndarray:
    """Beer-Lambert: I = I0 exp(-L)."""
    return (i0 * np.exp(-np.asarray(line_integral, dtype=np.float64))).astype(np.float32)
