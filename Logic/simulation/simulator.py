"""Simulated intraoperative C-arm X-ray with an exactly known pose (the ground truth for testing).

Everything is computed from a CT (HU, LPS mm), its vertebra label map and vertebral centroids. Frames and
units follow ``Logic/camera.py``: world = CT LPS mm, detector pixels (u, v) = (column, row) with pixel centres
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
   ``M_k @ ijk_to_lps``; rigid maps keep path lengths, so ``Logic.drr_cpu`` renders it exactly. With all
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
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
from scipy import ndimage

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import GeometryError, LandmarkError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project, rotation_matrix
from carmreg.logic.geometry.vertebrae import CARMREG_VERTEBRAE, level_ordinals
from carmreg.logic.geometry.volume import MuLevel, Volume, hu_to_mu
from carmreg.logic.io.atomic import atomic_write_json
from carmreg.logic.io.landmarks import (
    Landmarks2D,
    Landmarks3D,
    level_index,
    normalize_level_name,
    write_landmarks_2d,
    write_landmarks_3d,
)
from carmreg.logic.jit import njit

GROUND_TRUTH_SCHEMA = "carmreg-ground-truth/1"


@dataclass(frozen=True)
class SimulationOptions:
    """Every parameter of the simulation (units in the names). A value of 0 switches an effect off."""

    # detector (used by ``default_geometry``): 9-inch image intensifier
    sdd_mm: float = 1000.0
    size_px: tuple[int, int] = (1024, 1024)
    pixel_spacing_mm: float = 0.25
    sod_mm: float = 600.0
    field_diameter_mm: float = 230.0
    # pose ranges for ``random_pose`` (uniform in +- range)
    level_offset_levels: float = 2.0
    lateral_range_mm: float = 20.0
    depth_range_mm: float = 50.0
    rotation_range_deg: float = 10.0
    # per-level rigid motion: each angle ~ N(0, sd) clipped at max; translation rms magnitude
    level_rotation_sd_deg: float = 2.0
    level_rotation_max_deg: float = 5.0
    level_translation_rms_mm: float = 1.0
    # attenuation (thick slices refined linearly first, see ``refine_thick_slices``)
    refine_thick_slices: bool = True
    mu_water_per_mm: float = 0.02
    soft_tissue_hu: float = 40.0
    bone_contrast_factor: float = 1.5
    table_line_integral: float = 0.15
    n_kwires: int = 2
    kwire_diameter_mm: float = 1.6
    kwire_length_mm: float = 150.0
    kwire_mu_per_mm: float = 0.9
    # distortion at the field edge (detector mm)
    pincushion_edge_mm: float = 4.0
    s_distortion_edge_mm: float = 2.0
    # detection and display
    scatter_fraction: float = 0.10
    scatter_sigma_mm: float = 30.0
    photons_per_pixel: float = 2000.0
    detector_blur_sigma_mm: float = 0.3
    vignetting: float = 0.2
    display_mode: str = "log"
    display_mid_grey: float = 0.45
    display_contrast: float = 0.55
    edge_enhancement: float = 1.0
    edge_sigma_mm: float = 3.0
    range_compression: float = 0.75
    range_sigma_mm: float = 25.0
    burn_in_text: bool = True
    # landmark clicks
    n_clicks: int = 3
    click_levels: tuple[str, ...] | None = None
    click_sd_mm: float = 0.9
    ct_click_sd_mm: float = 0.0
    visibility_margin_mm: float = 5.0

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}


def sample_options(rng: np.random.Generator, base: SimulationOptions | None = None, *,
                   live_frame: bool = False) -> SimulationOptions:
    """Draw the realism parameters from the ranges reported in the literature (DATA.md).

    Bone contrast U(0.76, 1.7); scatter/glare U(0.05, 0.15); photons log-uniform in [1e3, 1e4] for a saved
    frame or [50, 500] for a live one; vignetting U(0.1, 0.3); pincushion U(2, 8) mm and S-distortion
    U(1, 5) mm at the field edge; 1 or 2 K-wires.
    """
    base = base or SimulationOptions()
    lo, hi = (50.0, 500.0) if live_frame else (1e3, 1e4)
    return dataclasses.replace(
        base, bone_contrast_factor=float(rng.uniform(0.76, 1.7)), scatter_fraction=float(rng.uniform(0.05, 0.15)),
        photons_per_pixel=float(np.exp(rng.uniform(np.log(lo), np.log(hi)))),
        vignetting=float(rng.uniform(0.1, 0.3)), pincushion_edge_mm=float(rng.uniform(2.0, 8.0)),
        s_distortion_edge_mm=float(rng.uniform(1.0, 5.0)), n_kwires=int(rng.integers(1, 3)))


def default_geometry(volume: Volume, options: SimulationOptions | None = None) -> CarmGeometry:
    """Nominal C-arm of ``options``: isocentre at the CT volume centre, square pixels, centred principal point."""
    o = options or SimulationOptions()
    intr = CarmIntrinsics(o.sdd_mm, (o.pixel_spacing_mm, o.pixel_spacing_mm), tuple(o.size_px),
                          sources={"sdd_mm": "simulation", "pixel_spacing_mm": "simulation"})
    return CarmGeometry(intr, tuple(float(x) for x in volume.center_lps_mm()), o.sod_mm)


# ----------------------------------------------------------------------------------------------- pose

def point_along_spine(centroids: Landmarks3D, level_position: float) -> np.ndarray:
    """LPS mm of a fractional position along the spine (``level_ordinals`` units: adjacent levels 1 apart)
    by linear interpolation of the centroids, clamped to the labelled range."""
    lm = centroids.sorted()
    ordinals = level_ordinals(lm.labels)
    idx = np.array([ordinals[lb] for lb in lm.labels], float)
    x = float(np.clip(level_position, idx[0], idx[-1]))
    return np.array([np.interp(x, idx, lm.points_lps_mm[:, a]) for a in range(3)])


def random_pose(rng: np.random.Generator, options: SimulationOptions, centroids: Landmarks3D,
                around_level: str | None = None, *, geometry: CarmGeometry) -> CarmPose:
    """A C-arm pose aimed near the spine: the principal ray passes through a point of the spine within
    +- ``level_offset_levels`` levels of ``around_level`` (random level when None), offset laterally by
    U(+- lateral_range_mm); depth U(+- depth_range_mm) about the nominal isocentre depth; rotations
    U(+- rotation_range_deg) each. The moved isocentre c + t lies on the principal ray (camera.py)."""
    labels = centroids.sorted().labels
    level = normalize_level_name(around_level) if around_level is not None else labels[int(rng.integers(len(labels)))]
    offset = rng.uniform(-1.0, 1.0) * options.level_offset_levels
    target = point_along_spine(centroids, level_ordinals([*labels, level])[level] + offset)
    c = np.asarray(geometry.isocenter_lps_mm, float)
    ty = target[0] - c[0] + rng.uniform(-1.0, 1.0) * options.lateral_range_mm
    tz = target[2] - c[2]
    tx = rng.uniform(-1.0, 1.0) * options.depth_range_mm
    rx, ry, rz = rng.uniform(-1.0, 1.0, 3) * options.rotation_range_deg
    return CarmPose(float(tx), float(ty), float(tz), float(rx), float(ry), float(rz))


# ----------------------------------------------------------------------------------------------- motion

@dataclass
class LevelMotion:
    """Rigid motion of one vertebra about ``center_lps_mm``: x -> R (x - c) + c + t (LPS mm).

    ``rotation_deg`` are the angles about the LPS x, y, z axes, R = Rz Ry Rx (applied x first)."""

    name: str
    center_lps_mm: np.ndarray
    rotation_deg: np.ndarray
    translation_mm: np.ndarray

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous LPS -> LPS."""
        ax, ay, az = self.rotation_deg
        r = rotation_matrix([0, 0, 1], az) @ rotation_matrix([0, 1, 0], ay) @ rotation_matrix([1, 0, 0], ax)
        m = np.eye(4)
        m[:3, :3] = r
        m[:3, 3] = self.center_lps_mm + self.translation_mm - r @ self.center_lps_mm
        return m

    def apply(self, points_lps_mm: np.ndarray) -> np.ndarray:
        m = self.matrix
        return np.asarray(points_lps_mm, float) @ m[:3, :3].T + m[:3, 3]


