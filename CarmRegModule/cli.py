"""Command line: ``carmreg register | demo | drr | simulate | gui | screenshot``.

Imports no Qt (``gui`` and ``screenshot`` import the widget layer only when called). A user error prints one
line ``carmreg: error: ...`` and exits with code 2; success exits 0; a registration whose own checks fail
writes its result (``ok: false``) and exits 1.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from carmreg import signals
from carmreg.logic.errors import CarmRegError

EXIT_OK, EXIT_CHECKS_FAILED, EXIT_USER_ERROR = 0, 1, 2


class ProgressBar:
    """Stage progress on stderr: a redrawn bar on a terminal, one line per finished stage otherwise."""

    def __init__(self, stream=None, width: int = 28):
        self.stream = stream or sys.stderr
        self.width = width
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def __call__(self, stage: str, fraction: float, message: str = "") -> None:
        if self.tty:
            done = int(round(self.width * fraction))
            bar = "#" * done + "-" * (self.width - done)
            end = "\n" if fraction >= 1.0 else ""
            self.stream.write(f"\r  {stage:<10} [{bar}] {100 * fraction:5.1f}%  {message[:40]:<40}{end}")
            self.stream.flush()
        elif fraction >= 1.0:
            self.stream.write(f"  {stage:<10} {message}\n")


# ---------------------------------------------------------------------------------------------- arguments

def _geometry_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("C-arm geometry (overrides or completes the X-ray's DICOM tags)")
    g.add_argument("--sdd-mm", type=float, help="source-to-detector distance, mm")
    g.add_argument("--pixel-spacing-mm", type=float, nargs="+", metavar="MM",
                   help="detector pixel spacing: one value, or column spacing then row spacing")
    g.add_argument("--principal-point-px", type=float, nargs=2, metavar=("U", "V"),
                   help="principal point (column, row) px; default: image centre")
    g.add_argument("--sod-mm", type=float, help="source-to-isocentre (patient) distance, mm")
    g.add_argument("--distortion-mm", type=float, metavar="MM",
                   help="image-intensifier pincushion from the C-arm's calibration: how far (mm) an image point "
                   "100 mm from the centre lies outward of a pinhole camera's; default: estimated from the image "
                   "when the exposed field is round (an intensifier's), else 0; 0 says none (a pinhole camera)")
    g.add_argument("--frame", type=int, help="frame of a multi-frame X-ray (0-based)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="carmreg", description="Register a preoperative CT to an "
                                     "intraoperative C-arm X-ray by vertebral centroids.")
    sub = parser.add_subparsers(dest="command", required=True)

    from carmreg.logic.image.turn import TURNS

    reg = sub.add_parser("register", help="register a CT to an X-ray")
    reg.add_argument("--ct", required=True, help="CT: DICOM folder, .nii/.nii.gz, .nrrd or .mha/.mhd")
    reg.add_argument("--ct-landmarks", required=True, help="CT centroids (.mrk.json or JSON), named by level")
    reg.add_argument("--xray", required=True, help="X-ray: DICOM (XA/RF/DX/CR), PNG, TIFF or JPEG")
    clicks = reg.add_mutually_exclusive_group(required=True)
    clicks.add_argument("--xray-landmarks", help="X-ray centroids: .mrk.json (points named by level, or unnamed: "
                        "CarmReg names them), JSON {\"T12\": [column, row]} or unnamed [[column, row], ...]")
    clicks.add_argument("--no-clicks", action="store_true",
                        help="no X-ray centroids: identify the levels in view from the image alone")
    reg.add_argument("--out", required=True, help="output folder")
    reg.add_argument("--series-uid", help="SeriesInstanceUID to read when the CT folder holds several series")
    reg.add_argument("--orient-xray", choices=TURNS, metavar="TURN",
                     help="turn the X-ray (and its clicks, given as on the stored image) before registering, when its "
                     "display was stored mirrored or rotated: " + ", ".join(TURNS) + " (the name a refused X-ray's "
                     "message gives); the results are drawn on the X-ray so turned")
    _registration_args(reg)
    _geometry_args(reg)

    demo = sub.add_parser("demo", help="run the whole pipeline on the embedded sample case")
    demo.add_argument("--out", default="carmreg-out", help="output folder (default: ./carmreg-out)")
    demo.add_argument("--clicks", choices=("named", "unnamed", "none"), default="named",
                      help="use the sample's X-ray clicks as named (default), without their names (CarmReg names "
                      "them), or none (levels from the image alone)")
    _registration_args(demo)

    drr = sub.add_parser("drr", help="render a DRR of a CT at a C-arm pose to PNG and NRRD")
    drr.add_argument("--ct", help="CT file or folder (default: the sample CT)")
    drr.add_argument("--out", required=True, help="output prefix: writes PREFIX.png and PREFIX.nrrd")
    drr.add_argument("--pose", type=float, nargs=6, default=[0, 0, 0, 0, 0, 0],
                     metavar=("TX", "TY", "TZ", "RX", "RY", "RZ"), help="C-arm pose, mm and degrees")
    drr.add_argument("--size-px", type=int, nargs=2, default=[512, 512], metavar=("COLS", "ROWS"))
    drr.add_argument("--engine", choices=("cpu", "vtk"), default="cpu")
    drr.add_argument("--xray", help="take the detector geometry from this X-ray instead")
    _geometry_args(drr)

    cal = sub.add_parser("calibrate-distortion", help="measure an image intensifier's pincushion on an X-ray of a "
                         "bead grid (for --distortion-mm)")
    cal.add_argument("--image", required=True, help="X-ray of a plate of beads on a square grid at the "
                     "intensifier's input: DICOM, PNG, TIFF or JPEG")
    cal.add_argument("--pixel-spacing-mm", type=float, nargs="+", metavar="MM",
                     help="detector pixel spacing: one value, or column then row (default: the DICOM's)")
    cal.add_argument("--principal-point-px", type=float, nargs=2, metavar=("U", "V"),
                     help="the distortion's centre (column, row) px; default: image centre")
    cal.add_argument("--bead-mm", type=float, default=2.0, help="the beads' size in the image, mm (default 2)")
    cal.add_argument("--frame", type=int, help="frame of a multi-frame X-ray (0-based)")

    sim = sub.add_parser("simulate", help="simulate an intraoperative X-ray with known ground truth")
    sim.add_argument("--ct", help="CT (default: the sample CT)")
    sim.add_argument("--vertebrae", help="vertebra label map on the CT grid (default: the sample's)")
    sim.add_argument("--ct-landmarks", help="CT centroids (default: the sample's)")
    sim.add_argument("--out", required=True, help="output folder")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--level", help="level the C-arm is centred near (default: random among labelled)")
    sim.add_argument("--size-px", type=int, default=None, help="detector columns = rows")

    gui = sub.add_parser("gui", help="open the desktop application",
                         formatter_class=argparse.RawDescriptionHelpFormatter,
                         description="Open the CarmReg window: empty (offers to recover a crashed session), with a\n"
                         "saved session, with the sample case or with your files.\n\n"
                         "Needs a display and, on a fresh Debian/Ubuntu machine, the system libraries of\n"
                         "  scripts/install-system-deps.sh\n"
                         "Without a display it exits with code 2 (carmreg screenshot works without one).")
    _window_inputs(gui)

    shot = sub.add_parser("screenshot", help="export screenshots of the application offscreen",
                          description="PNG screenshots of the window and its views without a display: the "
                          "sample case (default), a session or your files, registered first when a view shows "
                          "the result.")
    shot.add_argument("--out", required=True, help="output folder (carmreg_<view>.png)")
    _window_inputs(shot)
    shot.add_argument("--size", type=int, nargs=2, default=[1600, 1000], metavar=("WIDTH", "HEIGHT"),
                      help="window size in px (default 1600 1000)")
    shot.add_argument("--views", nargs="+", metavar="VIEW",
                      help="window, window_data, window_ct, window_xray, window_register, window_check, axial, "
                      "coronal, sagittal, ct, xray, overlay, 3d, result (default: the main ones)")
    shot.add_argument("--no-register", action="store_true", help="do not register (views without a result)")
    return parser


def _window_inputs(p: argparse.ArgumentParser) -> None:
    """What the window opens with: a session, the sample case, or data files (any of them)."""
    p.add_argument("--session", metavar="FILE", help="a saved session (*.carmreg.json): data, geometry, points "
                   "and the last result")
    p.add_argument("--sample", action="store_true", help="the embedded sample case")
    p.add_argument("--ct", help="CT: DICOM folder, .nii/.nii.gz, .nrrd or .mha/.mhd")
    p.add_argument("--xray", help="X-ray: DICOM (XA/RF/DX/CR), PNG, TIFF or JPEG")
    p.add_argument("--ct-landmarks", metavar="FILE", help="CT centroids (.mrk.json or JSON), named by level")
    p.add_argument("--xray-landmarks", metavar="FILE", help="X-ray clicks (.mrk.json or JSON), named or not")
    p.add_argument("--sdd-mm", type=float, help="the X-ray's source-to-detector distance, when its file does not "
                   "give it (PNG, TIFF, JPEG)")
    p.add_argument("--pixel-spacing-mm", type=float, nargs="+", metavar="MM",
                   help="the X-ray's detector pixel spacing: one value, or column then row")


def _window_geometry(args) -> dict:
    """The X-ray geometry given with ``--sdd-mm`` / ``--pixel-spacing-mm``, as the window's overrides."""
    spacing = _spacing(args.pixel_spacing_mm)
    geometry = {"sdd_mm": args.sdd_mm, "pixel_spacing_mm": spacing}
    return {k: v for k, v in geometry.items() if v is not None}


