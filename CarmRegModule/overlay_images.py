"""Composite images for checking a registration: blend, checkerboard and edge overlays (numpy only).

Inputs are two images of the same shape indexed image[row, column]: the X-ray as displayed and the DRR line
integral at the found pose (bone bright). Each is normalised to 0..1 between its 1st and 99.5th percentile
(``normalise``); the X-ray is first flipped to bone-bright when ``bone_dark`` so both read alike.
"""

from __future__ import annotations

import numpy as np

MODES = ("blend", "checkerboard", "edges")
DRR_TINT = np.array([1.0, 0.62, 0.25], np.float32)  # DRR drawn in amber in blend mode
EDGE_COLOR = np.array([0.25, 1.0, 0.45], np.float32)


def normalise(image: np.ndarray, low_pct: float = 1.0, high_pct: float = 99.5) -> np.ndarray:
    """Linear map of the percentile range to 0..1 (float32, clipped)."""
    img = np.asarray(image, np.float32)
    sample = img[:: max(1, img.shape[0] // 256), :: max(1, img.shape[1] // 256)]
    lo, hi = np.percentile(sample[np.isfinite(sample)], [low_pct, high_pct])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def xray_bone_bright(pixels: np.ndarray, bone_dark: bool) -> np.ndarray:
    """The X-ray normalised to 0..1 with bone bright."""
    x = normalise(pixels)
    return 1.0 - x if bone_dark else x


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
    """RGB: the X-ray in grey with the DRR's bone edges (gradient magnitude, top 10 %) in green."""
    from scipy import ndimage

    smooth = ndimage.gaussian_filter(drr01, 1.5)
    grad = np.hypot(ndimage.sobel(smooth, 0), ndimage.sobel(smooth, 1))
    threshold = np.percentile(grad, 90)
    edge = np.clip((grad - threshold) / max(grad.max() - threshold, 1e-6) * 3.0, 0, 1) * float(strength)
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