def draw_level_motions(rng: np.random.Generator, centers: dict[str, np.ndarray],
                       options: SimulationOptions) -> dict[str, LevelMotion]:
    """One motion per level, head to sacrum (reproducible order): angles ~ N(0, sd) clipped to +- max,
    translation ~ N(0, rms / sqrt(3)) per axis."""
    out = {}
    for name in sorted(centers, key=level_index):
        angles = np.clip(rng.normal(0.0, options.level_rotation_sd_deg, 3), -options.level_rotation_max_deg,
                         options.level_rotation_max_deg)
        shift = rng.normal(0.0, options.level_translation_rms_mm / np.sqrt(3.0), 3)
        out[name] = LevelMotion(name, np.asarray(centers[name], float), angles, shift)
    return out


# ----------------------------------------------------------------------------------------------- distortion

@dataclass(frozen=True)
class IntensifierDistortion:
    """Image-intensifier distortion about ``center_px``, in detector mm (x = (u - u0) du, y = (v - v0) dv).

    Ideal point at radius r appears at radius ``r (1 + k r^2)`` (pincushion, k = edge_mm / R^3) rotated by
    ``phi(r) = phi_edge (r / R)^2`` (S-distortion, phi_edge = s_edge_mm / R), R the field radius in mm.
    """

    center_px: tuple[float, float]
    pixel_spacing_mm: tuple[float, float]
    field_radius_mm: float
    pincushion_edge_mm: float = 0.0
    s_distortion_edge_mm: float = 0.0

    @property
    def k_per_mm2(self) -> float:
        return self.pincushion_edge_mm / self.field_radius_mm**3

    @property
    def phi_edge_rad(self) -> float:
        return self.s_distortion_edge_mm / self.field_radius_mm

    def _to_mm(self, uv_px):
        uv = np.asarray(uv_px, float)
        return ((uv[..., 0] - self.center_px[0]) * self.pixel_spacing_mm[0],
                (uv[..., 1] - self.center_px[1]) * self.pixel_spacing_mm[1])

    def _to_px(self, x, y):
        return np.stack([x / self.pixel_spacing_mm[0] + self.center_px[0],
                         y / self.pixel_spacing_mm[1] + self.center_px[1]], -1)

    def _twist(self, x, y, r, sign):
        phi = sign * self.phi_edge_rad * (r / self.field_radius_mm) ** 2
        c, s = np.cos(phi), np.sin(phi)
        return c * x - s * y, s * x + c * y

    def distort(self, uv_px) -> np.ndarray:
        """Ideal (pinhole) pixel positions (..., 2) -> where they appear in the image."""
        x, y = self._to_mm(uv_px)
        r = np.hypot(x, y)
        scale = 1.0 + self.k_per_mm2 * r * r
        x, y = self._twist(x * scale, y * scale, r, 1.0)
        return self._to_px(x, y)

    def undistort(self, uv_px) -> np.ndarray:
        """Image pixel positions (..., 2) -> ideal positions (exact inverse by Newton on the radius)."""
        x, y = self._to_mm(uv_px)
        rd = np.hypot(x, y)
        k = self.k_per_mm2
        r = rd.copy()
        for _ in range(30):
            step = (r + k * r**3 - rd) / (1.0 + 3.0 * k * r * r)
            r = r - step
            if np.all(np.abs(step) < 1e-12):
                break
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        x, y = self._twist(x, y, r, -1.0)
        return self._to_px(x * scale, y * scale)

    @classmethod
    def from_dict(cls, d: dict) -> IntensifierDistortion:
        """Inverse of ``as_dict`` (e.g. from ground_truth.json)."""
        return cls(tuple(d["center_px"]), tuple(d["pixel_spacing_mm"]), float(d["field_radius_mm"]),
                   float(d["pincushion_edge_mm"]), float(d["s_distortion_edge_mm"]))

    def as_dict(self) -> dict:
        return {"model": "pincushion r(1 + k r^2) then twist phi_edge (r/R)^2 about center_px, detector mm",
                "center_px": list(self.center_px), "pixel_spacing_mm": list(self.pixel_spacing_mm),
                "field_radius_mm": self.field_radius_mm,
                "pincushion_edge_mm": self.pincushion_edge_mm, "s_distortion_edge_mm": self.s_distortion_edge_mm,
                "k_per_mm2": self.k_per_mm2, "phi_edge_rad": self.phi_edge_rad}