def _registration_args(p: argparse.ArgumentParser) -> None:
    from carmreg.logic.image.appearance import POLARITY_SETTINGS
    from carmreg.logic.image.field import FIELDS
    from carmreg.logic.image.prepare import STORAGE_SETTINGS
    from carmreg.logic.similarity.metrics import METRICS

    p.add_argument("--metric", choices=METRICS, default="gc", help="spatial-search similarity (default gc)")
    p.add_argument("--all-metrics", action="store_true",
                   help="compute the similarity maps of all seven metrics (the chosen one still decides)")
    p.add_argument("--no-level-check", action="store_true",
                   help="named clicks: skip the wrong-level check (registration redone with the names shifted "
                   "+-1 and +-2 levels); unnamed clicks are always identified")
    p.add_argument("--polarity", choices=POLARITY_SETTINGS, default="auto",
                   help="how the X-ray shows bone (default auto: found from the image against the CT's DRRs and "
                   "recorded in result.json; set it only to override)")
    p.add_argument("--storage", choices=STORAGE_SETTINGS, default="auto",
                   help="how a bone-dark X-ray stores its values: linear-intensity (the detector's intensity, "
                   "converted with -log) or log-display (already log-like); default auto: as its DICOM states, else "
                   "found from the image against the CT's DRRs and recorded in result.json; set it only to override")
    p.add_argument("--field", choices=FIELDS, default="auto",
                   help="the X-ray's exposed field: auto (found from the image: the collimator's or intensifier's "
                   "shadow left out; recorded in result.json) or whole (every pixel exposed; when the field found "
                   "leaves out anatomy)")
    p.add_argument("--seed", type=int, default=1, help="CMA-ES seed (same seed, same result)")
    p.add_argument("--cache-dir", help="DRR database cache (default: ~/.cache/carmreg)")
    p.add_argument("--no-cache", action="store_true", help="always rebuild the DRR database")


