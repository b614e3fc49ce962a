"""``carmreg simulate``: a random realistic case from a CT (the embedded sample by default), its vertebra labels
or centroids; the pose and realism parameters drawn from ``--seed`` (``carmreg.logic.simulation``).
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.errors import LandmarkError
from carmreg.logic.geometry.vertebrae import CARMREG_VERTEBRAE
from carmreg.logic.io.vertebra_labels import load_vertebra_labels
from carmreg.logic.simulation.options import SimulationOptions, default_geometry, sample_options
from carmreg.logic.simulation.scene import random_pose
from carmreg.logic.simulation.simulator import simulate_case, write_simulated_case


def cli_inputs(args):
    """(CT, labels or None, centroids) from the CLI arguments; the embedded sample case by default."""
    from carmreg.logic.geometry.vertebrae import centroids_from_labels
    from carmreg.logic.io.landmarks import read_landmarks_3d
    from carmreg.logic.io.volumes import load_volume
    from carmreg.logic.resources import sample_case

    sample = sample_case() if not args.ct else None
    ct = load_volume(args.ct or sample["ct"])
    label_path = args.vertebrae or (sample["vertebrae"] if sample else None)
    labels = load_vertebra_labels(label_path, ct) if label_path else None
    if args.ct_landmarks or sample:
        centroids = read_landmarks_3d(args.ct_landmarks or sample["ct_landmarks"])
    elif labels is not None:
        centroids = centroids_from_labels(labels, ct.ijk_to_lps, CARMREG_VERTEBRAE, source=str(label_path))
    else:
        raise LandmarkError("simulate needs the CT's vertebral centroids: give --ct-landmarks (a .mrk.json) or "
                            "--vertebrae (a vertebra label map on the CT grid)")
    return ct, labels, centroids


def run_cli(args) -> int:
    """``carmreg simulate``: a random realistic case (pose and realism parameters drawn from ``--seed``)."""
    ct, labels, centroids = cli_inputs(args)
    rng = np.random.default_rng(args.seed)
    size = int(args.size_px or 1024)
    options = sample_options(rng, SimulationOptions(size_px=(size, size), pixel_spacing_mm=0.25 * 1024 / size))
    geometry = default_geometry(ct, options)
    for attempt in range(20):
        pose = random_pose(rng, options, centroids, args.level, geometry=geometry)
        try:
            sim = simulate_case(ct, labels, centroids, geometry, pose, options, seed=args.seed + 1000 * attempt)
            break
        except LandmarkError:
            if attempt == 19:
                raise
    paths = write_simulated_case(args.out, sim)
    visible = [lb for lb, ok in sim.visible.items() if ok]
    print(f"simulated {size}x{size} px in {sum(sim.timing_s.values()):.1f} s; pose "
          + ", ".join(f"{k} {v:+.1f}" for k, v in pose.as_dict().items()))
    print(f"visible {', '.join(visible)}; clicked {', '.join(sim.clicks.labels)}; bone contrast "
          f"x{options.bone_contrast_factor:.2f}, {options.photons_per_pixel:.0f} photons/px, pincushion "
          f"{options.pincushion_edge_mm:.1f} mm, S {options.s_distortion_edge_mm:.1f} mm, {len(sim.kwires)} K-wire(s)")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0