def resample_distorted(image: np.ndarray, distortion: IntensifierDistortion) -> np.ndarray:
    """Image as seen through the distortion: out(q) = image(D^-1(q)), bilinear, edge values outside."""
    rows, cols = image.shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    ideal = distortion.undistort(np.stack([uu, vv], -1))
    coords = np.stack([ideal[..., 1], ideal[..., 0]])
    return ndimage.map_coordinates(image, coords, order=1, mode="nearest").astype(np.float32)


# ----------------------------------------------------------------------------------------------- K-wires

@dataclass
class Kwire:
    """A steel cylinder from ``tip_lps_mm`` to ``end_lps_mm`` (surgical frame, after its level's motion)."""

    level: str
    tip_lps_mm: np.ndarray
    end_lps_mm: np.ndarray
    diameter_mm: float

    def as_dict(self) -> dict:
        return {"level": self.level, "tip_lps_mm": self.tip_lps_mm.tolist(),
                "end_lps_mm": self.end_lps_mm.tolist(), "diameter_mm": self.diameter_mm}


def plan_kwires(rng: np.random.Generator, levels: list[str], centroids: dict[str, np.ndarray],
                motions: dict[str, LevelMotion], options: SimulationOptions) -> list[Kwire]:
    """Pedicle wires: tip in the vertebral body 6-10 mm from the midline, running posteriorly and laterally
    (15-25 deg) with a small cranio-caudal tilt, out of the patient's back; alternate sides; moved with
    their level."""
    wires = []
    for n, name in enumerate(levels[: options.n_kwires]):
        side = 1.0 if n % 2 == 0 else -1.0
        tip = centroids[name] + np.array([side * rng.uniform(6.0, 10.0), rng.uniform(-2.0, 4.0),
                                          rng.uniform(-3.0, 3.0)])
        lateral, tilt = np.tan(np.deg2rad(rng.uniform(15.0, 25.0))), np.tan(np.deg2rad(rng.uniform(-10, 10)))
        direction = np.array([side * lateral, 1.0, tilt])
        end = tip + options.kwire_length_mm * direction / np.linalg.norm(direction)
        moved = motions[name].apply(np.array([tip, end])) if name in motions else np.array([tip, end])
        wires.append(Kwire(name, moved[0], moved[1], options.kwire_diameter_mm))
    return wires


