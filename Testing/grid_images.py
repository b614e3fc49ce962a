"""A bead-grid X-ray of an image intensifier, drawn through a known pincushion (grid-calibration tests)."""

import numpy as np

from carmreg.logic.geometry.distortion import RadialDistortion

SIZE, PIXEL_MM, STEP_MM = 768, 0.3, 8.0
CENTRE = (SIZE - 1) / 2.0


def grid_image(shift_mm: float, model: str = "carmreg", beads_dark: bool = True, seed: int = 0) -> np.ndarray:
    """A 768 px (0.3 mm) intensifier image of beads (0.7 mm sd) on an 8 mm grid turned 5 deg and off-centre, in a
    220 mm round field (0 outside), with noise. ``model``: "carmreg" = ``RadialDistortion.distort``; "forward" =
    the ideal radius r shown at r (1 + k r^2), k = shift / 100^3 (how the appearance benchmark draws it)."""
    turn = np.radians(5.0)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    ideal_mm = np.mgrid[-16:17, -16:17].reshape(2, -1).T @ rotation.T * STEP_MM + [1.3, -0.7]
    if model == "carmreg":
        shown = RadialDistortion.from_shift(shift_mm, (CENTRE, CENTRE), (PIXEL_MM, PIXEL_MM)).distort(
            ideal_mm / PIXEL_MM + CENTRE)
    else:
        shown = ideal_mm * (1 + shift_mm / 100.0**3 * (ideal_mm**2).sum(1, keepdims=True)) / PIXEL_MM + CENTRE
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    beads = np.zeros((SIZE, SIZE))
    sd_px = 0.7 / PIXEL_MM
    for u, v in shown[(shown.min(1) > 0) & (shown.max(1) < SIZE - 1)]:
        box = (slice(int(v) - 8, int(v) + 9), slice(int(u) - 8, int(u) + 9))
        beads[box] += np.exp(-((cols[box] - u) ** 2 + (rows[box] - v) ** 2) / (2 * sd_px**2))
    image = (1000.0 - 600.0 * beads if beads_dark else 300.0 + 600.0 * beads)
    image += np.random.default_rng(seed).normal(0.0, 15.0, image.shape)
    image[(cols - CENTRE) ** 2 + (rows - CENTRE) ** 2 > (110.0 / PIXEL_MM) ** 2] = 0.0
    return np.clip(image, 0, 65535)