# ---------------------------------------------------------------------------------------------- commands

def _parameters(args):
    from carmreg.logic.registration.pipeline import RegistrationParameters
    from carmreg.logic.resources import cache_dir

    if args.cache_dir and not args.no_cache and Path(args.cache_dir).exists() and not Path(args.cache_dir).is_dir():
        raise CarmRegError(f"--cache-dir {args.cache_dir}: this is a file, not a folder; give a folder for the "
                           "DRR database cache (created if missing), or --no-cache")
    params = RegistrationParameters(metric=args.metric, all_metrics=args.all_metrics, polarity=args.polarity,
                                    storage=args.storage, xray_field=args.field, level_check=not args.no_level_check,
                                    cache_dir=None if args.no_cache else str(args.cache_dir or cache_dir()))
    params.fine.seed = args.seed
    return params


def _spacing(values):
    if values is None:
        return None
    if len(values) not in (1, 2):
        raise CarmRegError("--pixel-spacing-mm takes one value, or column spacing then row spacing")
    return (values[0], values[-1])


def _load_xray(args):
    from carmreg.logic.io.xray import load_xray

    return load_xray(args.xray, sdd_mm=args.sdd_mm, pixel_spacing_mm=_spacing(args.pixel_spacing_mm),
                     principal_point_px=tuple(args.principal_point_px) if args.principal_point_px else None,
                     sod_mm=args.sod_mm, frame=args.frame, distortion_mm=args.distortion_mm)