def kwire_path_lengths(wire: Kwire, source_lps_mm: np.ndarray, pixels_lps_mm: np.ndarray) -> np.ndarray:
    """Exact length (mm) of each source->pixel ray inside a finite cylinder (flat ends). pixels: (n, 3)."""
    axis = wire.end_lps_mm - wire.tip_lps_mm
    length = np.linalg.norm(axis)
    e = axis / length
    d = pixels_lps_mm - source_lps_mm
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m0 = source_lps_mm - wire.tip_lps_mm
    w = d - (d @ e)[:, None] * e
    m = m0 - (m0 @ e) * e
    a, b, c = np.einsum("ij,ij->i", w, w), 2.0 * (w @ m), m @ m - (wire.diameter_mm / 2.0) ** 2
    disc = b * b - 4.0 * a * c
    hit = (disc > 0) & (a > 1e-12)
    root = np.sqrt(np.where(hit, disc, 0.0))
    a_safe = np.where(hit, a, 1.0)
    t1, t2 = (-b - root) / (2 * a_safe), (-b + root) / (2 * a_safe)
    # axial coordinate s(t) = m0.e + t d.e must lie in [0, length]
    de, s0 = d @ e, m0 @ e
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (0.0 - s0) / de, (length - s0) / de
    lo = np.where(np.abs(de) > 1e-12, np.minimum(ta, tb), -np.inf)
    hi = np.where(np.abs(de) > 1e-12, np.maximum(ta, tb), np.inf)
    inside_axial = (np.abs(de) > 1e-12) | ((s0 >= 0) & (s0 <= length))
    chord = np.minimum(t2, hi) - np.maximum(t1, lo)
    return np.where(hit & inside_axial, np.clip(chord, 0.0, None), 0.0)


