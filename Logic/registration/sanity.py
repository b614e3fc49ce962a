"""Content sanity before any registration: the CT must look like a CT, the X-ray like an X-ray.

A registration on garbage still "converges" and, with three consistent clicks, would be reported OK. These
checks refuse such inputs first (InputFileError naming the file; exit code 2 on the command line):

CT (HU): every value within [-5000, 50000] HU (a float block of 3e38 is not a tissue), and in a sample of
the voxels at least ``MIN_SOFT_TISSUE`` of soft tissue (-200..150 HU) and ``MIN_BONE`` of bone (> 150 HU),
at most ``MAX_BONE`` of bone (an all-air, all-water or all-metal volume is not a patient's spine).

X-ray: not every value <= 0 (detected intensities are positive), and structure rather than noise: after
averaging 4 x 4 pixel blocks (which keeps anatomy and divides noise by 4), the correlation of horizontally and
vertically adjacent blocks must reach ``MIN_NEIGHBOUR_CORRELATION`` (anatomy: > 0.9; white noise: about 0).
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.errors import InputFileError

HU_RANGE = (-5000.0, 50000.0)
MIN_SOFT_TISSUE = 0.02
MIN_BONE = 0.0005
MAX_BONE = 0.7
MIN_NEIGHBOUR_CORRELATION = 0.5
SAMPLE_VOXELS = 2_000_000


def _sample(values: np.ndarray, n: int) -> np.ndarray:
    """A strided sample of about ``n`` voxels (every k-th along each axis)."""
    step = max(1, int(np.ceil((values.size / n) ** (1 / values.ndim))))
    return np.asarray(values[tuple(slice(None, None, step) for _ in range(values.ndim))], dtype=np.float64)


def check_ct_content(hu: np.ndarray, source: str) -> dict:
    """Refuse a volume that is not a CT in HU; returns the tissue fractions measured (air, soft, bone)."""
    lo, hi = float(np.min(hu)), float(np.max(hu))
    if lo < HU_RANGE[0] or hi > HU_RANGE[1]:
        raise InputFileError(f"{source}: voxel values reach {lo:.4g} .. {hi:.4g}, outside any CT in Hounsfield "
                             f"units ({HU_RANGE[0]:.0f} to {HU_RANGE[1]:.0f}); the file is damaged or not a CT "
                             "in HU (check its rescale slope/intercept)")
    sample = _sample(hu, SAMPLE_VOXELS)
    fractions = {"air": float(np.mean(sample < -500)),
                 "soft_tissue": float(np.mean((sample >= -200) & (sample <= 150))),
                 "bone": float(np.mean(sample > 150))}
    text = ", ".join(f"{k.replace('_', ' ')} {100 * v:.2f} %" for k, v in fractions.items())
    if fractions["soft_tissue"] < MIN_SOFT_TISSUE or not MIN_BONE <= fractions["bone"] <= MAX_BONE:
        raise InputFileError(f"{source}: does not look like a CT of a patient ({text}; a spine CT has soft "
                             f"tissue >= {100 * MIN_SOFT_TISSUE:g} % and bone {100 * MIN_BONE:g}-"
                             f"{100 * MAX_BONE:g} %): give the patient's CT in Hounsfield units")
    return fractions


def neighbour_correlation(pixels: np.ndarray, block: int = 4) -> float:
    """Mean correlation of horizontally and vertically adjacent ``block`` x ``block`` means (1 = smooth
    structure, 0 = white noise)."""
    rows, cols = (s // block * block for s in pixels.shape)
    if rows < 2 * block or cols < 2 * block:
        block = 1
        rows, cols = pixels.shape
    binned = np.asarray(pixels[:rows, :cols], np.float64).reshape(rows // block, block, cols // block,
                                                                  block).mean(axis=(1, 3))
    values = []
    for a, b in ((binned[:, :-1], binned[:, 1:]), (binned[:-1, :], binned[1:, :])):
        a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
        denom = np.sqrt(np.dot(a, a) * np.dot(b, b))
        values.append(float(np.dot(a, b) / denom) if denom > 0 else 0.0)
    return float(np.mean(values))


def check_xray_content(pixels: np.ndarray, source: str) -> float:
    """Refuse an image that is not an X-ray (all values <= 0, or noise without structure); returns the
    neighbour correlation."""
    hi = float(np.max(pixels))
    if hi <= 0:
        raise InputFileError(f"{source}: every pixel is <= 0 (maximum {hi:g}); an X-ray holds detected "
                             "intensities, which are positive: export the image itself, not a processed or "
                             "log-subtracted one")
    r = neighbour_correlation(pixels)
    if r < MIN_NEIGHBOUR_CORRELATION:
        raise InputFileError(f"{source}: the image is noise, not anatomy (correlation of neighbouring 4x4-pixel "
                             f"blocks {r:.2f}, an X-ray has more than {MIN_NEIGHBOUR_CORRELATION}); give the "
                             "X-ray frame itself")
    return r
