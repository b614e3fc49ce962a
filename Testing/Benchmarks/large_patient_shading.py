"""Why a large patient's polarity is found wrong without clicks (stop 28's experiment, tune half only).

Not a test. For each appearance-benchmark case folder given (a variant already run by ``bench_appearance`` with
``--modes none``: ``out_none/result.json`` and ``truth.json`` beside the X-ray), two measurements:

1. at the **true pose** (the benchmark's own geometry and pose, ``appearance.make_geometry``), the GC of the
   X-ray converted as its true polarity with the DRR (the levels contest's coarse mu level and detector binning),
   plain and after removing the shading of scales above ``--sigma-mm`` from both images::

       hp(I) = I - G_s * (m I) / G_s * m        (m the exposed field, G_s a Gaussian of s = sigma / pixel)

2. the no-click polarity check as the CLI runs it (database cached): each polarity's refined image-alone
   registrations (``image_polarity``), their best GC as refined (plain) and rescored after the same high-pass.

Were the large patient's wrong verdict due to the search and not to the image, the true pose would agree with the
right polarity while the right polarity's refined poses do not reach it.

3. with ``--search``, the same polarity check again with the search changed: ``high-passed``: the DRR database,
   the X-ray's coarse image (``spatial_search`` and ``image_starts`` where the pipeline and its appearance checks
   call them: the starts) and every DRR and
   the X-ray in the refinement's GC (``image_refine.prepare``) all pass through ``without_shading`` first;
   ``high-passed-starts``: only the starts so (the high pass is CarmReg's ``image.shading`` since stop 29, which
   built the first of these into the pipeline as a second opinion, ``appearance_checks._polarity_without_shading``; the
   tables of stop 28 were measured with this script's own copy, its Gaussians reflected at the image's border);
   ``tilted-starts``: every start also tilted out of the image plane by
   +-``--tilt-deg`` about each of the two axes across the beam (ry, rz). An experiment only: the functions are
   replaced in this process, CarmReg is unchanged::

    .venv/bin/python Testing/Benchmarks/large_patient_shading.py /tmp/w/case026/fp-bright-large-tiff \\
        --cache-dir /tmp/c --search high-passed
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from carmreg.logic.geometry.camera import POSE_NAMES, CarmPose
from carmreg.logic.image.prepare import attenuation
from carmreg.logic.image.shading import without_shading
from carmreg.logic.registration import appearance_checks, image_refine, pipeline
from carmreg.logic.registration.image_refine import refine_grid
from carmreg.logic.registration.state import RegistrationParameters
from carmreg.logic.similarity.metrics import gc

sys.path.insert(0, str(Path(__file__).resolve().parent))
import appearance as app  # noqa: E402  (the benchmark's own appearance chain, beside this file)
from measure_without_shading import registered_without_clicks  # noqa: E402

REFINE_PIXEL_MM = RegistrationParameters().refine_coarse.detector_pixel_mm  # the image-alone refinement's pixel


@contextlib.contextmanager
def changed_search(search: str, sigma_mm: float, tilt_deg: float):
    """The no-click search changed as ``search`` says (module docstring, 3.), for the ``with`` block."""
    spatial, starts, prepare = pipeline.spatial_search, pipeline.image_starts, image_refine.prepare
    callers = (pipeline, appearance_checks)  # the modules that call the search's functions
    databases = {}

    def passed(db, xray_coarse, mask_coarse):
        sigma_px = sigma_mm / db.intrinsics.pixel_spacing_mm[0]
        if id(db) not in databases:
            databases[id(db)] = dataclasses.replace(db, drrs=without_shading(db.drrs, mask_coarse, sigma_px))
        return databases[id(db)], without_shading(xray_coarse, mask_coarse, sigma_px)

    def spatial_passed(db, xray_coarse, mask_coarse, metric="gc", metrics=("gc",), known=None):
        return spatial(*passed(db, xray_coarse, mask_coarse), mask_coarse, metric, metrics, None)

    def starts_passed(db, xray_coarse, mask_coarse, count):
        return starts(*passed(db, xray_coarse, mask_coarse), mask_coarse, count)

    def prepare_passed(metric, fixed, mask, dtype=np.float64):
        sigma_px = sigma_mm / REFINE_PIXEL_MM
        inner = prepare(metric, without_shading(fixed, mask, sigma_px), mask, dtype=dtype)
        return lambda drrs: inner(without_shading(np.asarray(drrs, float), mask, sigma_px))

    def starts_tilted(db, xray_coarse, mask_coarse, count):
        tilts = ((0.0, 0.0), (tilt_deg, 0.0), (-tilt_deg, 0.0), (0.0, tilt_deg), (0.0, -tilt_deg))
        return [start + np.array([0, 0, 0, 0, ry, rz]) for start in starts(db, xray_coarse, mask_coarse, count)
                for ry, rz in tilts]

    for module in callers:
        if search in ("high-passed", "high-passed-starts"):
            module.spatial_search, module.image_starts = spatial_passed, starts_passed
        if search == "tilted-starts":
            module.image_starts = starts_tilted
    if search == "high-passed":
        image_refine.prepare = prepare_passed
    try:
        yield
    finally:
        for module in callers:
            module.spatial_search, module.image_starts = spatial, starts
        image_refine.prepare = prepare


def scores(fixed: np.ndarray, drrs: np.ndarray, mask: np.ndarray, sigma_px: float) -> tuple[float, float]:
    """(best plain GC, best high-passed GC) of ``fixed`` against ``drrs`` (n, rows, cols)."""
    plain = float(np.max(gc(fixed, drrs, mask)))
    unshaded = gc(without_shading(fixed, mask, sigma_px), without_shading(drrs, mask, sigma_px), mask)
    return plain, float(np.max(unshaded))


def polarity_check(folder: Path, cache_dir: str):
    """(state after the spatial stage without clicks, CT, params) as the CLI runs it."""
    _, state = registered_without_clicks(folder, cache_dir, ("database", "spatial"))
    return state, state.ct, state.parameters


def verdict(state) -> str:
    """The no-click polarity verdict in words: polarity, (unclear), refined GC dark / bright."""
    a, refined = state.appearance, state.image_polarity.scores
    return (f"{a.polarity}{'' if a.clear else ' (unclear)'} "
            f"{refined['bone-dark']:.3f} / {refined['bone-bright']:.3f}")


def measure(folder: Path, cache_dir: str, sigma_mm: float, search: str | None, tilt_deg: float) -> str:
    """One table row (module docstring)."""
    truth = json.loads((folder / "truth.json").read_text())
    state, ct, params = polarity_check(folder, cache_dir)
    xray = state.xray
    grids = {p: refine_grid(state.geometry.intrinsics, params.refine_coarse,
                            attenuation(xray.pixels, state.mask, p == "bone-dark", "log-display"), state.mask)
             for p in ("bone-dark", "bone-bright")}
    level = state.pyramid.level(params.refine_coarse.mu_spacing_mm)
    sigma_px = sigma_mm / grids["bone-dark"].detector.pixel_spacing_mm[0]
    true_polarity = "bone-bright" if truth["bone_bright_displayed"] else "bone-dark"
    geometry = app.make_geometry(ct, app.DETECTORS[app.VARIANTS[folder.name].detector])
    pose = CarmPose(*[truth["pose"][k] for k in POSE_NAMES]).as_array()
    grid = grids[true_polarity]
    at_truth = scores(grid.image, grid.line_integrals(level, geometry, pose[None]), grid.mask, sigma_px)
    refined = {}
    for polarity, fits in state.image_polarity.registered.items():
        grid = grids[polarity]
        drrs = grid.line_integrals(level, state.geometry, np.array([f.pose for f in fits]))
        refined[polarity] = scores(grid.image, drrs, grid.mask, sigma_px)
    dark, bright = refined["bone-dark"], refined["bone-bright"]
    row = (f"| {folder.parent.name} {folder.name} | {true_polarity} | {verdict(state)} "
           f"| {at_truth[0]:.3f} | {at_truth[1]:.3f} | {dark[0]:.3f} / {bright[0]:.3f} "
           f"| {dark[1]:.3f} / {bright[1]:.3f} |")
    if search:
        with changed_search(search, sigma_mm, tilt_deg):
            row += f" {verdict(polarity_check(folder, cache_dir)[0])} |"
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", type=Path, help="case/variant folders with out_none/result.json")
    parser.add_argument("--cache-dir", required=True)
    parser.add_argument("--sigma-mm", type=float, default=20.0, help="the high-pass scale on the detector (mm)")
    parser.add_argument("--search", choices=("high-passed", "high-passed-starts", "tilted-starts"),
                        help="the polarity check again with the search changed (module docstring, 3.)")
    parser.add_argument("--tilt-deg", type=float, default=8.0, help="--search tilted-starts: the tilt (degrees)")
    args = parser.parse_args(argv)
    searched = f" found by the search {args.search}, GC dark / bright |" if args.search else ""
    print(f"| case | true polarity | found without clicks, refined GC dark / bright | GC at the true pose "
          f"| high-passed ({args.sigma_mm:g} mm) | refined GC, dark / bright "
          f"| refined poses high-passed, dark / bright |{searched}")
    print("|---|---|---|---|---|---|---|" + ("---|" if searched else ""))
    for folder in args.folders:
        print(measure(folder, args.cache_dir, args.sigma_mm, args.search, args.tilt_deg), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