# ----------------------------------------------------------------------------------------------- rendering

def add_kwire(line: np.ndarray, wire: Kwire, geometry: CarmGeometry, pose: CarmPose, mu_per_mm: float) -> None:
    """line += mu * (path length of every pixel ray inside the wire), only over the window the wire covers."""
    from carmreg.logic.geometry.camera import pixel_to_detector_lps

    rows, cols = line.shape
    uv = project(geometry.projection_matrix(pose), np.array([wire.tip_lps_mm, wire.end_lps_mm]))
    pad = 3 + wire.diameter_mm * float(np.max(geometry.magnification(pose, wire.end_lps_mm))) / min(
        geometry.intrinsics.pixel_spacing_mm)
    u_lo, v_lo = np.maximum(np.floor(uv.min(axis=0) - pad).astype(int), 0)
    u_hi, v_hi = np.minimum(np.ceil(uv.max(axis=0) + pad).astype(int) + 1, (cols, rows))
    if u_hi <= u_lo or v_hi <= v_lo:
        return
    vv, uu = np.mgrid[v_lo:v_hi, u_lo:u_hi]
    pixels = pixel_to_detector_lps(geometry, pose, np.stack([uu.ravel(), vv.ravel()], -1))
    chord = kwire_path_lengths(wire, geometry.source_lps_mm(pose), pixels)
    line[v_lo:v_hi, u_lo:u_hi] += (mu_per_mm * chord).reshape(vv.shape).astype(np.float32)


@njit(parallel=True)
def _refine_last_axis(src, f, out):
    """out[a, b, m] = linear interpolation of src[a, b, :] at x = (m + 0.5) / f - 0.5 (clamped)."""
    n0, n1, n = src.shape
    for i in numba.prange(n0):
        for j in range(n1):
            for m in range(n * f):
                x = min(max((m + 0.5) / f - 0.5, 0.0), n - 1.0)
                k = min(int(x), max(n - 2, 0))
                w = x - k
                out[i, j, m] = src[i, j, k] * (1.0 - w) + src[i, j, min(k + 1, n - 1)] * w


