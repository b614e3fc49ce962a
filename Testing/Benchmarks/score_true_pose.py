"""Is a wrong answer the optimiser's or the image's? One case of the appearance benchmark registered up to its levels
stage, then its winner's pose and the true pose scored alike: GC (``image_refine``'s own scores, on the X-ray as the
registration converted it, inside the exposed field) of a DRR at each, on the levels contest's grid (4 mm level,
4 mm pixels) and the local refinement's (3 mm, 2 mm). When the true pose scores lower the image itself prefers the
wrong pose (more starts cannot help); when higher, the search missed it.

    ../../.venv/bin/python score_true_pose.py --case 229 --variant ii-dark-log-png --mode none --cache-dir C

Stop 43, case 229 without clicks (T1-T6 proposed with T6 named wrong): its intensifier PNG GC 0.894 at the found
pose against 0.883 at the true one (4 mm), 0.832 against 0.823 (3 mm); its low-dose TIFF 0.893 against 0.882
(4 mm), 0.816 against 0.807 (3 mm): both the image's. Registered in process, as the benchmark's tests prepare a
case, which finds nearly but not exactly the poses of the command line.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_appearance as bench  # noqa: E402

from carmreg.logic.registration.image_refine import RefineParameters, grid_scores, refine_grid  # noqa: E402

GRIDS = ((4.0, 4.0), (3.0, 2.0))
"""(mu level mm, detector pixel mm) of the levels contest's refinements and of the local refinement."""


def gc_at(state, poses: np.ndarray, mu_mm: float, pixel_mm: float) -> np.ndarray:
    """GC of a DRR at each of ``poses`` (n, 6) against the X-ray as converted, on that grid."""
    p = RefineParameters(mu_spacing_mm=mu_mm, detector_pixel_mm=pixel_mm)
    grid = refine_grid(state.geometry.intrinsics, p, state.xray_line_integral, state.mask)
    return grid_scores(p, grid)(grid.line_integrals(state.pyramid.level(mu_mm), state.geometry, poses))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=int, required=True)
    parser.add_argument("--variant", required=True)
    parser.add_argument("--mode", choices=("unnamed", "none"), default="none")
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    args = parser.parse_args()
    state, true_pose = bench.registered_to_levels(args.case, args.variant, args.cache_dir, args.mode == "unnamed")
    winner = state.identification.winner
    print(f"case {args.case} {args.variant} {args.mode}: {state.identification.status}, winner "
          f"{'-'.join(winner.labels)}, found pose {np.round(winner.pose, 1)}, true pose {np.round(true_pose, 1)}")
    for mu_mm, pixel_mm in GRIDS:
        found, true = gc_at(state, np.array([winner.pose, true_pose]), mu_mm, pixel_mm)
        print(f"  {mu_mm:g} mm level, {pixel_mm:g} mm pixels: GC found {found:.3f}, true {true:.3f}")


if __name__ == "__main__":
    main()
