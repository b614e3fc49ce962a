#!/usr/bin/env python
"""Named vertebral centroids of the second real CT, ``example_ct.nii.gz`` (TotalSegmentator test data).

The CT (abdomen and pelvis, 122 x 101 x 112 voxels of 3 mm, HU; Apache-2.0, see the data folder's README
and LICENSE) has no vertebra labels of its own. ``example_seg.nii.gz`` labels a 30-slice crop of it
(``example_ct_sm.nii.gz``; its header repeats the full CT's affine, so the crop's place is found here by
comparing voxel values). This script finds every vertebra along the spine and names it by anchoring to the
crop's labelled vertebrae. All geometry is LPS mm through the CT's ``ijk_to_lps`` (voxel centres at integer
indices); axis k of this CT runs inferior -> superior, j posterior -> anterior, i left -> right.

Steps
-----
1. Crop offset: the k0 with ``ct[:, :, k0:k0 + 30] == crop`` exactly.
2. Anchors: centroids of the TotalSegmentator vertebrae (30 L2, 31 L1, 32 T12, 33 T11) on the full-CT grid
   (crop affine = CT affine shifted by k0 slices); only labels not cut by the crop are anchors.
3. Body line: in a 15 mm thick mid-sagittal slab (centred on the anchors' mean i) of the CT smoothed with a
   1-voxel Gaussian, each axial row (fixed k) is scanned from anterior to posterior; the anterior wall of the
   vertebral body is the first voxel starting a run of >= 5 voxels above 100 HU, the posterior wall the
   first voxel below 60 HU after it (the spinal canal).
   Rows where that fails or jumps (the discs, whose density is below the threshold) are interpolated; the
   body centre line (mean of the walls, mid-sagittal i) is smoothed (Gaussian, 2 slices) and resampled every
   1 mm of arc length s, with unit tangent t(s).
4. Discs: the mean HU over a 10 mm radius disc perpendicular to t(s) through the body line dips at each
   intervertebral disc (~80 HU between bright endplates; this patient's trabecular bone is barely denser).
   The band-pass score G_6mm * profile - G_1.5mm * profile (Gaussian smoothing along s) peaks there; peaks
   above ``DISC_SCORE_HU``, ``MIN_DISC_GAP_MM`` apart and ``EDGE_MM`` inside the scanned range are the
   discs; each disc is the plane through its body-line point with normal t(s).
5. Centroids: a vertebra is the slab between two consecutive disc planes (for the lowest level, S1, the
   slab below the lowest disc, as thick as the level above it). Its voxels are the bone (HU > 150, holes in
   each axial slice filled so the trabecular body counts) inside the slab, within 40 mm of the body line's
   sagittal plane laterally and from 75 mm posterior to 25 mm anterior of the body line (body and posterior
   elements; most of the pelvis stays out). The centroid is their mean position (LPS mm).
6. Names: the slab holding an anchor's centroid gets the anchor's name; the others are counted from it
   along the spine (``carmreg.logic.io.landmarks.next_level``). A level whose upper disc lies above the scan (here T12,
   cut by the top slice) has no slab; a slab whose bone reaches the first or last slice is left out too.
   S1 is the first sacral segment (TotalSegmentator's ``vertebrae_S1``), the level below the lowest disc.

Checked by eye on this CT (``sagittal.png``, ``coronal.png`` and axial views): the lowest ribs articulate
with the vertebra cut by the top slice (T12 in example_seg); below it five rib-free lumbar vertebrae, each
with a disc below, then the sacrum (alae and sacroiliac joints in the slices of the level below the lowest
disc). No transitional vertebra: the anchor count (L1 from example_seg) and the count up from the sacrum
(S1, L5, ..., L1) agree.

Check the result by eye: the script writes ``sagittal.png`` and ``coronal.png`` (named centroids drawn on
a mid-sagittal slab and a coronal maximum-intensity projection) to ``--png-dir``.

Usage::

    .venv/bin/python scripts/label_example_ct.py                  # writes Testing/Benchmarks/data/...
    .venv/bin/python scripts/label_example_ct.py --data-dir /work/shared/data/totalsegmentator-tests
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage, signal

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from carmreg.logic.geometry.vertebrae import TOTALSEGMENTATOR_V2_VERTEBRAE, summarize_labels  # noqa: E402
from carmreg.logic.geometry.volume import Volume, apply_affine  # noqa: E402
from carmreg.logic.io.landmarks import Landmarks3D, level_index, next_level, write_landmarks_3d  # noqa: E402
from carmreg.logic.io.volumes import load_volume  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "totalsegmentator-tests"
DEFAULT_OUT = ROOT / "Testing" / "Benchmarks" / "data" / "example_ct_centroids.mrk.json"
BODY_HU, CANAL_HU, BODY_RUN_VOX = 100.0, 60.0, 5
PROFILE_RADIUS_MM, DISC_SCORE_HU, MIN_DISC_GAP_MM, EDGE_MM = 10.0, 10.0, 22.0, 8.0
BONE_HU, LATERAL_MM, POSTERIOR_MM, ANTERIOR_MM = 150.0, 40.0, 75.0, 25.0
ANTERIOR_LPS = np.array([0.0, -1.0, 0.0])


# ----------------------------------------------------------------------------------------------- anchors

def crop_offset(ct_hu: np.ndarray, crop_hu: np.ndarray) -> int:
    """The slice k0 where the crop equals the CT exactly: ct[:, :, k0:k0 + n] == crop."""
    n = crop_hu.shape[2]
    for k0 in range(ct_hu.shape[2] - n + 1):
        if np.array_equal(ct_hu[:, :, k0:k0 + n], crop_hu):
            return k0
    raise SystemExit("example_ct_sm.nii.gz is not a slice range of example_ct.nii.gz")


def seg_summaries(seg: Volume, ct: Volume, k0: int) -> list:
    """TotalSegmentator vertebrae of the crop, centroids in the CT's LPS frame (crop affine = CT affine
    shifted by k0 slices; the crop file's own header repeats the CT's). ``complete`` = not cut by the crop."""
    shift = np.eye(4)
    shift[2, 3] = k0
    return summarize_labels(np.asarray(seg.hu), ct.ijk_to_lps @ shift, TOTALSEGMENTATOR_V2_VERTEBRAE)


# ----------------------------------------------------------------------------------------------- body line

def body_walls(slab: np.ndarray) -> np.ndarray:
    """(nk, 2) anterior and posterior body wall j per slice of a sagittal slab [j, k] (NaN where not found)."""
    walls = np.full((slab.shape[1], 2), np.nan)
    for k in range(slab.shape[1]):
        row = slab[:, k]
        hot = row > BODY_HU
        run = np.convolve(hot, np.ones(BODY_RUN_VOX), "valid") == BODY_RUN_VOX  # run[j]: hot[j:j+5]
        starts = np.nonzero(run)[0]
        if not len(starts):
            continue
        front = starts[-1] + BODY_RUN_VOX - 1
        back = front
        while back > 0 and row[back] > CANAL_HU:
            back -= 1
        walls[k] = front, back
    return walls


def clean_series(values: np.ndarray, window: int = 7, tolerance: float = 2.0) -> np.ndarray:
    """NaN where a value departs from its running median by more than ``tolerance``; then interpolated."""
    v = values.copy()
    ok = np.isfinite(v)
    med = ndimage.median_filter(np.where(ok, v, np.nanmedian(v)), window, mode="nearest")
    ok &= np.abs(v - med) <= tolerance
    idx = np.arange(len(v))
    return np.interp(idx, idx[ok], v[ok])


def spine_slices(found: np.ndarray, max_gap: int = 3) -> np.ndarray:
    """The run of slices, down from the top of the scan, where the body was found (gaps of up to
    ``max_gap`` slices, the discs, bridged)."""
    idx = np.nonzero(found)[0]
    top = idx.max()
    start = top
    for k in idx[::-1][1:]:
        if start - k > max_gap + 1:
            break
        start = k
    return np.arange(start, top + 1)


def body_line(ct: Volume, i_mid: int) -> tuple[np.ndarray, np.ndarray]:
    """(k values, (n, 3) LPS mm) of the smoothed vertebral-body centre line over the slices where found, in
    the sagittal plane i = i_mid."""
    smooth = ndimage.gaussian_filter(ct.hu.astype(np.float32), 1.0)
    i_mid = int(np.clip(i_mid, 2, ct.shape[0] - 3))
    walls = body_walls(smooth[i_mid - 2:i_mid + 3].mean(axis=0))
    ks = spine_slices(np.isfinite(walls[:, 0]))
    front, back = clean_series(walls[ks, 0]), clean_series(walls[ks, 1])
    j = ndimage.gaussian_filter1d((front + back) / 2.0, 2.0, mode="nearest")
    ijk = np.stack([np.full(len(ks), float(i_mid)), j, ks.astype(float)], axis=1)
    return ks, apply_affine(ct.ijk_to_lps, ijk)


def arclength_resample(points: np.ndarray, step_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(s, points, unit tangents) of a polyline resampled every ``step_mm`` of arc length."""
    seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    s = np.arange(0.0, seg[-1], step_mm)
    p = np.stack([np.interp(s, seg, points[:, a]) for a in range(3)], axis=1)
    t = np.gradient(p, axis=0)
    return s, p, t / np.linalg.norm(t, axis=1, keepdims=True)


