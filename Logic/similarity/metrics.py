"""Image similarity between one X-ray and a stack of DRRs (method paper Eq. 4-13, plus GC and GO).

Every metric takes ``fixed`` (h, w) and ``moving`` (n, h, w) float arrays on the same pixel grid and a boolean
``mask`` (h, w) of pixels to compare (the X-ray's exposed field), and returns (n,) scores where **larger is more
similar**. Images are compared as attenuation (line-integral-like: bone bright); see ``xray_prep``.

- NCC  (Eq. 13): Pearson correlation of intensities in the mask.
- PSNR (Eq. 10-11): 10 log10(R^2 / MSE) after each image is scaled to [0, 1] by its 1st-99th percentile in the
  mask (R = 1), since DRR and X-ray intensities have different units.
- SSIM (Eq. 12): mean over the mask (windows wholly inside it) of the local SSIM (7x7 uniform windows,
  C1 = 0.01^2, C2 = 0.03^2) of the [0, 1]-scaled images.
- MI   (Eq. 4-6): H(A) + H(B) - H(A, B) from a 32x32 joint histogram of the scaled images, in nats.
- GI   (Eq. 7-9): mean over the mask of w min(|grad A|, |grad B|), w = (cos a + 1) / 2, gradients of the
  z-scored images (central differences).
- GC: gradient correlation, mean of the NCC of the column- and row-derivative images.
- GO: gradient orientation (De Silva et al. 2016): mean over pixels where both gradient magnitudes exceed their
  median of (cos 2a + 1) / 2 = cos^2 a, insensitive to polarity and to the strength of edges.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from carmreg.logic.similarity.gc_kernel import gc_scores

METRICS = ("gc", "go", "ncc", "gi", "mi", "psnr", "ssim")


def _masked(stack: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(n, h, w) -> (n, m) values inside the mask."""
    return stack.reshape(stack.shape[0], -1)[:, mask.ravel()]


def _zscore(values: np.ndarray) -> np.ndarray:
    """Row-wise zero mean, unit norm; constant rows become zeros."""
    v = values - values.mean(axis=-1, keepdims=True)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 1e-12)


def _taken_in(moving: np.ndarray, dtype, gc: bool) -> np.ndarray:
    """``moving`` in the precision ``dtype`` the images are taken in; GC (``gc``) reads a float32 stack as it is
    (exact in either precision: ``gc_kernel`` differences and sums in float64)."""
    moving = np.asarray(moving)
    return moving if gc and moving.dtype == np.float32 else moving.astype(dtype, copy=False)