def _xray_clicks(xray, xray_lm_path, clicks: str = "named"):
    """The X-ray clicks: from the file (``clicks`` named), with their names dropped (unnamed), or none."""
    from carmreg.logic.io.landmarks import Landmarks2D, read_landmarks_2d

    if xray_lm_path is None or clicks == "none":
        return Landmarks2D([], np.zeros((0, 2)), "no clicks")
    lm = read_landmarks_2d(xray_lm_path, xray.intrinsics.pixel_spacing_mm if xray.intrinsics else None)
    return Landmarks2D([None] * len(lm.labels), lm.uv_px, lm.source) if clicks == "unnamed" else lm


def _register(ct_path, ct_lm_path, xray, xray_lm_path, out, params, series_uid=None, clicks="named",
              orient=None):
    """Register and write the results; ``orient``: a ``turn.TURNS`` name the X-ray and its clicks (given on the
    image as stored) are turned by first (``--orient-xray``)."""
    from carmreg.logic.image.turn import turned_clicks, turned_xray
    from carmreg.logic.io.landmarks import read_landmarks_3d
    from carmreg.logic.io.volumes import load_volume
    from carmreg.logic.registration.pipeline import CarmRegLogic
    from carmreg.logic.report.result_files import save_result

    t0 = time.perf_counter()
    ct = load_volume(ct_path, series_uid=series_uid)
    ct_lm = read_landmarks_3d(ct_lm_path)
    xray_lm = _xray_clicks(xray, xray_lm_path, clicks)
    if orient:
        xray_lm, xray = turned_clicks(xray_lm, orient, xray.size_px), turned_xray(xray, orient)
    print(f"CT {Path(ct_path).name}: {ct.shape} voxels, {np.round(ct.spacing_mm, 3).tolist()} mm; "
          f"X-ray {Path(xray.source).name}: {xray.size_px[0]}x{xray.size_px[1]} px"
          f"{f' (turned {orient})' if orient else ''}; "
          f"levels CT {', '.join(ct_lm.sorted().labels)}; X-ray clicks "
          f"{', '.join(x or '(unnamed)' for x in xray_lm.labels) or 'none'}")
    result = CarmRegLogic(progress=ProgressBar()).register(ct, ct_lm, xray, xray_lm, params)
    clicked = {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv.get("clicked_uv_px") is not None}
    paths = save_result(result, out, xray.pixels, clicked, ct=ct, ct_landmarks=ct_lm, draw_aside=True)
    _print_report(result, time.perf_counter() - t0, out)
    return result, paths


