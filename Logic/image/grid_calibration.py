"""An image intensifier's pincushion measured on an X-ray of a bead grid (``carmreg calibrate-distortion``).

A calibration plate - metal beads on a square grid, held at the intensifier's input - is imaged once; the
beads' ideal (pinhole) positions form a regular lattice, their image positions are pushed outward by the
pincushion. The fit finds ``distortion_mm`` (``geometry.distortion``: the shift of an image point 100 mm from the
principal point) for ``--distortion-mm``:

1. beads: local extremes of a difference of Gaussians (bead-sized minus background-sized, each normalised to the
   exposed field so that its rim does not pull the beads near it) inside the field, of the beads' polarity
   (metal dark or bright: the side of the field's median its extremes reach further), kept when they stand out
   by ``BEAD_CONTRAST`` robust standard deviations; each bead's position is the centroid of the filtered image
   in a bead-sized window about its peak (px);
2. lattice: the bead nearest the centre is (0, 0) (of those with a neighbour at about the grid step, the beads'
   median nearest-neighbour distance); its neighbours at that step give the two grid steps; indices grow
   outward, each bead predicted from an indexed neighbour with the steps measured locally (so the growing
   lattice follows the distortion) and taken when one lies within a third of a step;
3. fit: for a trial k, the beads' ideal points ``undistort(bead)`` are fitted by an affine map of their indices
   (linear least squares: the plate's scale, rotation and shear are free); k minimises the residual (bounded
   scalar search over the range ``CarmIntrinsics`` accepts). The residual (rms, detector mm) is reported with it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize
from scipy.spatial import cKDTree

from carmreg.logic.errors import InputFileError, RegistrationError
from carmreg.logic.geometry.camera import MAX_DISTORTION_MM, CarmIntrinsics
from carmreg.logic.geometry.distortion import RadialDistortion
from carmreg.logic.image.field import field_mask

BEAD_CONTRAST = 6.0   # a bead stands out by this many robust standard deviations of the filtered image
MIN_BEADS = 16        # fewer indexed beads than this: no fit
MAX_RMS_MM = 0.5      # a fit leaving more than this is refused (not a grid, or beads mis-indexed)


@dataclass
class GridCalibration:
    """The fitted pincushion, with what it rests on."""

    distortion_mm: float           # shift 100 mm from the centre (``CarmIntrinsics.distortion_mm``)
    beads: int                     # beads indexed on the lattice and fitted
    rms_mm: float                  # residual of the fit, detector mm
    rms_pinhole_mm: float          # ... of the same fit with no distortion (how much the pincushion explains)
    grid_step_mm: float            # the lattice step seen near the centre, detector mm
    bead_uv_px: np.ndarray         # (n, 2) the fitted beads' image positions (column, row)

    def summary(self) -> str:
        """One line for the user: the value and what it rests on."""
        return (f"pincushion {self.distortion_mm:.2f} mm at 100 mm from the centre, from {self.beads} beads on a "
                f"{self.grid_step_mm:.2f} mm grid; fit rms {self.rms_mm:.3f} mm ({self.rms_pinhole_mm:.3f} mm "
                "without it)")


def find_beads(pixels: np.ndarray, bead_px: float) -> np.ndarray:
    """(n, 2) bead centroids (column, row) px: extremes of a difference of Gaussians (module docstring, 1)."""
    image = np.asarray(pixels, np.float64)
    field = field_mask(image)
    mask = ndimage.binary_erosion(field, iterations=int(2 * bead_px) + 1)
    weight = field.astype(np.float64)

    def smooth(sigma):  # within the field only: the dark outside must not pull the beads near the rim inward
        return ndimage.gaussian_filter(image * weight, sigma) / np.maximum(ndimage.gaussian_filter(weight, sigma),
                                                                          1e-6)

    dog = smooth(bead_px / 2.0) - smooth(3.0 * bead_px)
    if not mask.any():
        return np.zeros((0, 2))
    low, middle, high = np.percentile(image[mask], [0.5, 50.0, 99.5])
    if middle - low > high - middle:
        dog = -dog  # beads darker than the plate: make them the maxima
    inside = dog[mask]
    spread = 1.4826 * np.median(np.abs(inside - np.median(inside))) + 1e-12
    peaks = (dog == ndimage.maximum_filter(dog, size=int(2 * bead_px) + 1)) & mask \
        & (dog > np.median(inside) + BEAD_CONTRAST * spread)
    if not peaks.any():
        return np.zeros((0, 2))
    half = int(np.ceil(bead_px))
    weights = np.pad(np.clip(dog, 0.0, None), half)  # padded: a window at the image's edge stays in range
    centroids = []
    for r, c in zip(*np.nonzero(peaks), strict=True):  # each peak's own bead-sized window, never a neighbour's
        window = weights[r:r + 2 * half + 1, c:c + 2 * half + 1]
        dr, dc = np.mgrid[-half:half + 1, -half:half + 1]
        centroids.append((c + (window * dc).sum() / window.sum(), r + (window * dr).sum() / window.sum()))
    return np.array(centroids, float)


def index_lattice(beads_px: np.ndarray, centre_px) -> dict:
    """{(i, j): bead index} of the beads on one square lattice grown from the bead nearest ``centre_px`` among
    those whose nearest neighbour lies at about the grid step (the beads' median nearest-neighbour distance)
    (module docstring, 2); empty when no lattice is seen."""
    if len(beads_px) < 5:
        return {}
    nearest = cKDTree(beads_px).query(beads_px, 2)[0][:, 1]
    pitch = float(np.median(nearest))
    on_grid = np.abs(nearest - pitch) < 0.25 * pitch
    centre_distance = np.where(on_grid, np.linalg.norm(beads_px - np.asarray(centre_px, float), axis=1), np.inf)
    start = int(np.argmin(centre_distance))
    offsets = beads_px - beads_px[start]
    apart = np.linalg.norm(offsets, axis=1)
    near = [k for k in np.argsort(apart) if abs(apart[k] - pitch) < 0.25 * pitch]
    if not near:
        return {}
    first = offsets[near[0]]
    second = next((offsets[k] for k in near[1:]
                   if abs(first[0] * offsets[k][1] - first[1] * offsets[k][0]) > 0.5 * pitch * pitch), None)
    if second is None:
        return {}
    steps, tree = {(1, 0): first, (0, 1): second}, cKDTree(beads_px)
    found, queue = {(0, 0): start}, deque([(0, 0)])
    taken = {start}
    while queue:
        i, j = queue.popleft()
        here = beads_px[found[(i, j)]]
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            key = (i + di, j + dj)
            if key in found:
                continue
            step = _local_step(beads_px, found, (i, j), (abs(di), abs(dj)), steps) * (di + dj)
            distance, k = tree.query(here + step)
            if distance < np.linalg.norm(step) / 3.0 and k not in taken:
                found[key], taken = k, taken | {k}
                queue.append(key)
    return found


def _local_step(beads_px, found, at, axis, default) -> np.ndarray:
    """The lattice step along ``axis`` ((1, 0) or (0, 1)) measured next to ``at``, else the central one."""
    i, j = at
    for a, b in ((at, (i + axis[0], j + axis[1])), ((i - axis[0], j - axis[1]), at)):
        if a in found and b in found:
            return beads_px[found[b]] - beads_px[found[a]]
    return default[axis]


def _residual_mm(shift_mm: float, beads_px, indices, centre_px, spacing_mm) -> np.ndarray:
    """Per-bead distance (mm) between the ideal bead and the affine lattice fitted to the ideal beads."""
    ideal = RadialDistortion.from_shift(shift_mm, centre_px, spacing_mm).undistort(beads_px) * spacing_mm
    design = np.column_stack([indices, np.ones(len(indices))])
    coef, *_ = np.linalg.lstsq(design, ideal, rcond=None)
    return np.linalg.norm(design @ coef - ideal, axis=1)


def calibrate_for_detector(pixels: np.ndarray, grid_spacing_mm, detector: CarmIntrinsics | None,
                           source: str = "the grid image") -> GridCalibration:
    """``calibrate`` a bead-grid X-ray taken on the C-arm whose X-ray has the intrinsics ``detector`` (None: no X-ray
    yet): the grid's own pixel spacing ``grid_spacing_mm`` (column, row) when known, else the X-ray's when the
    grid image has its size; the X-ray's principal point when the grid image has its size, else the grid image's
    centre. InputFileError when no spacing can be taken."""
    rows, cols = np.asarray(pixels).shape
    same_detector = detector is not None and tuple(detector.size_px) == (cols, rows)
    spacing = grid_spacing_mm if grid_spacing_mm is not None else (
        detector.pixel_spacing_mm if same_detector else None)
    if spacing is None:
        raise InputFileError(f"{source}: the grid image ({cols} x {rows} px) states no pixel spacing and is not the "
                             "X-ray's size; export it as the X-rays are, or give its pixel spacing")
    return calibrate(pixels, spacing, detector.principal_point_px if same_detector else None)


def calibrate(pixels: np.ndarray, pixel_spacing_mm, centre_px=None, bead_mm: float = 2.0) -> GridCalibration:
    """The pincushion of a bead-grid X-ray (module docstring); ``pixel_spacing_mm`` (column, row) at the detector,
    ``centre_px`` the principal point (default the image centre), ``bead_mm`` the beads' size in the image.
    RegistrationError when no grid is found or the fit is poor."""
    spacing = np.asarray(pixel_spacing_mm, float)
    rows, cols = np.asarray(pixels).shape
    centre = np.array(centre_px if centre_px is not None else ((cols - 1) / 2.0, (rows - 1) / 2.0), float)
    beads = find_beads(pixels, max(1.0, bead_mm / float(spacing.min())))
    lattice = index_lattice(beads, centre)
    if len(lattice) < MIN_BEADS:
        raise RegistrationError(f"found {len(lattice)} beads on one grid (of {len(beads)} bead-like spots); a "
                                f"calibration needs at least {MIN_BEADS}: image a plate of beads on a square grid "
                                "filling the field, or give the bead size in the image with --bead-mm")
    keys = list(lattice)
    uv = beads[[lattice[k] for k in keys]]
    ij = np.array(keys, float)

    def cost(shift):
        return float(np.mean(_residual_mm(shift, uv, ij, centre, spacing) ** 2))

    best = optimize.minimize_scalar(cost, bounds=(-MAX_DISTORTION_MM, MAX_DISTORTION_MM), method="bounded",
                                    options={"xatol": 1e-4})
    rms, pinhole = float(np.sqrt(best.fun)), float(np.sqrt(cost(0.0)))
    if rms > MAX_RMS_MM:
        raise RegistrationError(f"the {len(uv)} beads do not lie on one distorted grid (rms {rms:.2f} mm after the "
                                f"fit, more than {MAX_RMS_MM} mm): check that the image shows a square bead grid")
    step = float(np.linalg.norm((uv[keys.index((1, 0))] - uv[keys.index((0, 0))]) * spacing)) \
        if (1, 0) in lattice else float("nan")
    return GridCalibration(float(best.x), len(uv), rms, pinhole, step, uv)