def refine_thick_slices(values: np.ndarray, ijk_to_lps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Refine every axis more than 1.5 x coarser than the finest one by f = ceil(s / s_min), linearly.

    New voxel n of a refined axis sits at old index x = (n + 0.5) / f - 0.5 (same physical box; clamped at
    the ends). Linear in ``values``, so refining the parts of a sum equals refining the sum. Removes the
    stair-steps of thick slices from the simulated image (the patient is continuous, the CT is not).
    """
    out, affine = np.asarray(values, np.float32), np.asarray(ijk_to_lps, float).copy()
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    for axis in range(3):
        f = int(np.ceil(spacing[axis] / spacing.min() - 1e-6))
        if spacing[axis] <= 1.5 * spacing.min() or f <= 1:
            continue
        src = np.ascontiguousarray(np.moveaxis(out, axis, 2))
        refined = np.empty(src.shape[:2] + (src.shape[2] * f,), np.float32)
        _refine_last_axis(src, f, refined)
        out = np.moveaxis(refined, 2, axis)
        origin_shift = np.zeros(3)
        origin_shift[axis] = 0.5 / f - 0.5
        affine[:3, 3] = affine[:3, :3] @ origin_shift + affine[:3, 3]
        affine[:3, axis] /= f
    return np.ascontiguousarray(out, dtype=np.float32), affine


def _prepared(values: np.ndarray, ijk_to_lps: np.ndarray, refine: bool) -> MuLevel:
    if refine:
        return MuLevel(*refine_thick_slices(values, ijk_to_lps), None)
    return MuLevel(np.ascontiguousarray(values, dtype=np.float32), ijk_to_lps, None)


def render_moved_anatomy(mu: np.ndarray, labels: np.ndarray | None, ijk_to_lps: np.ndarray,
                         motions: dict[str, LevelMotion], mu_soft: float, geometry: CarmGeometry,
                         pose: CarmPose, refine: bool = False) -> np.ndarray:
    """Line integrals of the CT with each labelled vertebra moved rigidly (module docstring, step 2).

    With ``refine`` every part goes through ``refine_thick_slices`` before rendering (exact additivity is
    kept because the refinement is linear).
    """
    values = {v: n for v, n in CARMREG_VERTEBRAE.items() if n in motions}
    if labels is None or not values:
        return render_line_integrals(_prepared(mu, ijk_to_lps, refine), geometry, pose)
    moving = np.isin(labels, list(values))
    background = np.where(moving, np.float32(mu_soft), mu).astype(np.float32)
    total = render_line_integrals(_prepared(background, ijk_to_lps, refine), geometry, pose)
    del background
    boxes = ndimage.find_objects(np.where(moving, labels, 0).astype(np.int32))
    for value, box in enumerate(boxes, start=1):
        if box is None:
            continue
        sl = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, n)) for s, n in zip(box, labels.shape,
                                                                                  strict=True))
        sub = np.where(labels[sl] == value, mu[sl] - np.float32(mu_soft), np.float32(0.0))
        shift = np.eye(4)
        shift[:3, 3] = [s.start for s in sl]
        level = _prepared(sub, ijk_to_lps @ shift, refine)
        level.ijk_to_lps = motions[values[value]].matrix @ level.ijk_to_lps
        _add_rendered_window(total, level, geometry, pose)
    return total


def detector_window(intr: CarmIntrinsics, u_start: int, v_start: int, cols: int, rows: int) -> CarmIntrinsics:
    """Intrinsics of the sub-image [v_start:v_start+rows, u_start:u_start+cols] of the detector (same rays).

    Built without validation on purpose: the principal point may lie outside a small window.
    """
    window = object.__new__(CarmIntrinsics)
    u0, v0 = intr.principal_point_px
    for name, value in (("sdd_mm", intr.sdd_mm), ("pixel_spacing_mm", tuple(intr.pixel_spacing_mm)),
                        ("size_px", (int(cols), int(rows))), ("principal_point_px", (u0 - u_start, v0 - v_start)),
                        ("sources", {})):
        object.__setattr__(window, name, value)
    return window


def _add_rendered_window(total: np.ndarray, level: MuLevel, geometry: CarmGeometry, pose: CarmPose) -> None:
    """total += DRR of ``level``, rendered only over the detector window its grid box projects into."""
    n = np.array(level.mu_per_mm.shape, float)
    corners = np.array([[a, b, c] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                        for c in (-0.5, n[2] - 0.5)])
    uv = project(geometry.projection_matrix(pose), corners @ level.ijk_to_lps[:3, :3].T + level.ijk_to_lps[:3, 3])
    rows, cols = total.shape
    u_lo, v_lo = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
    u_hi, v_hi = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, (cols, rows))
    if u_hi <= u_lo or v_hi <= v_lo:
        return
    window = detector_window(geometry.intrinsics, u_lo, v_lo, u_hi - u_lo, v_hi - v_lo)
    total[v_lo:v_hi, u_lo:u_hi] += render_line_integrals(level, geometry, pose, intrinsics=window)


def label_centers(labels: np.ndarray, ijk_to_lps: np.ndarray) -> dict[str, np.ndarray]:
    """Centre of mass (LPS mm) of every CarmReg-labelled vertebra present."""
    out = {}
    for value, box in enumerate(ndimage.find_objects(np.asarray(labels).astype(np.int32, copy=False)), start=1):
        if box is None or value not in CARMREG_VERTEBRAE:
            continue
        ijk = np.argwhere(labels[box] == value).mean(axis=0) + [s.start for s in box]
        out[CARMREG_VERTEBRAE[value]] = ijk_to_lps[:3, :3] @ ijk + ijk_to_lps[:3, 3]
    return out


# ----------------------------------------------------------------------------------------------- detection

def _radius_mm(intr: CarmIntrinsics) -> np.ndarray:
    cols, rows = intr.size_px
    du, dv = intr.pixel_spacing_mm
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    return np.hypot((uu - (cols - 1) / 2.0) * du, (vv - (rows - 1) / 2.0) * dv)


def _wide_blur(image: np.ndarray, sigma_px: float, mode: str = "constant") -> np.ndarray:
    """Gaussian blur with a large sigma (>= 8 px), computed on 8 x 8 block means then upsampled linearly."""
    f = 8
    rows, cols = image.shape
    pad = ((0, -rows % f), (0, -cols % f))
    blocks = np.pad(image, pad, mode="edge").reshape((rows + pad[0][1]) // f, f, (cols + pad[1][1]) // f, f)
    small = ndimage.gaussian_filter(blocks.mean(axis=(1, 3)), sigma_px / f, mode=mode)
    # block b covers pixels [b f, b f + f - 1]: its centre is at pixel b f + (f - 1) / 2
    coords = [(np.arange(n) - (f - 1) / 2.0) / f for n in (rows, cols)]
    grid = np.meshgrid(*coords, indexing="ij")
    return ndimage.map_coordinates(small, grid, order=1, mode="nearest").astype(np.float32)


def detect(line_integrals: np.ndarray, intr: CarmIntrinsics, options: SimulationOptions,
           rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Distorted line integrals -> display values (float, 0..1, bone dark) and the exposure facts."""
    du = float(np.mean(intr.pixel_spacing_mm))
    r = _radius_mm(intr)
    radius = options.field_diameter_mm / 2.0
    field = np.clip((radius - r) / 0.75 + 0.5, 0.0, 1.0)  # ~1.5 mm soft collimator edge
    primary = np.exp(-line_integrals.astype(np.float64)) * field
    g = options.scatter_fraction
    signal = primary if g <= 0 else (1.0 - g) * primary + g * _wide_blur(primary, options.scatter_sigma_mm / du)
    central = r < 0.3 * radius
    n0 = max(options.photons_per_pixel, 1.0) / max(float(signal[central].mean()), 1e-300)
    counts = signal * n0
    if options.photons_per_pixel > 0:
        counts = rng.poisson(counts).astype(np.float64)
    if options.detector_blur_sigma_mm > 0:
        counts = ndimage.gaussian_filter(counts, options.detector_blur_sigma_mm / du)
    counts *= 1.0 - options.vignetting * np.clip(r / radius, 0.0, 1.0) ** 2
    display = video_display(counts / max(options.photons_per_pixel, 1.0), field, central, du, options)
    facts = {"n0_photons_unattenuated": float(n0), "mean_counts_central": float(np.mean(counts[central])),
             "display_mode": options.display_mode}
    return display, facts


def video_display(relative: np.ndarray, field: np.ndarray, central: np.ndarray, du_mm: float,
                  options: SimulationOptions) -> np.ndarray:
    """Detected signal (1 = the AEC target) -> display value 0..1, bone dark.

    linear: ``mid * relative`` (for tests). log (the usual II-TV chain with its image processing):
    ``y = log(relative)``; dynamic range compression ``y - b G_wide * y`` (b = range_compression); edge
    enhancement ``y + a (y - G_edge * y)``; then ``mid + contrast * (y - median of the AEC disc)`` (the AEC
    region at mid grey; lungs may saturate white as in real thoracic fluoroscopy).
    """
    mid = options.display_mid_grey
    if options.display_mode == "linear":
        return np.clip(mid * relative * field, 0.0, 1.0)
    y = np.log(np.clip(relative, 1e-4, None))
    y = np.where(field > 0.5, y, float(np.median(y[central])))  # no collimator edge ringing
    if options.range_compression > 0:
        y = y - options.range_compression * _wide_blur(y, options.range_sigma_mm / du_mm, "nearest")
    if options.edge_enhancement > 0:
        y = y + options.edge_enhancement * (y - ndimage.gaussian_filter(y, options.edge_sigma_mm / du_mm))
    y -= float(np.median(y[central]))
    return np.clip(mid + options.display_contrast * y, 0.0, 1.0) * field


def burn_in_text(pixels: np.ndarray, lines: dict[str, list[str]], value: int) -> np.ndarray:
    """Draw text into the corners ('tl', 'tr', 'bl', 'br') of a uint16 image (in place) with PIL."""
    from PIL import Image, ImageDraw, ImageFont

    rows, cols = pixels.shape
    size = max(10, rows // 40)
    font = ImageFont.load_default(size=size)
    canvas = Image.new("L", (cols, rows), 0)
    draw = ImageDraw.Draw(canvas)
    pad, step = rows // 60, int(size * 1.3)
    for corner, text in lines.items():
        for n, line in enumerate(text):
            width = draw.textlength(line, font=font)
            x = pad if corner[1] == "l" else cols - pad - width
            y = pad + n * step if corner[0] == "t" else rows - pad - (len(text) - n) * step
            draw.text((x, y), line, fill=255, font=font)
    mask = np.asarray(canvas) > 127
    pixels[mask] = value
    return pixels


def tube_kv(bone_contrast_factor: float) -> float:
    """Tube voltage matching a bone contrast factor (x1.7 at 60 kV, x1 at 90 kV, x0.76 at 120 kV; linear)."""
    return float(np.interp(bone_contrast_factor, [0.76, 1.0, 1.7], [120.0, 90.0, 60.0]))


def _text_lines(options: SimulationOptions, seed: int) -> dict[str, list[str]]:
    kv = tube_kv(options.bone_contrast_factor)
    return {"tl": ["CARMREG SIMULATION", f"SEED {seed}"],
            "tr": [f"{kv:.0f} kV  {1.0 + 2.0 * min(options.photons_per_pixel / 1e4, 1.0):.1f} mA", "PULSED 8 p/s"],
            "bl": ["AP", "NOT FOR DIAGNOSIS"],
            "br": ["SAVED 1/1", "9\" FIELD"]}


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
        burn_in_text(pixels, _text_lines(options, seed), 60000)
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


# ----------------------------------------------------------------------------------------------- command line

def load_vertebra_labels(path, ct: Volume) -> np.ndarray:
    """A vertebra label map on the CT grid, as CarmReg values. TotalSegmentator v2 maps (values above 27)
    are relabelled; anything else is taken as CarmReg values (1 + LEVEL_NAMES.index)."""
    from carmreg.logic.geometry.vertebrae import TOTALSEGMENTATOR_V2_VERTEBRAE, to_carmreg_labels
    from carmreg.logic.io.volumes import load_volume

    labels = load_volume(path)
    if labels.shape != ct.shape or not np.allclose(labels.ijk_to_lps, ct.ijk_to_lps, atol=1e-3):
        raise GeometryError(f"{path}: the vertebra label map ({'x'.join(map(str, labels.shape))}) is not on the "
                            f"CT grid ({'x'.join(map(str, ct.shape))}); resample it onto the CT first")
    values = np.asarray(labels.hu)
    if int(values.max()) > max(CARMREG_VERTEBRAE):
        return to_carmreg_labels(values, TOTALSEGMENTATOR_V2_VERTEBRAE)
    return values.astype(np.uint8)


def _cli_inputs(args):
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
    ct, labels, centroids = _cli_inputs(args)
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