def _print_report(result, seconds: float, out) -> None:
    print("stage       mPDE (mm)   seconds")
    for s in result.stages:
        m = f"{s.mpde_mm:9.2f}" if s.mpde_mm is not None else "        -"
        print(f"  {s.name:<10}{m}   {s.seconds:7.2f}")
    in_image = [lv for lv in result.levels if lv["in_image"]]
    from carmreg.logic.report.style import names_shown

    if names_shown(result.level_check):
        print("levels on the X-ray: " + ", ".join(
            f"{lv['label']}{'*' if lv['fitted'] else ''} ({lv['uv_px'][0]:.0f}, {lv['uv_px'][1]:.0f})"
            for lv in in_image) + ("   (* = clicked)" if any(lv["fitted"] for lv in in_image) else ""))
    else:
        print("levels on the X-ray: none named (the image was refused, below)")
    print("pose: " + ", ".join(f"{k} {v:.2f}" for k, v in result.pose.as_dict().items())
          + f"; magnification {result.magnification:.2f}")
    if result.appearance is not None:
        print(f"X-ray appearance: {result.appearance.summary(result.xray_turned)}")
    if result.level_check:
        from carmreg.logic.report.style import level_summary

        print(level_summary(result.level_check))
    for w in result.warnings:
        print(f"warning: {w}")
    print(f"{'OK' if result.ok else 'CHECKS FAILED'}: wrote {out}/result.json, overlay.png, drr.png, drr.nrrd, "
          f"carm.tfm, slicer/CarmReg.mrml, report.pdf ({seconds:.1f} s in all)")



def _check_out_dir(out) -> None:
    """Refuse an output folder that cannot be created or written, before any work is done."""
    from carmreg.logic.io.transaction import check_writable_folder

    check_writable_folder(out)


MAX_SEED = 2**32 - 1


def _check_numbers(args) -> None:
    """Refuse, before any work, numbers the commands would silently reinterpret (quoting the user's value)."""
    seed = getattr(args, "seed", None)
    if seed is not None and not 0 <= seed <= MAX_SEED:
        raise CarmRegError(f"--seed {seed} is not a valid seed: give a whole number from 0 to {MAX_SEED}")
    frame = getattr(args, "frame", None)
    if frame is not None and frame < 0:
        raise CarmRegError(f"--frame {frame}: frames are counted from 0 (the first); give --frame 0 or more")
    if getattr(args, "out", None) is not None and not str(args.out).strip():
        raise CarmRegError("--out '' is empty; give the output folder (or file prefix for drr)")


def cmd_register(args) -> int:
    _check_out_dir(args.out)
    xray = _load_xray(args)
    result, _ = _register(args.ct, args.ct_landmarks, xray, args.xray_landmarks, args.out, _parameters(args),
                          args.series_uid, "none" if args.no_clicks else "named", args.orient_xray)
    return EXIT_OK if result.ok else EXIT_CHECKS_FAILED


def cmd_demo(args) -> int:
    from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d
    from carmreg.logic.io.xray import load_xray
    from carmreg.logic.resources import sample_case
    from carmreg.logic.simulation.evaluation import evaluate

    _check_out_dir(args.out)
    case = sample_case()
    print(f"CarmReg demo on the embedded sample case ({case['ct'].parent})")
    xray = load_xray(case["xray"])
    result, _ = _register(case["ct"], case["ct_landmarks"], xray, case["xray_landmarks"], args.out,
                          _parameters(args), clicks=args.clicks)
    if case["ground_truth"].is_file():
        truth = json.loads(case["ground_truth"].read_text())
        centroids = read_landmarks_3d(case["ct_landmarks"]).as_dict()
        fitted = {lv["label"] for lv in result.levels if lv["fitted"]}
        score = evaluate(result.projection_matrix, centroids, truth, fitted,
                         shown=result.geometry.intrinsics.distortion.distort)
        true_clicked = read_landmarks_2d(case["xray_landmarks"]).labels
        assigned = result.level_check.assigned_labels if result.level_check else None
        if args.clicks == "unnamed" and assigned is not None:
            right = assigned == list(true_clicked)
            print(f"clicks named {', '.join(assigned)}; the sample's true names are {', '.join(true_clicked)}: "
                  f"{'right' if right else 'WRONG'}")
        print("against the simulation's ground truth, levels not clicked (from the true pose's projection / from "
              "where the X-ray shows the vertebra): " + ", ".join(
                  f"{r['label']} {r['pde_pose_mm']:.1f} / {r['pde_image_mm']:.1f} mm"
                  for r in score["levels"] if not r["fitted"]))
        print(f"every visible level named correctly: {'yes' if score['all_named_correctly'] else 'NO'}")
    return EXIT_OK if result.ok else EXIT_CHECKS_FAILED