def _unit_range(stack: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Scale each image to [0, 1] by its 1st-99th percentile inside the mask (clipped)."""
    vals = _masked(stack, mask)
    lo = np.percentile(vals, 1, axis=1)[:, None, None]
    hi = np.percentile(vals, 99, axis=1)[:, None, None]
    return np.clip((stack - lo) / np.maximum(hi - lo, 1e-9), 0.0, 1.0).astype(np.float32)


def ncc(fixed, moving, mask):
    f = _zscore(_masked(fixed[None], mask))
    return _zscore(_masked(moving, mask)) @ f[0]


def psnr(fixed, moving, mask):
    f = _masked(_unit_range(fixed[None], mask), mask)
    m = _masked(_unit_range(moving, mask), mask)
    mse = np.mean((m - f) ** 2, axis=1)
    return 10.0 * np.log10(1.0 / np.maximum(mse, 1e-12))


def ssim(fixed, moving, mask, window: int = 7):
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    a = _unit_range(fixed[None], mask)
    b = _unit_range(moving, mask)
    size = (1, window, window)
    mu_a, mu_b = ndimage.uniform_filter(a, size), ndimage.uniform_filter(b, size)
    var_a = ndimage.uniform_filter(a * a, size) - mu_a ** 2
    var_b = ndimage.uniform_filter(b * b, size) - mu_b ** 2
    cov = ndimage.uniform_filter(a * b, size) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    inner = ndimage.binary_erosion(mask, np.ones((window, window), bool))
    return _masked(s, inner if inner.any() else mask).mean(axis=1)


def mi(fixed, moving, mask, bins: int = 32):
    f = np.minimum((_masked(_unit_range(fixed[None], mask), mask)[0] * bins).astype(np.int64), bins - 1)
    m = np.minimum((_masked(_unit_range(moving, mask), mask) * bins).astype(np.int64), bins - 1)
    n, npx = m.shape
    index = (np.arange(n)[:, None] * bins * bins + m * bins + f[None, :]).ravel()
    joint = np.bincount(index, minlength=n * bins * bins).reshape(n, bins, bins) / npx
    pm, pf = joint.sum(axis=2), joint.sum(axis=1)

    def entropy(p, axes):
        return -np.sum(np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0), axis=axes)

    return entropy(pm, 1) + entropy(pf, 1) - entropy(joint, (1, 2))


def _gradients(stack: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference derivatives along columns (gu) and rows (gv) of z-scored images."""
    vals = _masked(stack, mask)
    mean = vals.mean(axis=1)[:, None, None]
    std = np.maximum(vals.std(axis=1), 1e-9)[:, None, None]
    z = (stack - mean) / std
    gu = np.zeros_like(z)
    gv = np.zeros_like(z)
    gu[:, :, 1:-1] = 0.5 * (z[:, :, 2:] - z[:, :, :-2])
    gv[:, 1:-1, :] = 0.5 * (z[:, 2:, :] - z[:, :-2, :])
    return gu, gv


def _inner_mask(mask: np.ndarray) -> np.ndarray:
    """Mask pixels whose 3x3 neighbourhood is inside the mask (no gradients across the field edge)."""
    inner = ndimage.binary_erosion(mask, np.ones((3, 3), bool))
    return inner if inner.any() else mask


def _paired_gradients(fixed, moving, mask):
    """Column and row derivatives of both images at the pixels inside the (eroded) mask: (n or 1, m) each."""
    inner = _inner_mask(mask)
    fu, fv = _gradients(fixed[None], mask)
    mu, mv = _gradients(moving, mask)
    return tuple(_masked(g, inner) for g in (fu, fv, mu, mv))


def gi(fixed, moving, mask):
    fu, fv, mu, mv = _paired_gradients(fixed, moving, mask)
    fmag, mmag = np.hypot(fu, fv), np.hypot(mu, mv)
    cos = (fu * mu + fv * mv) / np.maximum(fmag * mmag, 1e-12)
    return np.mean((cos + 1.0) / 2.0 * np.minimum(fmag, mmag), axis=1)


class GradientCorrelation:
    """GC against one fixed image, its half prepared once (an optimiser scores thousands of DRRs against the
    same X-ray): 0.5 (NCC(du F, du M) + NCC(dv F, dv M)) over the pixels whose 3x3 neighbourhood lies in the
    mask, du and dv central differences along columns and rows. NCC ignores a positive scale and an offset, so
    the derivatives are taken of the images as they are (the same numbers as of z-scored images). The moving
    half is ``gc_kernel.gc_scores`` (compiled, sums in float64); the fixed half is made here in the fixed image's
    dtype."""

    def __init__(self, fixed: np.ndarray, mask: np.ndarray):
        inner = ndimage.binary_erosion(mask, np.ones((3, 3), bool))  # border_value 0: never an image edge
        self.index, self.width = np.flatnonzero(inner), mask.shape[1]
        flat, i, w = np.asarray(fixed).ravel(), self.index, self.width
        self.fixed_u, self.fixed_v = ((_zscore(flat[i + 1] - flat[i - 1]), _zscore(flat[i + w] - flat[i - w]))
                                      if i.size else (np.zeros(0), np.zeros(0)))  # nothing to compare: scores 0

    def __call__(self, moving: np.ndarray) -> np.ndarray:
        return gc_scores(moving, self.index, self.width, self.fixed_u[None], self.fixed_v[None])[:, 0]


def gc(fixed, moving, mask):
    return GradientCorrelation(fixed, mask)(moving)


def gc_maps(fixed_images: list, moving: np.ndarray, mask: np.ndarray, dtype=np.float32) -> list[np.ndarray]:
    """``[similarity("gc", f, moving, mask, dtype=dtype) for f in fixed_images]`` bit for bit, with each moving
    image read once for every fixed image (``gc_against_each``): several GC maps over a DRR database for little
    more than one."""
    return list(gc_against_each(np.asarray(fixed_images), moving, mask, dtype).T)


def gc_against_each(fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray, dtype=np.float32) -> np.ndarray:
    """(n, k) GC of every moving image (n, h, w) with every fixed image (k, h, w) on one ``mask``: column j is
    ``gc(fixed[j], moving, mask)`` bit for bit, the fixed images taken in ``dtype`` (``gc_kernel``: each moving
    image read once for all k, so a GC map over a DRR database for k turns of the X-ray costs about one map)."""
    prepared = [GradientCorrelation(f, mask) for f in np.asarray(fixed, dtype=dtype)]
    first = prepared[0]
    fixed_u = np.stack([g.fixed_u for g in prepared])  # (k, m) unit rows
    fixed_v = np.stack([g.fixed_v for g in prepared])
    return gc_scores(_taken_in(moving, dtype, True), first.index, first.width, fixed_u, fixed_v)


def go(fixed, moving, mask):
    fu, fv, mu, mv = _paired_gradients(fixed, moving, mask)
    fmag, mmag = np.hypot(fu, fv), np.hypot(mu, mv)
    cos2 = (fu * mu + fv * mv) ** 2 / np.maximum((fmag * mmag) ** 2, 1e-24)
    strong = (fmag > np.median(fmag)) & (mmag > np.median(mmag, axis=1, keepdims=True))
    return np.sum(cos2 * strong, axis=1) / np.maximum(strong.sum(axis=1), 1)


FUNCTIONS = {"gc": gc, "go": go, "ncc": ncc, "gi": gi, "mi": mi, "psnr": psnr, "ssim": ssim}


PREPARED = {"gc": GradientCorrelation}
"""Metrics with a prepared form: the fixed image's half computed once (else the plain function is called)."""


def prepare(metric: str, fixed: np.ndarray, mask: np.ndarray | None = None, chunk: int = 512, dtype=np.float32):
    """``scores(moving)`` -> (n,) float64 similarity of ``moving`` (n, h, w) against ``fixed`` (h, w): the same
    numbers as ``similarity``, with whatever depends only on ``fixed`` and ``mask`` computed here, once.

    ``dtype``: the precision the images are taken in. GC sums in float64 whatever it is, in a fixed order
    (``gc_kernel``), and reads a float32 stack as it is (exact in either precision); for the other metrics float64
    makes the scores reproducible across processes to ~1e-15 (float32 reductions in BLAS and SIMD loops can round
    differently with memory alignment, which flips close rankings in an optimiser).
    """
    if metric not in FUNCTIONS:
        raise ValueError(f"unknown metric {metric!r}; choose one of {', '.join(METRICS)}")
    fixed = np.asarray(fixed, dtype=dtype)
    mask = np.ones(fixed.shape, bool) if mask is None else np.asarray(mask, bool)
    if metric in PREPARED:
        score = PREPARED[metric](fixed, mask)
    else:
        def score(moving):
            return FUNCTIONS[metric](fixed, moving, mask)

    def scores(moving: np.ndarray) -> np.ndarray:
        moving = _taken_in(moving, dtype, metric in PREPARED).reshape(-1, *fixed.shape)
        return np.concatenate([score(moving[i:i + chunk]) for i in range(0, len(moving), chunk)]).astype(np.float64)

    return scores


def similarity(metric: str, fixed: np.ndarray, moving: np.ndarray, mask: np.ndarray | None = None,
               chunk: int = 512, dtype=np.float32) -> np.ndarray:
    """Scores (n,) of ``moving`` (n, h, w) against ``fixed`` (h, w); larger = more similar. Chunked for memory;
    ``dtype`` as in ``prepare``."""
    return prepare(metric, fixed, mask, chunk, dtype)(moving)
