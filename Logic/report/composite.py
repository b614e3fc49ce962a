"""Composite images for checking a registration: blend, checkerboard and edge overlays (numpy only).

Inputs are two images of the same shape indexed image[row, column]: the X-ray as displayed and the DRR line
integral at the found pose (bone bright). Each is normalised to 0..1 inside the exposed field (``normalise``;
black outside it): the X-ray between its display range (``image.field.display_range``: the field's 1st-99th
percentiles without clipped pixels, the X-ray view's default contrast), the DRR between its 1st and 99.5th
percentiles; the X-ray is flipped to bone-bright when ``bone_dark`` so both read alike.
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.image.field import DISPLAY_PERCENTILES, display_range

MODES = ("blend", "checkerboard", "edges")
DRR_TINT = np.array([1.0, 0.62, 0.25], np.float32)  # DRR drawn in amber in blend mode
EDGE_COLOR = np.array([0.25, 1.0, 0.45], np.float32)


def normalise(image: np.ndarray, mask: np.ndarray | None = None, low_pct: float = 1.0,
              high_pct: float = 99.5, drop_clipped: bool = False) -> np.ndarray:
    """Linear map of the percentile range (inside ``mask``, the exposed field; ``image.field.display_range``)
    to 0..1; 0 outside the mask."""
    img = np.asarray(image, np.float32)
    lo, hi = display_range(img, mask, (low_pct, high_pct), drop_clipped)
    out = np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    return out if mask is None else np.where(mask, out, 0.0).astype(np.float32)


def xray_bone_bright(pixels: np.ndarray, bone_dark: bool, mask: np.ndarray | None = None) -> np.ndarray:
    """The X-ray normalised to 0..1 over its display range (the X-ray view's default contrast) with bone
    bright; 0 (black) outside the exposed field ``mask``."""
    x = normalise(pixels, mask, *DISPLAY_PERCENTILES, drop_clipped=True)
    x = 1.0 - x if bone_dark else x
    return x if mask is None else np.where(mask, x, 0.0).astype(np.float32)


def blend(xray01: np.ndarray, drr01: np.ndarray, alpha: float) -> np.ndarray:
    """RGB: grey X-ray with the DRR added in amber; alpha = 0 shows only the X-ray, 1 only the DRR."""
    a = float(np.clip(alpha, 0.0, 1.0))
    grey = (1.0 - a) * xray01[..., None] * np.ones(3, np.float32)
    return to_u8(grey + a * drr01[..., None] * DRR_TINT[None, None, :] / DRR_TINT.max())


def checkerboard(xray01: np.ndarray, drr01: np.ndarray, tiles: int = 8) -> np.ndarray:
    """RGB: alternating square tiles of X-ray (grey) and DRR (amber), ``tiles`` along the longer side."""
    rows, cols = xray01.shape
    size = max(1, int(np.ceil(max(rows, cols) / max(int(tiles), 1))))
    ii, jj = np.meshgrid(np.arange(rows) // size, np.arange(cols) // size, indexing="ij")
    use_drr = ((ii + jj) % 2).astype(bool)
    grey = xray01[..., None] * np.ones(3, np.float32)
    tinted = drr01[..., None] * DRR_TINT[None, None, :] / DRR_TINT.max()
    return to_u8(np.where(use_drr[..., None], tinted, grey))


def edges(xray01: np.ndarray, drr01: np.ndarray, strength: float = 1.0) -> np.ndarray:
    """RGB: the X-ray in grey with the DRR's strongest edges (top 8 % gradient, Gaussian sigma 2 px) in green.

    Only edges well inside the DRR's footprint count, so the border of the CT volume (where rays leave the
    scan) is not mistaken for anatomy."""
    from scipy import ndimage

    footprint = ndimage.binary_erosion(drr01 > 0.02, iterations=max(3, drr01.shape[0] // 100))
    smooth = ndimage.gaussian_filter(drr01, 2.0)
    grad = np.hypot(ndimage.sobel(smooth, 0), ndimage.sobel(smooth, 1)) * footprint
    inside = grad[footprint] if footprint.any() else grad.ravel()
    threshold = np.percentile(inside, 92)
    edge = np.clip((grad - threshold) / max(float(grad.max() - threshold), 1e-6) * 3.0, 0, 1) * float(strength)
    edge = np.clip(edge, 0.0, 1.0)
    grey = xray01[..., None] * np.ones(3, np.float32) * 0.85
    return to_u8(grey * (1 - edge[..., None]) + edge[..., None] * EDGE_COLOR[None, None, :])


def composite(mode: str, xray01: np.ndarray, drr01: np.ndarray, alpha: float = 0.5, tiles: int = 8) -> np.ndarray:
    if mode == "blend":
        return blend(xray01, drr01, alpha)
    if mode == "checkerboard":
        return checkerboard(xray01, drr01, tiles)
    if mode == "edges":
        return edges(xray01, drr01, max(alpha, 0.2) * 2)
    raise ValueError(f"unknown overlay mode {mode!r}; choose one of {', '.join(MODES)}")


def to_u8(rgb01: np.ndarray) -> np.ndarray:
    return (np.clip(rgb01, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