def cmd_drr(args) -> int:
    from carmreg.logic.geometry.camera import CarmIntrinsics, CarmPose, nominal_geometry
    from carmreg.logic.geometry.volume import MuPyramid
    from carmreg.logic.io.volumes import load_volume
    from carmreg.logic.report.result_files import save_png, to_uint8, write_drr_nrrd
    from carmreg.logic.resources import sample_case

    if not np.all(np.isfinite(args.pose)):
        raise CarmRegError("--pose must be six finite numbers: tx ty tz (mm) rx ry rz (degrees)")
    if not all(2 <= n <= 4096 for n in args.size_px):
        raise CarmRegError(f"--size-px {args.size_px[0]} {args.size_px[1]} must be two numbers between 2 and 4096 "
                           "(columns rows)")
    _check_out_dir(Path(args.out).parent)
    ct = load_volume(args.ct or sample_case()["ct"])
    if args.xray:
        xray = _load_xray(args)
        intrinsics, sod = xray.require_intrinsics(), xray.sod_mm
    else:
        spacing = _spacing(args.pixel_spacing_mm) or (0.5, 0.5)
        try:
            intrinsics = CarmIntrinsics(1020.0 if args.sdd_mm is None else args.sdd_mm, spacing,
                                        tuple(args.size_px),
                                        tuple(args.principal_point_px) if args.principal_point_px else None,
                                        {"sdd_mm": "default" if args.sdd_mm is None else "manual"},
                                        distortion_mm=args.distortion_mm or 0.0)
        except CarmRegError as exc:
            raise CarmRegError(f"carmreg drr: {exc}") from None
        sod = args.sod_mm
    geometry = nominal_geometry(intrinsics, ct, sod)
    pose = CarmPose.from_array(args.pose)
    t0 = time.perf_counter()
    if args.engine == "vtk":
        from carmreg.logic.drr.vtk_raycast import render_line_integrals_vtk
        drr = render_line_integrals_vtk(MuPyramid(ct).level(None), geometry, pose)
    else:
        from carmreg.logic.drr.cpu import render_line_integrals
        drr = render_line_integrals(MuPyramid(ct).level(None), geometry, pose)
    seconds = time.perf_counter() - t0
    prefix = Path(args.out)
    png, nrrd_path = prefix.with_suffix(".png"), prefix.with_suffix(".nrrd")
    save_png(png, to_uint8(drr))
    write_drr_nrrd(nrrd_path, drr, geometry, pose)
    print(f"DRR {intrinsics.size_px[0]}x{intrinsics.size_px[1]} px ({args.engine}, {seconds:.2f} s), line integral "
          f"{drr.min():.2f}..{drr.max():.2f}; wrote {png} and {nrrd_path}")
    return EXIT_OK


def cmd_calibrate_distortion(args) -> int:
    from carmreg.logic.image.grid_calibration import calibrate
    from carmreg.logic.io.xray import load_xray

    manual = _spacing(args.pixel_spacing_mm)
    image = load_xray(args.image, pixel_spacing_mm=manual, frame=args.frame)
    spacing = manual or (image.intrinsics.pixel_spacing_mm if image.intrinsics else None)
    if spacing is None:
        raise CarmRegError(f"{args.image}: the detector pixel spacing is not in the file; give --pixel-spacing-mm")
    if not 0.0 < args.bead_mm <= 20.0:
        raise CarmRegError(f"--bead-mm {args.bead_mm:g}: give the beads' size in the image, 0.5 to 20 mm")
    cal = calibrate(image.pixels, spacing, args.principal_point_px, args.bead_mm)
    print(cal.summary())
    print(f"use: --distortion-mm {cal.distortion_mm:.2f} (window: C-arm geometry, Pincushion; 3D Slicer: Pincushion "
          "at 100 mm), for X-rays of this C-arm at this field size and orientation")
    return EXIT_OK