def local_frames(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit anterior (patient anterior made perpendicular to t) and lateral (t x anterior) axes."""
    a = ANTERIOR_LPS - t * (t @ ANTERIOR_LPS)[:, None]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(t, a)


def sample_lps(ct: Volume, points_lps: np.ndarray) -> np.ndarray:
    """Trilinear HU at LPS points (any shape (..., 3)); -1000 outside."""
    ijk = apply_affine(ct.lps_to_ijk, points_lps.reshape(-1, 3))
    values = ndimage.map_coordinates(ct.hu.astype(np.float32), ijk.T, order=1, cval=-1000.0)
    return values.reshape(points_lps.shape[:-1])


# ----------------------------------------------------------------------------------------------- discs

def disc_profile(ct: Volume, p: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean HU over a disc of PROFILE_RADIUS_MM perpendicular to t(s) at each p(s), whether that disc lies
    wholly inside the CT)."""
    a, lat = local_frames(t)
    u = np.arange(-PROFILE_RADIUS_MM, PROFILE_RADIUS_MM + 0.1, 1.5)
    uu, vv = np.meshgrid(u, u, indexing="ij")
    keep = uu ** 2 + vv ** 2 <= PROFILE_RADIUS_MM ** 2
    uu, vv = uu[keep], vv[keep]
    pts = p[:, None, :] + uu[None, :, None] * a[:, None, :] + vv[None, :, None] * lat[:, None, :]
    inside = ct.contains_lps(pts.reshape(-1, 3), margin_vox=0.0).reshape(pts.shape[:2]).all(axis=1)
    return sample_lps(ct, pts).mean(axis=1), inside


def find_discs(profile: np.ndarray, inside: np.ndarray, step_mm: float = 1.0) -> np.ndarray:
    """Indices (along s) of the intervertebral discs: peaks of the band-pass score
    G_6mm * profile - G_1.5mm * profile (a dark band ~10 mm thick between bright endplates), at least
    DISC_SCORE_HU high and MIN_DISC_GAP_MM apart, not within EDGE_MM of where the profile leaves the CT."""
    idx = np.arange(len(profile))
    filled = np.interp(idx, idx[inside], profile[inside])
    score = (ndimage.gaussian_filter1d(filled, 6.0 / step_mm, mode="nearest")
             - ndimage.gaussian_filter1d(filled, 1.5 / step_mm, mode="nearest"))
    peaks, _ = signal.find_peaks(score, height=DISC_SCORE_HU, distance=int(MIN_DISC_GAP_MM / step_mm))
    first, last = idx[inside].min(), idx[inside].max()
    edge = int(EDGE_MM / step_mm)
    return peaks[(peaks >= first + edge) & (peaks <= last - edge)]


# ----------------------------------------------------------------------------------------------- centroids

def filled_bone(ct: Volume) -> np.ndarray:
    """Bone (HU > BONE_HU) with the holes of each axial slice filled (trabecular bodies count)."""
    bone = ct.hu > BONE_HU
    return np.stack([ndimage.binary_fill_holes(bone[:, :, k]) for k in range(bone.shape[2])], axis=2)


def slab_centroid(x_lps: np.ndarray, top: tuple, bottom: tuple, axis_point: np.ndarray,
                  axis_t: np.ndarray) -> tuple[np.ndarray, int]:
    """Mean of the bone points between two planes ((point, normal toward the sacrum) each), in the box of
    LATERAL_MM / POSTERIOR_MM / ANTERIOR_MM about the body line (frame at ``axis_point``)."""
    below_top = (x_lps - top[0]) @ top[1] >= 0.0
    above_bottom = (x_lps - bottom[0]) @ bottom[1] < 0.0
    a, lat = local_frames(axis_t[None])
    rel = x_lps - axis_point
    along_a, along_l = rel @ a[0], rel @ lat[0]
    box = (np.abs(along_l) <= LATERAL_MM) & (along_a >= -POSTERIOR_MM) & (along_a <= ANTERIOR_MM)
    chosen = x_lps[below_top & above_bottom & box]
    return chosen.mean(axis=0), len(chosen)


def vertebra_slabs(s: np.ndarray, p: np.ndarray, t: np.ndarray, discs: np.ndarray) -> list[dict]:
    """Slabs between consecutive discs, head to sacrum, plus one below the lowest disc (as thick as the
    level above it). The body line runs inferior -> superior, so normals toward the sacrum are -t."""
    order = discs[::-1]
    slabs = []
    for upper, lower in zip(order[:-1], order[1:], strict=True):
        mid = (upper + lower) // 2
        slabs.append({"top": (p[upper], -t[upper]), "bottom": (p[lower], -t[lower]), "axis": (p[mid], t[mid]),
                      "height_mm": float(s[upper] - s[lower])})
    last = order[-1]
    height = slabs[-1]["height_mm"] if slabs else 30.0
    normal = -t[last]
    slabs.append({"top": (p[last], normal), "bottom": (p[last] + normal * height, normal),
                  "axis": (p[last] + normal * height / 2.0, t[last]), "height_mm": height})
    return slabs


def cut_by_scan(slab: dict, ct: Volume, x_lps: np.ndarray, k_index: np.ndarray) -> bool:
    """True when the slab's bone reaches the first or last slice of the CT."""
    top, bottom = slab["top"], slab["bottom"]
    inside = ((x_lps - top[0]) @ top[1] >= 0.0) & ((x_lps - bottom[0]) @ bottom[1] < 0.0)
    near = np.linalg.norm(np.cross(x_lps - slab["axis"][0], slab["axis"][1]), axis=1) < LATERAL_MM
    ks = k_index[inside & near]
    return bool(len(ks) and (ks.min() == 0 or ks.max() == ct.shape[2] - 1))


def name_slabs(slabs: list[dict], anchors: list) -> list[str]:
    """Names from the anchors (the slab holding an anchor's centroid) counted along the spine."""
    named = {}
    for anchor in anchors:
        for n, slab in enumerate(slabs):
            c = anchor.centroid_lps_mm
            if (c - slab["top"][0]) @ slab["top"][1] >= 0 and (c - slab["bottom"][0]) @ slab["bottom"][1] < 0:
                named[n] = anchor.name
    if not named:
        raise SystemExit("no labelled vertebra of the crop lies in a found slab; cannot name the levels")
    ref, ref_name = min(named.items())
    names = [""] * len(slabs)
    names[ref] = ref_name
    for n in range(ref + 1, len(slabs)):
        names[n] = next_level(names[n - 1])
    for n in range(ref - 1, -1, -1):
        names[n] = next_level(names[n + 1], -1)
    clash = {n: (names[n], v) for n, v in named.items() if names[n] != v}
    if clash:
        raise SystemExit(f"anchors disagree with the level count: {clash}")
    return names


# ----------------------------------------------------------------------------------------------- pictures

def draw_check_images(ct: Volume, landmarks: Landmarks3D, line_lps: np.ndarray, discs: tuple, anchors: list,
                      out_dir: Path) -> list[Path]:
    """sagittal.png (15 mm mid-sagittal slab) and coronal.png (MIP) with the named centroids, the body line
    and the disc planes (traces 25 mm either side of the body line) drawn; ``discs`` = (points, tangents)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    hu = ct.hu.astype(np.float32)
    to_ijk = ct.lps_to_ijk
    c_ijk = apply_affine(to_ijk, landmarks.points_lps_mm)
    line_ijk = apply_affine(to_ijk, line_lps)
    anterior, lateral = local_frames(discs[1])
    i_mid = int(round(float(np.median(line_ijk[:, 0]))))
    views = {"sagittal": (hu[i_mid - 2:i_mid + 3].mean(axis=0), 1, anterior, (-100, 700)),
             "coronal": (hu.clip(-200, 1500).max(axis=1), 0, lateral, (-100, 1200))}
    box = {"boxstyle": "round,pad=0.15", "fc": "black", "alpha": 0.6, "ec": "none"}
    paths = []
    for name, (image, col, in_plane, (lo, hi)) in views.items():
        fig, ax = plt.subplots(figsize=(9, 10))
        ax.imshow(image.T, origin="lower", cmap="gray", vmin=lo, vmax=hi)
        ax.plot(line_ijk[:, col], line_ijk[:, 2], "y-", lw=0.8, label="body line")
        for n, (point, direction) in enumerate(zip(discs[0], in_plane, strict=True)):
            ends = apply_affine(to_ijk, np.array([point - 25 * direction, point + 25 * direction]))
            ax.plot(ends[:, col], ends[:, 2], "c-", lw=1.5, label="disc planes" if n == 0 else None)
        for a in anchors:
            q = apply_affine(to_ijk, a.centroid_lps_mm[None])[0]
            ax.plot(q[col], q[2], "m+", ms=12, mew=2)
            ax.annotate(f"seg {a.name}{'' if a.complete else ' (cut)'}", (q[col], q[2]), color="m", bbox=box,
                        xytext=(-90, 4), textcoords="offset points", fontsize=8)
        for label, q in zip(landmarks.labels, c_ijk, strict=True):
            ax.plot(q[col], q[2], "ro", ms=5)
            ax.annotate(f"{label} (k {q[2]:.1f})", (q[col], q[2]), color="r", xytext=(12, -4), bbox=box,
                        textcoords="offset points", fontsize=10, weight="bold")
        ax.set_title(f"example_ct {name}: red = centroids written, magenta = example_seg crop")
        ax.set_xlabel("j (posterior -> anterior)" if col == 1 else "i (patient left -> right)")
        ax.set_ylabel("k (inferior -> superior), 3 mm")
        ax.legend(loc="lower right", fontsize=8)
        fig.tight_layout()
        path = out_dir / f"{name}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


# ----------------------------------------------------------------------------------------------- main

def label_example_ct(data_dir: Path, png_dir: Path | None = None, verbose: bool = True) -> Landmarks3D:
    ct = load_volume(data_dir / "example_ct.nii.gz")
    k0 = crop_offset(np.asarray(ct.hu), np.asarray(load_volume(data_dir / "example_ct_sm.nii.gz").hu))
    summaries = seg_summaries(load_volume(data_dir / "example_seg.nii.gz"), ct, k0)
    anchors = [a for a in summaries if a.complete]
    i_mid = round(float(np.mean([apply_affine(ct.lps_to_ijk, a.centroid_lps_mm[None])[0, 0] for a in anchors])))
    _, line = body_line(ct, i_mid)
    s, p, t = arclength_resample(line)
    discs = find_discs(*disc_profile(ct, p, t))
    slabs = vertebra_slabs(s, p, t, discs)
    bone_ijk = np.argwhere(filled_bone(ct))
    x = apply_affine(ct.ijk_to_lps, bone_ijk.astype(float))
    results = [slab_centroid(x, sl["top"], sl["bottom"], *sl["axis"]) for sl in slabs]
    names = name_slabs(slabs, anchors)
    keep = [n for n, sl in enumerate(slabs) if not cut_by_scan(sl, ct, x, bone_ijk[:, 2])]
    landmarks = Landmarks3D([names[n] for n in keep], np.array([results[n][0] for n in keep]),
                            "scripts/label_example_ct.py")
    if verbose:
        print(f"crop example_ct_sm = example_ct slices {k0}..{k0 + 29}")
        for a in summaries:
            print(f"  seg {a.name}: {a.n_voxels} voxels, centroid LPS {np.round(a.centroid_lps_mm, 1)}, "
                  f"{'complete' if a.complete else 'cut by the crop'}")
        print("discs (LPS z mm):", np.round(p[discs][::-1, 2], 1))
        for n, (sl, (c, count)) in enumerate(zip(slabs, results, strict=True)):
            k = apply_affine(ct.lps_to_ijk, c[None])[0, 2]
            print(f"  {names[n]:>3}: z {c[2]:7.1f} mm (k {k:5.1f}), {count} bone voxels, slab "
                  f"{sl['height_mm']:.1f} mm{'' if n in keep else '  -- cut by the scan, left out'}")
        found = landmarks.as_dict()
        for a in anchors:
            if a.name in found:
                print(f"  anchor {a.name}: {np.linalg.norm(found[a.name] - a.centroid_lps_mm):.1f} mm from the "
                      "example_seg centroid")
        print("  spacing of consecutive centroids (mm):",
              np.round(np.linalg.norm(np.diff(landmarks.points_lps_mm, axis=0), axis=1), 1))
    if png_dir is not None:
        for path in draw_check_images(ct, landmarks, line, (p[discs], t[discs]), summaries, png_dir):
            print("wrote", path)
    return landmarks


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--png-dir", type=Path, default=Path("/tmp/second_ct"))
    args = parser.parse_args(argv)
    landmarks = label_example_ct(args.data_dir, args.png_dir)
    ordered = sorted(landmarks.labels, key=level_index)
    if ordered != landmarks.labels:
        raise SystemExit(f"levels out of order: {landmarks.labels}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    print("wrote", write_landmarks_3d(args.out, landmarks))
    return 0


if __name__ == "__main__":
    sys.exit(main())
