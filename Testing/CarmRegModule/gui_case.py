"""The synthetic spine case shared by the GUI tests (a module with its own name: ``conftest`` is ambiguous
when several test folders have one)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carmreg.logic.registration.image_refine import RefineParameters

LEVELS = ("T11", "T12", "L1", "L2", "L3")
TRUE_POSE = (20.0, 6.0, -8.0, 1.0, 0.0, 0.0)


@dataclass
class SyntheticCase:
    ct_path: Path
    xray_path: Path          # DICOM with geometry
    png_path: Path           # same pixels, no geometry
    ct_landmarks_path: Path
    xray_landmarks_path: Path
    centroids_lps_mm: np.ndarray
    uv_px: np.ndarray
    labels: tuple
    sdd_mm: float
    pixel_spacing_mm: float
    size_px: tuple


def make_volume():
    """A small torso: soft-tissue ellipse, five vertebral bodies 30 mm apart along z, ribs as bars (LPS)."""
    from carmreg.logic.geometry.volume import Volume

    shape, spacing = (90, 70, 80), 2.0
    i, j, k = np.meshgrid(*[np.arange(n, dtype=np.float32) for n in shape], indexing="ij")
    x, y, z = (i - 44.5) * spacing, (j - 34.5) * spacing, (k - 39.5) * spacing
    hu = np.full(shape, -1000.0, np.float32)
    hu[(x / 80) ** 2 + (y / 60) ** 2 < 1] = 30.0
    centres = []
    for n in range(len(LEVELS)):
        c = np.array([1.5 * np.sin(n), 20.0 + 0.5 * n, 60.0 - 30.0 * n])
        centres.append(c)
        body = ((x - c[0]) / 18) ** 2 + ((y - c[1]) / 14) ** 2 + ((z - c[2]) / 10) ** 2 < 1
        cortex = ((x - c[0]) / 20) ** 2 + ((y - c[1]) / 16) ** 2 + ((z - c[2]) / 11.5) ** 2 < 1
        hu[cortex] = 1100.0
        hu[body] = 450.0
        hu[(abs(x - c[0]) < 5) & (y > c[1] + 14) & (y < c[1] + 40) & (abs(z - c[2]) < 6)] = 800.0  # process
        hu[(abs(z - c[2] - 12) < 3) & (abs(y - 5) < 40) & (abs(x) > 25) & (abs(x) < 75)] = 600.0      # rib
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = [-44.5 * spacing, -34.5 * spacing, -39.5 * spacing]
    return Volume(hu.astype(np.int16), affine, "synthetic"), np.array(centres)



# Small search and no image refinement: these tests check the window's wiring on an exact synthetic case
# (blobs, exact clicks), where the landmark stages alone recover the pose.
FAST_PARAMETERS = {"ty_half_range_mm": 16.0, "tz_half_range_mm": 24.0, "grid_step_mm": 4.0, "cache_dir": None,
                   "refine": RefineParameters(enabled=False), "level_check": False}
