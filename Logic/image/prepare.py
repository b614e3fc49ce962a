"""Turn a stored X-ray into something comparable with a DRR: attenuation, exposed field, coarse binning.

A DRR is a line integral L (bone bright). A fluoroscopy frame stores detected intensity I ~ I0 exp(-L)
(bone dark); a processed radiograph often stores something like L already (bone bright). So:

- ``bone_dark`` images: ``L_est = -log(I / I_ref)`` with ``I_ref`` the 99.5th percentile in the field;
- bone-bright images: ``L_est = (I - I_min) / (I_max - I_min)`` (already attenuation-like, unknown scale).

The exposed field (circular collimation of an image intensifier, shutters) is found as the largest connected
region brighter than 5 % of the image range (bone-dark) after a small opening, then eroded by 2 % of its
size so the collimator edge and vignetting rim do not dominate gradient metrics.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def field_mask(pixels: np.ndarray, bone_dark: bool = True) -> np.ndarray:
    """Boolean (rows, cols) mask of the exposed field."""
    img = ndimage.uniform_filter(np.asarray(pixels, np.float32), 5)
    lo, hi = np.percentile(img, [0.5, 99.5])
    mask = img > lo + 0.05 * (hi - lo)
    mask = ndimage.binary_opening(mask, np.ones((5, 5), bool))
    labels, n = ndimage.label(mask)
    if n == 0:
        return np.ones(img.shape, bool)
    sizes = ndimage.sum(mask, labels, index=np.arange(1, n + 1))
    mask = ndimage.binary_fill_holes(labels == 1 + int(np.argmax(sizes)))
    if mask.mean() < 0.05:  # no usable field found: compare everything
        return np.ones(img.shape, bool)
    margin = max(1, int(0.02 * np.sqrt(mask.sum())))
    eroded = ndimage.binary_erosion(mask, iterations=margin)
    return eroded if eroded.mean() > 0.05 else mask


def attenuation(pixels: np.ndarray, mask: np.ndarray, bone_dark: bool = True) -> np.ndarray:
    """Line-integral-like image (bone bright) from stored pixels; 0 outside the field."""
    img = np.asarray(pixels, np.float64)
    inside = img[mask]
    if bone_dark:
        ref = np.percentile(inside, 99.5)
        floor = max(ref * 1e-4, 1e-6)
        out = -np.log(np.clip(img, floor, None) / ref)
    else:
        lo, hi = np.percentile(inside, [0.5, 99.5])
        out = (img - lo) / max(hi - lo, 1e-9)
    out[~mask] = 0.0
    return np.clip(out, 0.0, None).astype(np.float32)


def bin_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean over factor x factor blocks (drops the incomplete last row/column); matches ``binned`` intrinsics."""
    f = int(factor)
    rows, cols = (np.array(image.shape) // f) * f
    return image[:rows, :cols].reshape(rows // f, f, cols // f, f).mean(axis=(1, 3)).astype(np.float32)


def bin_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    """A binned pixel is inside when all its fine pixels are."""
    return bin_image(mask.astype(np.float32), factor) > 0.999


def coarse_factor(pixel_spacing_mm: tuple[float, float], target_mm: float = 4.0) -> int:
    """Binning factor that brings the detector pixel closest to ``target_mm`` (paper: 4 mm coarse images)."""
    return max(1, int(round(target_mm / max(min(pixel_spacing_mm), 1e-6))))
