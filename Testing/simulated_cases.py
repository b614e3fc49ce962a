"""A realistic simulated AP case of the sample CT (CarmReg's own simulator), as several tests need one."""

import dataclasses

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


def intensifier_case(sample_ct):
    """(SimulatedCase, CarmGeometry): an intensifier image of 384 x 384 pixels of 0.6 mm with 8 mm of pincushion at
    its rim and no S-distortion (the simulator's k 100^3 = 5.26 mm), a level in the middle of the view drawn as
    ``random_pose`` draws it (stop 23's case); the geometry a pinhole (the reader's, no distortion given)."""
    ct, labels, centroids = sample_ct
    rng = np.random.default_rng(502)
    options = dataclasses.replace(sample_options(rng, SimulationOptions(size_px=(384, 384), pixel_spacing_mm=0.6)),
                                  pincushion_edge_mm=8.0, s_distortion_edge_mm=0.0)
    geometry = default_geometry(ct, options)
    inner = centroids.sorted().labels[3:-2]
    pose = random_pose(rng, options, centroids, inner[int(rng.integers(len(inner)))], geometry=geometry)
    return simulate_case(ct, labels, centroids, geometry, pose, options, seed=2), geometry
