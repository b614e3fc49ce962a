"""Which starts bring a labelling to its true pose? One case of the appearance benchmark registered up to its levels
stage, then one labelling's image refinement (the contest's own, ``labelling_fit.refit_from``) run again from its
registered pose turned about L (``ry``, the cranio-caudal tilt) and about S (``rz``) by a grid of angles, and from the
true pose; each run's score, GC, click mPDE (detector mm) and pose are printed.

    ../../.venv/bin/python labelling_starts.py --case 263 --variant ii-dark-jpeg --labels L1,L2,L3 --cache-dir C

Stop 46, case 263 (second CT; true pose rx -9.8, ry -9.0, rz -8.7 degrees), right labelling L1-L3, registered at
ry 2.6 and rz 2.0 with the source 30 mm off (score 0.83, GC 0.17): its intensifier JPEG reaches the true pose (0.22,
GC 0.79) from ry -16 (rz 0 or -8) and from (ry -8, rz -8), not from ry -8 alone (the contest's tilted refits) nor rz
-8 alone; its intensifier PNG from ry -8 alone too (0.16, GC 0.84), but there L1-L3 was third, not one of the
leading two that get the tilted refits. Registered in process, as ``score_true_pose.py``.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_appearance as bench  # noqa: E402

from carmreg.logic.geometry.camera import POSE_NAMES  # noqa: E402
from carmreg.logic.registration.labelling_fit import refit_from, state_context  # noqa: E402

TURNS_DEG = [(ry, rz) for ry in (-16, -8, 0, 8, 16) for rz in (-8, 0, 8) if (ry, rz) != (0, 0)]
"""(ry, rz) degrees added to the registered pose's rotations, one start each."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=int, required=True)
    parser.add_argument("--variant", required=True)
    parser.add_argument("--labels", required=True, help="the labelling, comma-separated, head first")
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    args = parser.parse_args()
    state, true_pose = bench.registered_to_levels(args.case, args.variant, args.cache_dir)
    labels = args.labels.split(",")
    fit = next((f for f in state.identification.fits if f.labels == labels), None)
    if fit is None or not fit.refined:
        sys.exit(f"labelling {labels} was not registered in this run")
    ctx = state_context(state, state.xray_line_integral, state.spatial.ty_mm, state.spatial.tz_mm, None)
    print(f"case {args.case} {args.variant}: {state.identification.status}, winner "
          f"{'-'.join(state.identification.winner.labels)}; {'-'.join(labels)} registered at {fit.score:.3f} "
          f"{np.round(fit.pose, 1)}, true pose {np.round(true_pose, 1)}")
    starts = {"true pose": true_pose}
    iy, iz = POSE_NAMES.index("ry_deg"), POSE_NAMES.index("rz_deg")
    for ry, rz in TURNS_DEG:
        start = fit.pose.copy()
        start[iy] += ry
        start[iz] += rz
        starts[f"ry {ry:+d} rz {rz:+d}"] = start
    for name, start in starts.items():
        run = fit.copy()
        run.refine = None
        refit_from(ctx, run, start)
        print(f"  {name:14s} -> {run.score:.3f}  GC {run.similarity:.3f}  mPDE {run.mpde_mm:.2f} mm  "
              f"pose {np.round(run.pose, 1)}")


if __name__ == "__main__":
    main()
