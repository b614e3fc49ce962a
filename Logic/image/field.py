"""The exposed field of a stored X-ray: where the beam reached the detector, found without knowing the polarity.

Outside the field (the collimator's shadow of an image intensifier's circle, shutters, the corners a circular
field leaves) a stored image is *flat* and sits at one *extreme* of its range - black in most exports, white in
some (bone-dark fluoroscopy whose corners are blanked white, inverted displays). So the background is::

    B = union over e in {low end, high end} of the connected regions of
        { |I_s - e| <= 5 % of the range  and  local std(I_s, 5 x 5 px) <= 2 % of the range }
    that touch the image border, grown by the 2 px the 5 x 5 window blurs across the field's edge,

with ``I_s`` the image after a 3 x 3 mean and the range the 0.5-99.5th percentiles. The field is the largest
connected part of the rest (holes filled: burnt-in text and dense metal inside the field stay in), eroded by
2 % of its size so the collimator edge and the vignetting rim do not dominate gradient metrics. When nothing
plausible is found (< 5 % of the image) the whole image is the field. The rule does not depend on which way bone
is displayed, so it can be found *before* the polarity (``appearance``).

``round_field`` tells an image intensifier's round field from a rectangular collimation (the pipeline warns when
such an image comes without a distortion calibration). The user may say the whole image is exposed instead
(``FIELDS``: ``--field whole``, the window's and the Slicer module's X-ray field), when the rule takes exposed
anatomy for background; ``field_record`` is what result.json keeps of the field used, and how it was decided.

``display_range`` is the X-ray's default contrast, used by the window's X-ray view and by every overlay (window,
report page, ``overlay.png``): the 1st-99th percentiles of the field's pixels, clipped pixels left out - those at
the field's lowest or highest value when they are more than 0.1 % of it (burned-out air at the detector's
saturation, zero-filled metal), which would otherwise stretch the window and flatten the bone.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

EXTREME_FRACTION = 0.05   # background within this fraction of the range of an extreme value
FLAT_FRACTION = 0.02      # and locally flat: 5 x 5 std below this fraction of the range
CLIPPED_FRACTION = 0.001  # a field's extreme value held by more than this fraction of its pixels is clipping
DISPLAY_PERCENTILES = (1.0, 99.0)
SHUTTER_STEP = 0.25       # a shutter edge's median step, fraction of the range (inside_shutters)
SHUTTER_ZONE = 0.4        # searched within this outer fraction of the field's box on each side
SHUTTER_HALF_WIDTH = 2    # the step is taken across 2 x this many pixels
SAMPLE_SIZE = 250_000     # percentiles from about this many pixels (a regular subsample)
FIELDS = ("auto", "whole")
"""The field settings (``RegistrationParameters.xray_field``): found from the image (``field_mask``), or the whole
image."""


def _border_connected(candidates: np.ndarray) -> np.ndarray:
    """The connected regions of ``candidates`` that touch the image border."""
    labels, n = ndimage.label(candidates)
    if n == 0:
        return np.zeros_like(candidates)
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    touching = np.unique(edge[edge > 0])
    return np.isin(labels, touching)


def field_mask(pixels: np.ndarray) -> np.ndarray:
    """Boolean (rows, cols) mask of the exposed field (module docstring); polarity-independent."""
    img = ndimage.uniform_filter(np.asarray(pixels, np.float32), 3)
    lo, hi = np.percentile(img, [0.5, 99.5])
    span = float(hi - lo)
    if not np.isfinite(span) or span <= 0:
        return np.ones(img.shape, bool)
    mean = ndimage.uniform_filter(img, 5)
    local_std = np.sqrt(np.clip(ndimage.uniform_filter(img * img, 5) - mean * mean, 0, None))
    flat = local_std <= FLAT_FRACTION * span
    tol = EXTREME_FRACTION * span
    background = _border_connected(flat & (img <= lo + tol)) | _border_connected(flat & (img >= hi - tol))
    background = ndimage.binary_dilation(background, iterations=2)  # the rim the 5 x 5 window blurred
    field = ndimage.binary_opening(~background, np.ones((5, 5), bool))
    labels, n = ndimage.label(field)
    if n == 0:
        return np.ones(img.shape, bool)
    sizes = ndimage.sum(field, labels, index=np.arange(1, n + 1))
    field = ndimage.binary_fill_holes(labels == 1 + int(np.argmax(sizes)))
    if field.mean() < 0.05:
        return np.ones(img.shape, bool)
    field &= inside_shutters(img, field, span)
    margin = max(1, int(0.02 * np.sqrt(field.sum())))
    eroded = ndimage.binary_erosion(field, iterations=margin)
    return eroded if eroded.mean() > 0.05 else field


ROUND_INLIERS = 0.45      # a field whose edge lies on one circle this much is round (``round_field``) ...
ROUND_TOLERANCE = 0.02    # ... within this fraction of the circle's radius


def _circle(u: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    """Least-squares circle (centre u, centre v, radius) through points: x^2 + y^2 + D x + E y + F = 0."""
    (d, e, f), *_ = np.linalg.lstsq(np.stack([u, v, np.ones(len(u))], 1), -(u * u + v * v), rcond=None)
    cu, cv = -d / 2.0, -e / 2.0
    return cu, cv, float(np.sqrt(max(cu * cu + cv * cv - f, 0.0)))


def exposed_field(found: np.ndarray, setting: str = "auto") -> np.ndarray:
    """The field a registration uses (``FIELDS``): the one ``found`` (``field_mask``) when "auto", else every pixel.
    Whichever is used, the detector's shape is the found field's (``round_field``): an intensifier stays one, its
    pincushion estimated, when the user takes the whole image."""
    return found if setting == "auto" else np.ones(found.shape, bool)


def field_record(mask: np.ndarray, round_: bool, setting: str = "auto") -> dict:
    """What result.json keeps of the field used (``inputs.xray_field``): how it was decided (``setting``), the shape
    of the field found (round: an intensifier's, ``round_field``), the fraction of the image the field used covers
    and its bounding box [first column, first row, last column, last row] in px of the registered image (0-based
    pixel centres)."""
    rows, cols = np.nonzero(mask)
    box = [int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max())] if len(rows) else None
    return {"decided_by": "image" if setting == "auto" else "user (the whole image)",
            "shape": "round" if round_ else "rectangular", "exposed_fraction": float(np.mean(mask)), "box_px": box}


def round_field(mask: np.ndarray) -> bool:
    """Whether the exposed field is a disc (as an image intensifier's), possibly cut by the image's edges or
    missing a burnt-out part: a circle is fitted to the field's edge pixels away from the image border, refitted
    on those within 1.5 x the median distance of it until it settles, and at least ``ROUND_INLIERS`` of the edge
    must lie within ``ROUND_TOLERANCE`` of its radius, a radius of at least a quarter of the image. A rectangle's
    edge lies that close to one circle for about a fifth of its length at most, a body outline in air is no circle;
    the benchmark's intensifiers (0.99) and a real Siemens RF fluoroscopy (0.55: its burnt-out air is left out of
    the field) are round."""
    edge = mask & ~ndimage.binary_erosion(mask)
    edge[:3], edge[-3:], edge[:, :3], edge[:, -3:] = False, False, False, False
    v, u = (x.astype(float) for x in np.nonzero(edge))
    if len(u) < 20:
        return False
    keep = np.ones(len(u), bool)
    for _ in range(8):
        cu, cv, radius = _circle(u[keep], v[keep])
        off = np.abs(np.hypot(u - cu, v - cv) - radius)
        keep = off <= 1.5 * np.median(off) + 1e-9
    inliers = float(np.mean(off <= ROUND_TOLERANCE * radius))
    return inliers >= ROUND_INLIERS and radius >= min(mask.shape) / 4.0


def inside_shutters(image: np.ndarray, field: np.ndarray, span: float) -> np.ndarray:
    """Where ``field`` may lie given the straight collimator edges (shutter blades) found on each side.

    A shutter's shadow in a linear-intensity image is not flat: scatter glows in it, fading away from the edge, so
    the flat-extreme rule keeps it inside the field. Its edge is a straight step along the whole side instead. For
    the columns c of ``field``'s bounding box (rows alike), with h = ``SHUTTER_HALF_WIDTH``::

        s(c) = median over the rows r where both ends are in the field of (I[r, c + h] - I[r, c - h]) / span

    An anatomical edge does not keep one direction along a whole side; a shutter edge does, by about half the
    range (measured: 0.40-0.60 on flat-panel images with scatter outside). On each side the strongest
    |s| >= ``SHUTTER_STEP`` within the outer ``SHUTTER_ZONE`` of the box is taken as the blade, and what lies
    beyond it, with the h pixels the step is blurred over, leaves the field."""
    h = SHUTTER_HALF_WIDTH
    keep = np.ones(field.shape, bool)
    rows, cols = np.where(field.any(axis=1))[0], np.where(field.any(axis=0))[0]
    r0, c0 = rows[0], cols[0]
    box = np.asarray(image[r0:rows[-1] + 1, c0:cols[-1] + 1], np.float64)
    inside = field[r0:rows[-1] + 1, c0:cols[-1] + 1]
    for transpose, offset in ((False, c0), (True, r0)):  # vertical blades (steps along rows), then horizontal
        b, m = (box.T, inside.T) if transpose else (box, inside)
        if b.shape[1] <= 2 * h + 1:
            continue
        step = np.where(m[:, 2 * h:] & m[:, :-2 * h], (b[:, 2 * h:] - b[:, :-2 * h]) / span, np.nan)
        counted = np.isfinite(step).sum(axis=0) >= max(10, 0.25 * b.shape[0])
        with np.errstate(all="ignore"):
            strength = np.where(counted, np.abs(np.nanmedian(np.where(counted, step, 0.0), axis=0)), 0.0)
        zone = max(1, int(SHUTTER_ZONE * len(strength)))
        for outer in (np.arange(zone), np.arange(len(strength) - zone, len(strength))):
            j = outer[int(np.argmax(strength[outer]))]
            if strength[j] < SHUTTER_STEP:
                continue
            edge = offset + j + h  # the step's centre, image index
            cut = slice(None, edge + h + 1) if outer[0] == 0 else slice(edge - h, None)
            if transpose:
                keep[cut, :] = False
            else:
                keep[:, cut] = False
    return keep


def display_range(pixels: np.ndarray, mask: np.ndarray | None = None,
                  percentiles: tuple[float, float] = DISPLAY_PERCENTILES,
                  drop_clipped: bool = True) -> tuple[float, float]:
    """(low, high) pixel values to display an image between (module docstring): the ``percentiles`` of the
    pixels inside ``mask`` (the exposed field, (rows, cols) bool as ``field_mask`` gives; None or empty = the
    whole image), without the clipped ones when ``drop_clipped``. Values in the image's own units; high > low."""
    img = np.asarray(pixels, np.float32)
    values = img[mask] if mask is not None and np.shape(mask) == img.shape and mask.any() else img.ravel()
    values = values[:: max(1, values.size // SAMPLE_SIZE)]
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 0.0, 1.0
    if drop_clipped:
        values = _without_clipped(values)
    lo, hi = np.percentile(values, percentiles)
    return float(lo), float(hi) if hi > lo else float(lo) + 1.0


def _without_clipped(values: np.ndarray) -> np.ndarray:
    """``values`` without those equal to their minimum or maximum when either is held by more than
    CLIPPED_FRACTION of them (clipping); unchanged when that would leave nothing."""
    keep = np.ones(values.shape, bool)
    for extreme in (values.min(), values.max()):
        at = values == extreme
        if at.mean() > CLIPPED_FRACTION:
            keep &= ~at
    return values[keep] if keep.any() else values
