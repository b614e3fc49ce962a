"""A realistic simulated AP case of the sample CT (CarmReg's own simulator), as several tests need one."""

import numpy as np

from carmreg.logic.simulation.options import SimulationOptions, default_geometry, sample_options
from carmreg.logic.simulation.scene import random_pose
from carmreg.logic.simulation.simulator import simulate_case


def simulated_ap_case(sample_ct, seed: int, level: str, sim_seed: int, size_px: int = 512, pixel_mm: float = 0.5):
    """(SimulatedCase, CarmGeometry): options and pose drawn with ``seed``, ``level`` in the middle of the view,
    the image made with ``sim_seed``; a square detector of ``size_px`` pixels of ``pixel_mm``."""
    ct, labels, centroids = sample_ct
    rng = np.random.default_rng(seed)
    options = sample_options(rng, SimulationOptions(size_px=(size_px, size_px), pixel_spacing_mm=pixel_mm))
    geometry = default_geometry(ct, options)
    pose = random_pose(rng, options, centroids, level, geometry=geometry)
    return simulate_case(ct, labels, centroids, geometry, pose, options, seed=sim_seed), geometry
