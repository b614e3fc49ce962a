"""Simulated intraoperative C-arm X-ray with an exactly known pose (the ground truth for testing).

Everything is computed from a CT (HU, LPS mm), its vertebra label map and vertebral centroids. Frames and
units follow ``geometry.camera``: world = CT LPS mm, detector pixels (u, v) = (column, row) with pixel centres
at integer coordinates, images indexed ``image[row, column]``.

The chain (each step exact or a documented model)
-------------------------------------------------
1. Attenuation: ``mu = mu_water (1000 + HU) / 1000`` (>= 0), then another tube voltage than the CT's:
   ``mu' = mu + (f - 1) max(mu - mu_water, 0)`` (bone contrast relative to ~90 kV: f ~ 1.7 at 60 kV,
   0.76 at 120 kV).
2. Per-level rigid motion (supine CT vs prone surgery): vertebra k moves by ``M_k: x -> R_k (x - c_k) + c_k
   + t_k`` about its centroid c_k. By additivity of line integrals the moved anatomy is rendered *exactly*
   as ``L = DRR(mu_bg) + sum_k DRR(e_k moved by M_k)`` where ``mu_bg`` is mu with every vertebra voxel
   replaced by soft tissue and ``e_k = (mu - mu_soft) * [label == k]`` is the vertebra's excess over soft
   tissue, cropped to its bounding box. Moving a volume by M_k is the same as giving its grid the affine
   ``M_k @ ijk_to_lps``; rigid maps keep path lengths, so ``drr.cpu`` renders it exactly. With all
   M_k = I the sum equals the plain DRR of mu'. (Model: the space a vertebra moves into holds soft tissue.)
3. Things that are not in the CT: the carbon-fibre table (uniform ``table_line_integral``) and K-wires
   (steel cylinders, exact chord length of every pixel ray times ``kwire_mu_per_mm``), pedicle wires moving
   with their vertebra.
4. Image-intensifier distortion (``IntensifierDistortion``): an ideal detector point p (pinhole projection,
   ``P`` of the ground truth) appears at ``q = D(p)``: pincushion ``r -> r (1 + k r^2)`` plus S-distortion,
   a twist by ``phi(r) = phi_edge (r / R)^2`` about the field centre. The image is resampled with the exact
   inverse, so ``uv_true_px = D(project(P, M_k c_k))`` holds to interpolation accuracy.
5. Detection: primary ``I = exp(-L)``; scatter and veiling glare ``(1 - g) I + g G_wide * I`` (contrast loss
   g); automatic exposure control scales the field so that the central disc receives ``photons_per_pixel``
   on average; Poisson quantum noise; detector blur (Gaussian); vignetting ``1 - v (r / R)^2``; circular
   collimation (black outside the field); log display with dynamic range compression and edge enhancement
   (``video_display``), bone dark (fluoroscopy polarity), 16-bit; text burnt into the black corners.
6. Clicks: a surgeon's centroids of ``n_clicks`` adjacent visible levels, ``uv_true_px`` plus Gaussian noise
   of ``click_sd_mm`` per axis at the detector; optional 3D noise on the CT centroids (``ct_click_sd_mm``).

``simulate_case`` returns a ``SimulatedXray``; ``write_simulated_case`` writes xray.dcm, xray.png,
xray_centroids.mrk.json, ct_centroids.mrk.json and ground_truth.json.

Where each step lives: parameters ``options``; pose, motion and K-wires ``scene``; step 2's exact rendering
``render``; steps 4-5 ``detector``; steps 1 and 6 and the assembly here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carmreg.logic.errors import GeometryError, LandmarkError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.geometry.vertebrae import level_ordinals
from carmreg.logic.geometry.volume import Volume, hu_to_mu
from carmreg.logic.io.atomic import atomic_write_json
from carmreg.logic.io.landmarks import (
    Landmarks2D,
    Landmarks3D,
    level_index,
    write_landmarks_2d,
    write_landmarks_3d,
)
from carmreg.logic.simulation.detector import (
    IntensifierDistortion,
    burn_in_text,
    detect,
    resample_distorted,
    text_lines,
)
from carmreg.logic.simulation.options import GROUND_TRUTH_SCHEMA, SimulationOptions
from carmreg.logic.simulation.render import add_kwire, label_centers, render_moved_anatomy
from carmreg.logic.simulation.scene import Kwire, LevelMotion, draw_level_motions, plan_kwires

# ----------------------------------------------------------------------------------------------- result

@dataclass
class SimulatedXray:
    """The simulated image and everything needed to score a registration against it."""

    pixels: np.ndarray                      # (rows, cols) uint16, bone dark
    geometry: CarmGeometry
    pose: CarmPose
    distortion: IntensifierDistortion
    motions: dict[str, LevelMotion]
    ct_centroids: Landmarks3D              # true CT centroids
    ct_landmarks: Landmarks3D              # what a user would give (with 3D click noise if any)
    uv_projected_px: dict[str, np.ndarray]
    uv_true_px: dict[str, np.ndarray]
    visible: dict[str, bool]
    clicks: Landmarks2D
    kwires: list[Kwire]
    options: SimulationOptions
    seed: int
    facts: dict = field(default_factory=dict)  # exposure: photons, AEC normalisation, display mode
    line_integrals: np.ndarray | None = None  # undistorted L incl. table and wires, float32 (tests, previews)
    timing_s: dict = field(default_factory=dict)  # seconds per step (not part of the ground truth)

    @property
    def projection_matrix(self) -> np.ndarray:
        return self.geometry.projection_matrix(self.pose)

    def ground_truth(self) -> dict:
        """JSON-ready ground truth (see module docstring for every quantity's meaning)."""
        g, intr = self.geometry, self.geometry.intrinsics
        levels = {}
        for name, point in zip(self.ct_centroids.labels, self.ct_centroids.points_lps_mm, strict=True):
            motion = self.motions.get(name)
            levels[name] = {
                "centroid_lps_mm": point.tolist(),
                "motion_rotation_deg": motion.rotation_deg.tolist() if motion else [0.0, 0.0, 0.0],
                "motion_translation_mm": motion.translation_mm.tolist() if motion else [0.0, 0.0, 0.0],
                "motion_matrix_lps": motion.matrix.tolist() if motion else np.eye(4).tolist(),
                "uv_projected_px": self.uv_projected_px[name].tolist(),
                "uv_true_px": self.uv_true_px[name].tolist(),
                "visible": bool(self.visible[name]),
                "magnification": float(g.magnification(self.pose, point)),
            }
        return {
            "schema": GROUND_TRUTH_SCHEMA,
            "conventions": "world = CT LPS mm; (u, v) = (column, row) px, pixel centres at integers, row 0 at "
                           "top; P maps homogeneous LPS mm to homogeneous (u, v) px of the ideal (undistorted) "
                           "detector; uv_true_px = distortion(project(P, motion(centroid)))",
            "seed": int(self.seed),
            "pose": self.pose.as_dict(),
            "projection_matrix": self.projection_matrix.tolist(),
            "intrinsics": {"sdd_mm": intr.sdd_mm, "pixel_spacing_mm": list(intr.pixel_spacing_mm),
                           "size_px": list(intr.size_px), "principal_point_px": list(intr.principal_point_px)},
            "isocenter_lps_mm": list(g.isocenter_lps_mm),
            "sod_mm": g.sod_mm,
            "source_lps_mm": g.source_lps_mm(self.pose).tolist(),
            "magnification_isocenter": float(g.magnification(self.pose)),
            "distortion": self.distortion.as_dict(),
            "levels": levels,
            "clicks_uv_px": {lb: uv.tolist() for lb, uv in self.clicks.as_dict().items()},
            "ct_landmarks_lps_mm": {lb: p.tolist() for lb, p in self.ct_landmarks.as_dict().items()},
            "kwires": [w.as_dict() for w in self.kwires],
            "exposure": self.facts,
            "options": self.options.as_dict(),
        }


# ----------------------------------------------------------------------------------------------- main entry

def _check_inputs(volume: Volume, labels, centroids: Landmarks3D) -> None:
    if labels is not None and np.asarray(labels).shape != volume.shape:
        raise GeometryError(f"vertebra label map {np.asarray(labels).shape} is not on the CT grid "
                            f"{volume.shape}; resample it to the CT first")
    inside = volume.contains_lps(centroids.points_lps_mm) if len(centroids.labels) else []
    outside = [lb for lb, ok in zip(centroids.labels, inside, strict=True) if not ok]
    if outside:
        raise LandmarkError(f"CT centroids {', '.join(outside)} lie outside the CT volume; check that the "
                            "landmark file belongs to this CT and is in LPS")


def choose_click_levels(names: list[str], uv_true: dict[str, np.ndarray], visible: dict[str, bool],
                        center_px: np.ndarray, n: int) -> list[str]:
    """The run of ``n`` adjacent visible levels whose mean position is nearest the image centre."""
    ordered = sorted(names, key=level_index)
    ordinal = level_ordinals(ordered)
    runs = [ordered[i:i + n] for i in range(len(ordered) - n + 1)
            if all(visible[lb] for lb in ordered[i:i + n])
            and ordinal[ordered[i + n - 1]] - ordinal[ordered[i]] == n - 1]
    if not runs:
        raise LandmarkError(f"fewer than {n} adjacent vertebrae are visible in the simulated image; "
                            "aim the C-arm at the labelled spine (another pose or seed)")
    return min(runs, key=lambda run: np.linalg.norm(np.mean([uv_true[lb] for lb in run], 0) - center_px))


def attenuation(hu: np.ndarray, options: SimulationOptions) -> tuple[np.ndarray, float]:
    """(mu' per mm at the simulated tube voltage, mu of soft tissue): module docstring, step 1."""
    mu_w = options.mu_water_per_mm
    mu = hu_to_mu(hu, mu_w)
    if options.bone_contrast_factor != 1.0:
        mu = mu + np.float32(options.bone_contrast_factor - 1.0) * np.maximum(mu - np.float32(mu_w), 0)
    return mu, float(mu_w * (1000.0 + options.soft_tissue_hu) / 1000.0)


def motion_centers(labels: np.ndarray | None, ijk_to_lps: np.ndarray, centroids: Landmarks3D) -> dict:
    """Centre of each labelled vertebra's motion: its CT centroid when given, else its centre of mass."""
    if labels is None:
        return {}
    centers = label_centers(labels, ijk_to_lps)
    centers.update({k: v for k, v in centroids.as_dict().items() if k in centers})
    return centers


def add_devices(line: np.ndarray, rng: np.random.Generator, geometry: CarmGeometry, pose: CarmPose,
                uv_ideal: dict[str, np.ndarray], centroids: Landmarks3D, motions: dict[str, LevelMotion],
                options: SimulationOptions) -> list[Kwire]:
    """Table and K-wires (in the levels nearest the image centre) added to the line integrals, in place."""
    cols, rows = geometry.intrinsics.size_px
    nearest = sorted(uv_ideal, key=lambda lb: np.linalg.norm(uv_ideal[lb] - ((cols - 1) / 2.0, (rows - 1) / 2.0)))
    wires = plan_kwires(rng, nearest, centroids.as_dict(), motions, options) if options.n_kwires > 0 else []
    line += np.float32(options.table_line_integral)
    for wire in wires:
        add_kwire(line, wire, geometry, pose, options.kwire_mu_per_mm)
    return wires


def surgeon_clicks(rng: np.random.Generator, uv_true: dict[str, np.ndarray], visible: dict[str, bool],
                   intr: CarmIntrinsics, options: SimulationOptions) -> Landmarks2D:
    """``click_levels`` (or the adjacent visible run nearest the centre) at uv_true + N(0, click_sd_mm)."""
    names = sorted(uv_true, key=level_index)
    center_px = (np.asarray(intr.size_px, float) - 1.0) / 2.0
    if options.click_levels:
        chosen = list(options.click_levels)
    elif options.n_clicks > 0:
        chosen = choose_click_levels(names, uv_true, visible, center_px, options.n_clicks)
    else:
        chosen = []
    missing = [lb for lb in chosen if lb not in uv_true]
    if missing:
        raise LandmarkError(f"click level(s) {', '.join(missing)} have no CT centroid; choose among "
                            f"{', '.join(names)}")
    sd_px = options.click_sd_mm / np.asarray(intr.pixel_spacing_mm, float)
    uv = np.array([uv_true[lb] + rng.normal(0.0, 1.0, 2) * sd_px for lb in chosen]).reshape(-1, 2)
    return Landmarks2D(chosen, uv, "simulation", tuple(intr.pixel_spacing_mm))


def simulate_case(volume: Volume, vertebra_labels: np.ndarray | None, centroids: Landmarks3D,
                  geometry: CarmGeometry, pose: CarmPose, options: SimulationOptions | None = None,
                  seed: int = 0) -> SimulatedXray:
    """Simulate one intraoperative AP C-arm image of ``volume`` under ``pose`` (module docstring).

    vertebra_labels: label map on the CT grid with CarmReg values (1 + LEVEL_NAMES.index; see
        ``carmreg.logic.geometry.vertebrae.to_carmreg_labels``), or None for no per-level motion.
    centroids: true CT centroids (LPS mm) of the levels to report (e.g. ``centroids_from_labels``).
    Deterministic for a given seed (random draws in order: motions, K-wires, noise, clicks, 3D noise).
    """
    options = options or SimulationOptions()
    _check_inputs(volume, vertebra_labels, centroids)
    rng = np.random.default_rng(seed)
    intr, centroids = geometry.intrinsics, centroids.sorted()
    t0 = time.perf_counter()
    mu, mu_soft = attenuation(volume.hu, options)
    motions = draw_level_motions(rng, motion_centers(vertebra_labels, volume.ijk_to_lps, centroids), options)
    t1 = time.perf_counter()
    line = render_moved_anatomy(mu, vertebra_labels, volume.ijk_to_lps, motions, mu_soft, geometry, pose,
                                options.refine_thick_slices)
    del mu
    t2 = time.perf_counter()

    P = geometry.projection_matrix(pose)
    points = centroids.as_dict()
    uv_projected = {lb: project(P, c[None])[0] for lb, c in points.items()}
    uv_ideal = {lb: project(P, (motions[lb].apply(c) if lb in motions else c)[None])[0] for lb, c in points.items()}
    wires = add_devices(line, rng, geometry, pose, uv_ideal, centroids, motions, options)
    distortion = IntensifierDistortion(tuple((np.asarray(intr.size_px, float) - 1.0) / 2.0),
                                       tuple(intr.pixel_spacing_mm), options.field_diameter_mm / 2.0,
                                       options.pincushion_edge_mm, options.s_distortion_edge_mm)
    seen = line
    if options.pincushion_edge_mm or options.s_distortion_edge_mm:
        seen = resample_distorted(line, distortion)
    display, facts = detect(seen, intr, options, rng)
    pixels = np.round(display * 65535.0).astype(np.uint16)
    if options.burn_in_text:
        burn_in_text(pixels, text_lines(options, seed), 60000)
    t3 = time.perf_counter()

    uv_true = {lb: distortion.distort(uv) for lb, uv in uv_ideal.items()}
    limit_px = (options.field_diameter_mm / 2.0 - options.visibility_margin_mm) / float(np.mean(intr.pixel_spacing_mm))
    visible = {lb: bool(np.linalg.norm(uv - distortion.center_px) < limit_px) for lb, uv in uv_true.items()}
    clicks = surgeon_clicks(rng, uv_true, visible, intr, options)
    ct_points = centroids.points_lps_mm + rng.normal(0.0, options.ct_click_sd_mm, centroids.points_lps_mm.shape)
    timing = {"prepare_s": t1 - t0, "render_s": t2 - t1, "detect_s": t3 - t2}
    return SimulatedXray(pixels, geometry, pose, distortion, motions, centroids,
                         Landmarks3D(centroids.labels, ct_points, "simulation"), uv_projected, uv_true, visible,
                         clicks, wires, options, int(seed), facts, line, timing)


def write_simulated_case(out_dir: str | Path, sim: SimulatedXray) -> dict[str, Path]:
    """Write xray.dcm (XA with geometry), xray.png (16-bit), xray_centroids.mrk.json, ct_centroids.mrk.json
    and ground_truth.json into ``out_dir`` (atomic writes). Returns the paths by key."""
    from carmreg.logic.io.xray import write_png16, write_xray_dicom

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    intr = sim.geometry.intrinsics
    paths = {"xray": out / "xray.dcm", "xray_png": out / "xray.png",
             "xray_landmarks": out / "xray_centroids.mrk.json", "ct_landmarks": out / "ct_centroids.mrk.json",
             "ground_truth": out / "ground_truth.json"}
    write_xray_dicom(paths["xray"], sim.pixels, intr, sod_mm=sim.geometry.sod_mm, modality="XA")
    write_png16(paths["xray_png"], sim.pixels)
    write_landmarks_2d(paths["xray_landmarks"], sim.clicks, tuple(intr.pixel_spacing_mm))
    write_landmarks_3d(paths["ct_landmarks"], sim.ct_landmarks)
    atomic_write_json(paths["ground_truth"], sim.ground_truth())
    return paths