def cmd_simulate(args) -> int:
    from carmreg.cli_simulate import run_cli

    if args.size_px is not None and not 64 <= args.size_px <= 4096:
        raise CarmRegError(f"--size-px {args.size_px} must be between 64 and 4096 (detector columns = rows)")
    _check_out_dir(args.out)

    return run_cli(args)


def _check_window_inputs(args) -> None:
    """Refuse, before any window opens, input files that do not exist or a session that cannot be read."""
    for flag in ("ct", "xray", "ct_landmarks", "xray_landmarks"):
        value = getattr(args, flag)
        if value and not Path(value).exists():
            raise CarmRegError(f"--{flag.replace('_', '-')} {value}: no such file or folder")
    if _window_geometry(args) and not args.xray:
        raise CarmRegError("--sdd-mm and --pixel-spacing-mm describe the X-ray given with --xray: give it too")
    if args.session:
        from carmreg.logic.io.session import load_session

        load_session(args.session)  # InputFileError naming the file and the problem
        if args.sample or args.ct or args.xray:
            raise CarmRegError("--session opens a saved session: give it alone, without --sample/--ct/--xray")


def _gui_module():
    """The widget layer, or a CarmRegError saying how to install it."""
    try:
        from carmreg import app
    except ImportError as exc:
        raise CarmRegError(f"the desktop application is not installed ({exc}): install it with "
                           "pip install 'carmreg[gui]' (scripts/setup.sh does)") from None
    return app


def cmd_gui(args) -> int:
    _check_window_inputs(args)
    app = _gui_module()
    app.check_display()  # no display, or Qt cannot open a window: one line, exit 2, nothing left behind
    return app.run_gui(ct=args.ct, xray=args.xray, ct_landmarks=args.ct_landmarks,
                       xray_landmarks=args.xray_landmarks, sample=args.sample, session=args.session,
                       geometry=_window_geometry(args))


def cmd_screenshot(args) -> int:
    _check_window_inputs(args)
    app = _gui_module()
    inputs = {k: getattr(args, k) for k in ("ct", "xray", "ct_landmarks", "xray_landmarks") if getattr(args, k)}
    sample = args.sample or not (inputs or args.session)
    views = tuple(args.views) if args.views else app.DEFAULT_VIEWS
    notes: list[str] = []
    for path in app.export_screenshots(args.out, sample=sample, views=views, register=not args.no_register,
                                       size=tuple(args.size),
                                       inputs=dict(inputs, geometry=_window_geometry(args)) if inputs else {},
                                       session=args.session, notes=notes):
        print(f"wrote {path}")
    for note in notes:
        print(f"warning: {note}", file=sys.stderr)
    return EXIT_OK


COMMANDS = {"register": cmd_register, "demo": cmd_demo, "drr": cmd_drr, "simulate": cmd_simulate,
            "calibrate-distortion": cmd_calibrate_distortion, "gui": cmd_gui, "screenshot": cmd_screenshot}


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    signals.install()
    try:
        _check_numbers(args)
        return COMMANDS[args.command](args)
    except CarmRegError as exc:
        print(f"carmreg: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("carmreg: interrupted", file=sys.stderr)
        return 130


WINDOWLESS = ("register", "demo", "drr", "simulate", "calibrate-distortion")
"""Commands whose process ends at once when ``main`` returns (``run``)."""


def run() -> None:
    """The ``carmreg`` console script: ``main``, then the process ends. After a command without a window every
    output is written, committed (``FolderTransaction``) and flushed when ``main`` returns, so the process ends
    at once (``os._exit``) instead of tearing the interpreter down: that teardown (numba's worker threads, every
    array of the registration freed one by one, the modules' finalisers) took 0.5-0.7 s of a 13-18 s
    ``carmreg register`` here and changes nothing on disk. ``gui`` and ``screenshot`` exit the usual way (Qt closes
    its windows), and so does an exception escaping ``main`` (Python prints it)."""
    code = main()
    if sys.argv[1:2] and sys.argv[1] in WINDOWLESS:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe (``carmreg ... | head``) has nothing left to flush
                pass
        logging.shutdown()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    run()
