"""The simulation's parameters (``SimulationOptions``: geometry, motion, devices, detector, display, clicks) and
how they are drawn at random for a realistic case (``sample_options``); the nominal C-arm for a CT.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
from carmreg.logic.geometry.volume import Volume

GROUND_TRUTH_SCHEMA = "carmreg-ground-truth/1"


@dataclass(frozen=True)
class SimulationOptions:
    """Every parameter of the simulation (units in the names). A value of 0 switches an effect off."""

    # detector (used by ``default_geometry``): 9-inch image intensifier
    sdd_mm: float = 1000.0
    size_px: tuple[int, int] = (1024, 1024)
    pixel_spacing_mm: float = 0.25
    sod_mm: float = 600.0
    field_diameter_mm: float = 230.0
    # pose ranges for ``random_pose`` (uniform in +- range)
    level_offset_levels: float = 2.0
    lateral_range_mm: float = 20.0
    depth_range_mm: float = 50.0
    rotation_range_deg: float = 10.0
    # per-level rigid motion: each angle ~ N(0, sd) clipped at max; translation rms magnitude
    level_rotation_sd_deg: float = 2.0
    level_rotation_max_deg: float = 5.0
    level_translation_rms_mm: float = 1.0
    # attenuation (thick slices refined linearly first, see ``refine_thick_slices``)
    refine_thick_slices: bool = True
    mu_water_per_mm: float = 0.02
    soft_tissue_hu: float = 40.0
    bone_contrast_factor: float = 1.5
    table_line_integral: float = 0.15
    n_kwires: int = 2
    kwire_diameter_mm: float = 1.6
    kwire_length_mm: float = 150.0
    kwire_mu_per_mm: float = 0.9
    # distortion at the field edge (detector mm)
    pincushion_edge_mm: float = 4.0
    s_distortion_edge_mm: float = 2.0
    # detection and display
    scatter_fraction: float = 0.10
    scatter_sigma_mm: float = 30.0
    photons_per_pixel: float = 2000.0
    detector_blur_sigma_mm: float = 0.3
    vignetting: float = 0.2
    display_mode: str = "log"
    display_mid_grey: float = 0.45
    display_contrast: float = 0.55
    edge_enhancement: float = 1.0
    edge_sigma_mm: float = 3.0
    range_compression: float = 0.75
    range_sigma_mm: float = 25.0
    burn_in_text: bool = True
    # landmark clicks
    n_clicks: int = 3
    click_levels: tuple[str, ...] | None = None
    click_sd_mm: float = 0.9
    ct_click_sd_mm: float = 0.0
    visibility_margin_mm: float = 5.0

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


def sample_options(rng: np.random.Generator, base: SimulationOptions | None = None, *,
                   live_frame: bool = False) -> SimulationOptions:
    """Draw the realism parameters from the ranges reported in the literature (DATA.md).

    Bone contrast U(0.76, 1.7); scatter/glare U(0.05, 0.15); photons log-uniform in [1e3, 1e4] for a saved
    frame or [50, 500] for a live one; vignetting U(0.1, 0.3); pincushion U(2, 8) mm and S-distortion
    U(1, 5) mm at the field edge; 1 or 2 K-wires.
    """
    base = base or SimulationOptions()
    lo, hi = (50.0, 500.0) if live_frame else (1e3, 1e4)
    return dataclasses.replace(
        base, bone_contrast_factor=float(rng.uniform(0.76, 1.7)), scatter_fraction=float(rng.uniform(0.05, 0.15)),
        photons_per_pixel=float(np.exp(rng.uniform(np.log(lo), np.log(hi)))),
        vignetting=float(rng.uniform(0.1, 0.3)), pincushion_edge_mm=float(rng.uniform(2.0, 8.0)),
        s_distortion_edge_mm=float(rng.uniform(1.0, 5.0)), n_kwires=int(rng.integers(1, 3)))


def default_geometry(volume: Volume, options: SimulationOptions | None = None) -> CarmGeometry:
    """Nominal C-arm of ``options``: isocentre at the CT volume centre, square pixels, centred principal point."""
    o = options or SimulationOptions()
    intr = CarmIntrinsics(o.sdd_mm, (o.pixel_spacing_mm, o.pixel_spacing_mm), tuple(o.size_px),
                          sources={"sdd_mm": "simulation", "pixel_spacing_mm": "simulation"})
    return CarmGeometry(intr, tuple(float(x) for x in volume.center_lps_mm()), o.sod_mm)
