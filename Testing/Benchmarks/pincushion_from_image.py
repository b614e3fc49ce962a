"""Can an intensifier's pincushion be found from the image itself? (stop 27's experiment; the answer was no.)

Not a test. For each appearance-benchmark case folder given (an intensifier variant already registered with named
clicks by ``bench_appearance``: ``out_named/result.json`` and ``truth.json`` beside the X-ray), the registration is
run again as the CLI runs it up to the levels stage (database cached), and then the local image refinement
(``image_refine``, the pipeline's own parameters, or a finer ``--mu-mm``/``--pixel-mm``) is repeated with the
detector's distortion fixed at each ``--shifts`` value (``CarmIntrinsics.distortion_mm``: the outward shift of an
image point 100 mm from the centre), the clicks taken to the pinhole through it. Printed per shift: the
refinement's objective and GC, the clicks' mPDE and the median / max projection distance of every CT level
between the found and the true pose (pinhole P, detector mm). Were the pincushion visible to the image
agreement, the objective would be lowest near the true shift (truth.json ``distortion.k_per_mm2`` x 100^3)::

    .venv/bin/python Testing/Benchmarks/pincushion_from_image.py /tmp/w/case024/ii-dark-log-png --cache-dir /tmp/c
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from carmreg.logic.geometry.camera import project
from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d
from carmreg.logic.io.volumes import load_volume
from carmreg.logic.io.xray import load_xray
from carmreg.logic.registration.image_refine import intensity_refine
from carmreg.logic.registration.pipeline import CarmRegLogic, ideal_clicks
from carmreg.logic.registration.state import RegistrationParameters


def scan(folder: Path, shifts: list[float], cache_dir: str, mu_mm: float | None, pixel_mm: float | None) -> list[str]:
    """The table rows of one case folder (module docstring)."""
    result = json.loads((folder / "out_named" / "result.json").read_text())
    truth = json.loads((folder / "truth.json").read_text())
    inputs, g = result["inputs"], result["geometry"]
    xray = load_xray(inputs["xray"], sdd_mm=g["sdd_mm"], pixel_spacing_mm=g["pixel_spacing_mm"][0])
    ct, ct_lm = load_volume(inputs["ct"]), read_landmarks_3d(inputs["ct_landmarks"])
    clicks = read_landmarks_2d(inputs["xray_landmarks"], xray.intrinsics.pixel_spacing_mm)
    params = RegistrationParameters(cache_dir=cache_dir)
    refine = dataclasses.replace(params.refine, **{k: v for k, v in (("mu_spacing_mm", mu_mm),
                                                                    ("detector_pixel_mm", pixel_mm)) if v})
    logic = CarmRegLogic()
    state = logic.prepare(ct, ct_lm, xray, clicks, params)
    logic.run_through(state, "fine")
    start, spacing = state.pose.copy(), np.asarray(g["pixel_spacing_mm"], float)
    points = np.array([ct_lm.points_lps_mm[ct_lm.labels.index(lb)] for lb in clicks.labels])
    true_uv = project(np.asarray(truth["projection_matrix"], float), ct_lm.points_lps_mm)
    true_shift = (truth.get("distortion") or {}).get("k_per_mm2", 0.0) * 100.0**3
    rows = []
    for shift in shifts:
        intr = dataclasses.replace(state.geometry.intrinsics, distortion_mm=shift)
        geometry = dataclasses.replace(state.geometry, intrinsics=intr)
        r = intensity_refine(state.pyramid.level(refine.mu_spacing_mm), geometry, start, state.xray_line_integral,
                             state.mask, points, ideal_clicks(clicks, intr).uv_px, refine)
        pde = np.linalg.norm((project(geometry.projection_matrix(r.pose), ct_lm.points_lps_mm) - true_uv) * spacing,
                             axis=1)
        rows.append(f"| {folder.parent.name} {folder.name} | {true_shift:.2f} | {shift:.1f} | {r.objective_end:.4f} | "
                    f"{r.similarity_end:.3f} | {r.mpde_mm:.2f} | {np.median(pde):.2f} | {pde.max():.2f} |")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--shifts", default="0,1,2,3,4,5", help="distortion shifts at 100 mm to try (mm)")
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    parser.add_argument("--mu-mm", type=float, default=None, help="mu level of the refinement (default: pipeline's)")
    parser.add_argument("--pixel-mm", type=float, default=None, help="detector pixel of the refinement (ditto)")
    args = parser.parse_args(argv)
    shifts = [float(s) for s in args.shifts.split(",")]
    print("| case | true shift (mm) | shift tried (mm) | objective | GC | clicks mPDE (mm) | "
          "levels vs true pose, median (mm) | max (mm) |\n|---|---|---|---|---|---|---|---|")
    for folder in args.folders:
        for row in scan(folder, shifts, args.cache_dir, args.mu_mm, args.pixel_mm):
            print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
