"""An X-ray appearance chain written independently of CarmReg's simulator (issue 11, item 4).

Used by ``bench_appearance.py``. Only the *geometry* is shared with ``carmreg.logic.simulation.simulator``:
the pose draw (``random_pose``), the per-level rigid motion (``draw_level_motions``), pedicle K-wires
(``plan_kwires``/``add_kwire``: exact chord lengths) and the exact line integrals of the moved anatomy
(``render_moved_anatomy``, CarmReg's ray-caster). Everything that turns line integrals into a picture is chosen
here and differs from ``simulator.detect``/``video_display``:

Frames and units: world = CT LPS mm; detector pixels (u, v) = (column, row), 0-based pixel centres; images are
``image[row, column]``; line integrals L are dimensionless (mu in 1/mm times mm).

1. **Attenuation, own bone contrast.** Two line-integral images per detector: ``l_water`` of
   ``mu_w max(1 + HU/1000, 0)`` and ``l_bone`` of the bone excess ``mu_w max(HU - 100, 0) / 1000`` (both with
   each vertebra moved; rendering is linear, so any tube voltage is one sum). The effective attenuation at tube
   voltage kV is ``L = l_water + (f - 1) l_bone + table + mu_w * extra_water_mm`` with the bone factor
   ``f = (100 / kV)^1.2`` (1.68 at 65 kV, 0.80 at 120 kV), then beam hardening ``L_eff = ln(1 + b L) / b``.
2. **Detector geometry.** Image intensifier ("ii"): 960 x 960 px of 0.25 mm, SDD 980 mm, circular field of
   diameter 225 mm; pincushion ``r_d = r (1 + k r^2)`` about a centre off the image centre by up to 6 px, plus a
   1 % anisotropic stretch, applied to the line integrals by exact inverse resampling; electronic black mask
   outside the field. Flat panel ("fp"): 768 x 768 px of 0.388 mm (2 x 2 binned), SDD 1020 mm, no distortion,
   a rectangular collimated field (200-290 mm per side, off-centre) whose outside receives only scatter.
3. **Detection.** Primary ``I = exp(-L_eff)`` inside the field; scatter = ``spr`` times the primary convolved
   with an exponential kernel ``exp(-r / lambda)`` (normalised to the central region's primary); anode heel
   (linear gain along rows) and, on the intensifier, veiling glare and a ``1 / (1 + (c r / R)^2)^2`` brightness
   fall-off; quanta: Poisson with a mean of ``photons`` per pixel in the central region, plus Gaussian read
   noise, then the detector blur; flat panel: a 1 % per-pixel gain residual.
4. **Storage** (``Look.storage``): ``linear`` (value = dark offset + gain x quanta: bone dark; bone bright is the
   same stored with MONOCHROME1 or inverted), ``log`` (attenuation ``-ln(D / D_ref)`` windowed on the field's
   0.5-99.5 percentiles: bone bright; bone dark is its complement), ``display`` (log, dynamic-range
   compression, unsharp mask, window, gamma; 8-bit JPEG). ``bone_bright`` says the polarity *as displayed*.
5. **Display flip and turn** (``mirrored``, ``display_turn``; C-arm display settings): the stored image is flipped
   left-right, then turned (``DISPLAY_TURNS``: by 180 degrees, flipped up-down, or a quarter turn counter-clockwise,
   which swaps columns and rows); the truth follows through the same pixel map (``display_map``).
6. Burnt-in corner text (not in the field on the intensifier; at the detector corners on the flat panel).
"""

from __future__ import annotations

import dataclasses
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage, signal

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.io.landmarks import Landmarks3D
from carmreg.logic.simulation.options import SimulationOptions
from carmreg.logic.simulation.render import add_kwire, render_moved_anatomy
from carmreg.logic.simulation.scene import draw_level_motions, plan_kwires, random_pose
from carmreg.logic.simulation.simulator import choose_click_levels, motion_centers

MU_WATER_PER_MM = 0.02
BONE_THRESHOLD_HU = 100.0
SOFT_TISSUE_HU = 40.0


@dataclass(frozen=True)
class Detector:
    """A C-arm detector: ``kind`` "ii" (image intensifier, circular field) or "fp" (flat panel, rectangular)."""

    kind: str
    sdd_mm: float
    size_px: tuple[int, int]
    pixel_mm: float
    field_diameter_mm: float = 0.0   # intensifier field
    blur_mm: float = 0.3

    @property
    def sod_mm(self) -> float:
        """Source to isocentre: 0.6 SDD (what CarmReg assumes without a DICOM value)."""
        return 0.6 * self.sdd_mm

    def intrinsics(self) -> CarmIntrinsics:
        return CarmIntrinsics(self.sdd_mm, (self.pixel_mm, self.pixel_mm), self.size_px)


DETECTORS = {
    "ii": Detector("ii", 980.0, (960, 960), 0.25, field_diameter_mm=225.0, blur_mm=0.35),
    "fp": Detector("fp", 1020.0, (768, 768), 0.388, blur_mm=0.25),
}


@dataclass(frozen=True)
class Look:
    """Every appearance parameter of one X-ray (units in the names)."""

    kv: float = 80.0
    extra_water_mm: float = 0.0
    table_line_integral: float = 0.15
    hardening: float = 0.05
    spr: float = 0.4
    scatter_length_mm: float = 50.0
    photons: float = 1500.0
    read_noise: float = 2.0
    glare: float = 0.05
    falloff: float = 0.4
    heel: float = 0.0
    storage: str = "log"            # linear | log | display
    bone_bright: bool = False       # as displayed
    compression: float = 0.4
    usm_amount: float = 1.0
    usm_sigma_mm: float = 2.5
    gamma: float = 1.0
    jpeg_quality: int = 85
    mirrored: bool = False
    file: str = "png16"             # png16 | tiff16 | jpeg8 | dcm-sign | dcm-nosign | dcm-mono1
    modality: str = "XA"
    display_turn: str = "none"      # a key of DISPLAY_TURNS, after the mirror

    @property
    def bone_factor(self) -> float:
        """Bone excess attenuation relative to the CT's: (100 / kV)^1.2."""
        return float((100.0 / self.kv) ** 1.2)


@dataclass(frozen=True)
class Variant:
    """A named appearance: its detector and how it changes the case's base look."""

    name: str
    detector: str
    changes: dict
    low_dose: bool = False
    large_patient: bool = False
    note: str = ""


VARIANTS = {v.name: v for v in (
    Variant("ii-dark-log-png", "ii", {"storage": "log", "bone_bright": False, "file": "png16"},
            note="intensifier, log storage, bone dark, 16-bit PNG"),
    Variant("ii-bright-log-png", "ii", {"storage": "log", "bone_bright": True, "file": "png16"},
            note="intensifier, log storage, bone bright, 16-bit PNG"),
    Variant("fp-dark-linear-dcm", "fp", {"storage": "linear", "bone_bright": False, "file": "dcm-sign",
                                        "modality": "RF"},
            note="flat panel, linear storage, bone dark, DICOM RF with PixelIntensityRelationshipSign +1"),
    Variant("fp-bright-linear-mono1-dcm", "fp", {"storage": "linear", "bone_bright": True, "file": "dcm-mono1",
                                                "modality": "DX"},
            note="flat panel, linear storage shown bone bright: DICOM DX MONOCHROME1, sign +1"),
    Variant("fp-bright-log-dcm-nosign", "fp", {"storage": "log", "bone_bright": True, "file": "dcm-nosign",
                                              "modality": "RF"},
            note="flat panel, log storage, bone bright, DICOM RF without PixelIntensityRelationshipSign"),
    Variant("ii-dark-jpeg", "ii", {"storage": "display", "bone_bright": False, "file": "jpeg8"},
            note="intensifier, processed display (unsharp mask, gamma), bone dark, 8-bit JPEG"),
    Variant("fp-bright-jpeg", "fp", {"storage": "display", "bone_bright": True, "file": "jpeg8"},
            note="flat panel, processed display (unsharp mask, gamma), bone bright, 8-bit JPEG"),
    Variant("ii-dark-lowdose-tiff", "ii", {"storage": "log", "bone_bright": False, "file": "tiff16"},
            low_dose=True, note="intensifier, low dose (15-50 quanta/px), log, bone dark, 16-bit TIFF"),
    Variant("fp-bright-large-tiff", "fp", {"storage": "log", "bone_bright": True, "file": "tiff16"},
            large_patient=True, note="flat panel, large patient (+100-160 mm water, 110-125 kV, scatter "
            "2.5-5 x primary): bone barely shows; log, bone bright, 16-bit TIFF"),
    Variant("ii-dark-mirrored-png", "ii", {"storage": "log", "bone_bright": False, "file": "png16",
                                          "mirrored": True},
            note="intensifier, display flipped left-right, log, bone dark, 16-bit PNG"),
    Variant("ii-dark-turned180-png", "ii", {"storage": "log", "bone_bright": False, "file": "png16",
                                           "display_turn": "turned-180"},
            note="intensifier, display turned 180 degrees (head at the bottom), log, bone dark, 16-bit PNG"),
    Variant("fp-bright-flipped-tiff", "fp", {"storage": "log", "bone_bright": True, "file": "tiff16",
                                            "display_turn": "flipped-up-down"},
            note="flat panel, display flipped up-down, log, bone bright, 16-bit TIFF"),
    Variant("fp-dark-turned90-jpeg", "fp", {"storage": "display", "bone_bright": False, "file": "jpeg8",
                                           "display_turn": "turned-90"},
            note="flat panel, display turned a quarter counter-clockwise (the spine across the image), processed "
                 "display, bone dark, 8-bit JPEG"),
)}

DISPLAY_TURNS = ("none", "turned-180", "flipped-up-down", "turned-90")
"""How a display may be turned after its mirror (``Look.display_turn``): not, by 180 degrees, flipped up-down, or a
quarter turn counter-clockwise (the stored image's first row then holds the acquisition's last column)."""


def base_look(rng: np.random.Generator, detector: Detector) -> Look:
    """The case's look on this detector (own ranges): 65-95 kV, scatter 0.2-0.7 x primary (with grid),
    kernel 30-70 mm, 400-4000 quanta/px (log-uniform), read noise 1-4, heel +-15 %, intensifier glare 3-8 %,
    fall-off c 0.3-0.5, compression 0.3-0.6, unsharp mask 0.6-1.5 at 1.5-4 mm, gamma 0.6-1.5, JPEG 70-92."""
    return Look(kv=float(rng.uniform(65, 95)), table_line_integral=float(rng.uniform(0.1, 0.25)),
                hardening=float(rng.uniform(0.03, 0.08)), spr=float(rng.uniform(0.2, 0.7)),
                scatter_length_mm=float(rng.uniform(30, 70)),
                photons=float(np.exp(rng.uniform(np.log(400), np.log(4000)))),
                read_noise=float(rng.uniform(1, 4)), glare=float(rng.uniform(0.03, 0.08)) if detector.kind == "ii"
                else 0.0, falloff=float(rng.uniform(0.3, 0.5)) if detector.kind == "ii" else 0.0,
                heel=float(rng.uniform(-0.15, 0.15)), compression=float(rng.uniform(0.3, 0.6)),
                usm_amount=float(rng.uniform(0.6, 1.5)), usm_sigma_mm=float(rng.uniform(1.5, 4.0)),
                gamma=float(rng.uniform(0.6, 1.5)), jpeg_quality=int(rng.integers(70, 93)))


def variant_look(base: Look, variant: Variant, rng: np.random.Generator) -> Look:
    """The base look changed as the variant says (low dose, large patient, storage, polarity, file)."""
    look = dataclasses.replace(base, **variant.changes)
    if variant.low_dose:
        look = dataclasses.replace(look, photons=float(rng.uniform(15, 50)))
    if variant.large_patient:
        look = dataclasses.replace(look, extra_water_mm=float(rng.uniform(100, 160)), kv=float(rng.uniform(110, 125)),
                                   spr=float(rng.uniform(2.5, 5.0)), scatter_length_mm=float(rng.uniform(60, 100)))
    return look


# ----------------------------------------------------------------------------------------------- scene

@dataclass
class Scene:
    """One case on one detector: line integrals and the truth (ideal P, where each level appears)."""

    ct_name: str
    detector: Detector
    geometry: CarmGeometry
    pose: CarmPose
    l_water: np.ndarray               # (rows, cols) float32, incl. K-wires; distorted on the intensifier
    l_bone: np.ndarray                # (rows, cols) float32, bone excess
    field: np.ndarray                 # (rows, cols) float32 0..1, the exposed field
    uv_true_px: dict                  # level -> (2,) where its moved centroid appears (after distortion)
    visible: dict                     # level -> bool (5 mm inside the field)
    clicked: list                     # three adjacent visible levels nearest the centre
    clicks_uv_px: np.ndarray          # (3, 2) with 0.9 mm click noise per axis
    distortion: dict = field(default_factory=dict)

    @property
    def projection_matrix(self) -> np.ndarray:
        return self.geometry.projection_matrix(self.pose)


def split_mu(hu: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(mu_water_part, mu_bone_excess, their soft-tissue values) per mm (module docstring, step 1)."""
    hu = np.asarray(hu, np.float32)
    water = np.float32(MU_WATER_PER_MM) * np.maximum(1.0 + hu / 1000.0, 0.0).astype(np.float32)
    bone = np.float32(MU_WATER_PER_MM / 1000.0) * np.maximum(hu - BONE_THRESHOLD_HU, 0.0).astype(np.float32)
    return water, bone, MU_WATER_PER_MM * (1.0 + SOFT_TISSUE_HU / 1000.0), 0.0


def draw_pose_and_motion(rng: np.random.Generator, ct, labels, centroids: Landmarks3D,
                         depth_range_mm: float = SimulationOptions.depth_range_mm):
    """(pose on the intensifier geometry, per-level motions): bench_levels' draws (+-2 levels of an inner level,
    +-20 mm lateral, +-``depth_range_mm`` depth about the nominal isocentre (50 mm), +-10 deg; 2 deg / 1 mm rms per
    level). The depth is U(-1, 1) * ``depth_range_mm`` from the same random stream: another range draws the same
    scene with its source nearer or farther."""
    options = SimulationOptions(depth_range_mm=depth_range_mm)
    names = centroids.sorted().labels
    inner = names[2:-2] if len(names) > 5 else names[1:-1]
    geometry = make_geometry(ct, DETECTORS["ii"])
    pose = random_pose(rng, options, centroids, inner[int(rng.integers(len(inner)))], geometry=geometry)
    motions = draw_level_motions(rng, motion_centers(labels, ct.ijk_to_lps, centroids.sorted()), options)
    return pose, motions


def make_geometry(ct, detector: Detector) -> CarmGeometry:
    return CarmGeometry(detector.intrinsics(), tuple(float(x) for x in ct.center_lps_mm()), detector.sod_mm)


def collimation(rng: np.random.Generator, detector: Detector) -> tuple[np.ndarray, dict]:
    """(field 0..1 with a ~1 mm soft edge, description): circle (ii) or off-centre rectangle (fp)."""
    cols, rows = detector.size_px
    d = detector.pixel_mm
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    x, y = (uu - (cols - 1) / 2.0) * d, (vv - (rows - 1) / 2.0) * d
    if detector.kind == "ii":
        radius = detector.field_diameter_mm / 2.0
        inside = radius - np.hypot(x, y)
        desc = {"shape": "circle", "radius_mm": radius, "center_mm": [0.0, 0.0]}
    else:
        half = rng.uniform(100, 145, 2)
        centre = rng.uniform(-15, 15, 2)
        inside = np.minimum(half[0] - np.abs(x - centre[0]), half[1] - np.abs(y - centre[1]))
        desc = {"shape": "rectangle", "half_size_mm": half.tolist(), "center_mm": centre.tolist()}
    return np.clip(inside / 1.0 + 0.5, 0.0, 1.0).astype(np.float32), desc


@dataclass(frozen=True)
class Pincushion:
    """Image-intensifier distortion in detector mm about ``center_px``: r -> r (1 + k r^2), then y *= 1 + a."""

    center_px: tuple[float, float]
    pixel_mm: float
    k_per_mm2: float
    stretch_y: float

    def distort(self, uv_px: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv_px, float)
        x, y = (uv[..., 0] - self.center_px[0]) * self.pixel_mm, (uv[..., 1] - self.center_px[1]) * self.pixel_mm
        s = 1.0 + self.k_per_mm2 * (x * x + y * y)
        return np.stack([x * s / self.pixel_mm + self.center_px[0],
                         y * s * (1.0 + self.stretch_y) / self.pixel_mm + self.center_px[1]], -1)

    def undistort(self, uv_px: np.ndarray) -> np.ndarray:
        """Exact inverse by fixed-point iteration (the map is a small perturbation of the identity)."""
        uv = np.asarray(uv_px, float)
        xd = (uv[..., 0] - self.center_px[0]) * self.pixel_mm
        yd = (uv[..., 1] - self.center_px[1]) * self.pixel_mm / (1.0 + self.stretch_y)
        x, y = xd.copy(), yd.copy()
        for _ in range(40):
            s = 1.0 + self.k_per_mm2 * (x * x + y * y)
            x, y = xd / s, yd / s
        return np.stack([x / self.pixel_mm + self.center_px[0], y / self.pixel_mm + self.center_px[1]], -1)


def draw_pincushion(rng: np.random.Generator, detector: Detector) -> Pincushion:
    """3-7 mm displacement at the field edge, centre up to 6 px off, +-1 % vertical stretch."""
    cols, rows = detector.size_px
    radius = detector.field_diameter_mm / 2.0
    centre = ((cols - 1) / 2.0 + rng.uniform(-6, 6), (rows - 1) / 2.0 + rng.uniform(-6, 6))
    return Pincushion(centre, detector.pixel_mm, float(rng.uniform(3, 7)) / radius**3, float(rng.uniform(-0.01, 0.01)))


def resample(image: np.ndarray, warp: Pincushion) -> np.ndarray:
    """out(q) = image(D^-1(q)) bilinear."""
    rows, cols = image.shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    ideal = warp.undistort(np.stack([uu, vv], -1))
    return ndimage.map_coordinates(image, [ideal[..., 1], ideal[..., 0]], order=1, mode="nearest").astype(np.float32)


def visible_levels(uv: dict, field_desc: dict, detector: Detector, margin_mm: float = 5.0) -> dict:
    cols, rows = detector.size_px
    out = {}
    for lb, p in uv.items():
        x = (p[0] - (cols - 1) / 2.0) * detector.pixel_mm - field_desc["center_mm"][0]
        y = (p[1] - (rows - 1) / 2.0) * detector.pixel_mm - field_desc["center_mm"][1]
        if field_desc["shape"] == "circle":
            out[lb] = bool(np.hypot(x, y) < field_desc["radius_mm"] - margin_mm)
        else:
            hx, hy = field_desc["half_size_mm"]
            out[lb] = bool(abs(x) < hx - margin_mm and abs(y) < hy - margin_mm)
    return out


@dataclass
class ScenePlan:
    """One case on one detector before its line integrals are rendered: everything drawn at random (K-wires,
    collimation, the intensifier's pincushion, the click noise) and the truth. ``render_scene`` renders it; the
    renders draw nothing at random, so a scene planned now and rendered later is the one ``make_scene`` makes."""

    ct_name: str
    detector: Detector
    geometry: CarmGeometry
    pose: CarmPose
    motions: dict
    wires: list
    field: np.ndarray                 # (rows, cols) float32 0..1, the exposed field
    warp: Pincushion | None           # the intensifier's distortion (None: a flat panel)
    uv_true_px: dict
    visible: dict
    clicked: list
    clicks_uv_px: np.ndarray
    distortion: dict


def plan_scene(ct_name: str, centroids: Landmarks3D, pose: CarmPose, motions: dict, detector: Detector, geometry,
               rng: np.random.Generator) -> ScenePlan:
    """The random draws and the truth of a scene, in ``make_scene``'s order (``geometry``: ``make_geometry``).
    Raises LookupError when fewer than 3 adjacent levels are visible (draw another pose)."""
    P = geometry.projection_matrix(pose)
    points = centroids.sorted().as_dict()
    uv_ideal = {lb: project(P, (motions[lb].apply(c) if lb in motions else c)[None])[0] for lb, c in points.items()}
    cols, rows = detector.size_px
    nearest = sorted(uv_ideal, key=lambda lb: np.linalg.norm(uv_ideal[lb] - ((cols - 1) / 2.0, (rows - 1) / 2.0)))
    wires = plan_kwires(rng, nearest, points, motions, dataclasses.replace(SimulationOptions(),
                                                                            n_kwires=int(rng.integers(0, 3))))
    field_img, desc = collimation(rng, detector)
    distortion: dict = {"model": "none"}
    uv_true, warp = dict(uv_ideal), None
    if detector.kind == "ii":
        warp = draw_pincushion(rng, detector)
        uv_true = {lb: warp.distort(uv) for lb, uv in uv_ideal.items()}
        distortion = {"model": "r (1 + k r^2), y *= 1 + a about center_px (detector mm)",
                      **dataclasses.asdict(warp)}
    visible = visible_levels(uv_true, desc, detector)
    try:
        centre_px = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
        clicked = choose_click_levels(list(uv_true), uv_true, visible, centre_px, 3)
    except Exception as exc:  # LandmarkError: too few adjacent visible levels
        raise LookupError(str(exc)) from None
    clicks = np.array([uv_true[lb] + rng.normal(0.0, 0.9 / detector.pixel_mm, 2) for lb in clicked])
    distortion["field"] = desc
    return ScenePlan(ct_name, detector, geometry, pose, motions, wires, field_img, warp, uv_true, visible,
                     list(clicked), clicks, distortion)


def render_scene(plan: ScenePlan, ct, labels, mu_parts) -> Scene:
    """Render both line-integral parts of the moved anatomy on the plan's detector, the K-wires added and the
    intensifier's pincushion applied (module docstring)."""
    water, bone, water_soft, bone_soft = mu_parts
    geometry, pose = plan.geometry, plan.pose
    l_water = render_moved_anatomy(water, labels, ct.ijk_to_lps, plan.motions, water_soft, geometry, pose, True)
    l_bone = render_moved_anatomy(bone, labels, ct.ijk_to_lps, plan.motions, bone_soft, geometry, pose, True)
    for wire in plan.wires:
        add_kwire(l_water, wire, geometry, pose, 0.9)
    if plan.warp is not None:
        l_water, l_bone = resample(l_water, plan.warp), resample(l_bone, plan.warp)
    return Scene(plan.ct_name, plan.detector, geometry, pose, l_water, l_bone, plan.field, plan.uv_true_px,
                 plan.visible, list(plan.clicked), plan.clicks_uv_px, plan.distortion)


def make_scene(ct_name: str, ct, labels, centroids: Landmarks3D, mu_parts, pose: CarmPose, motions: dict,
               detector: Detector, rng: np.random.Generator) -> Scene:
    """Render both line-integral parts of the moved anatomy on ``detector`` and the truth (module docstring):
    ``plan_scene`` then ``render_scene``. Raises LookupError when fewer than 3 adjacent levels are visible (draw
    another pose)."""
    plan = plan_scene(ct_name, centroids, pose, motions, detector, make_geometry(ct, detector), rng)
    return render_scene(plan, ct, labels, mu_parts)


def truth_dict(scene: Scene, mirrored: bool, display_turn: str = "none") -> dict:
    """Ground truth in the form ``carmreg.logic.simulation.evaluation.evaluate`` reads (projection_matrix,
    intrinsics.pixel_spacing_mm and size_px, levels[uv_true_px, visible]) on the display: every acquired pixel
    position taken through ``display_map`` (the 'true' P then maps to where each level shows on the display)."""
    F, size_px = display_map(scene.detector.size_px, mirrored, display_turn)
    P = F @ scene.projection_matrix
    levels = {lb: {"uv_true_px": displayed_uv(uv, F).tolist(), "visible": scene.visible[lb]}
              for lb, uv in scene.uv_true_px.items()}
    return {"projection_matrix": P.tolist(), "pose": scene.pose.as_dict(), "mirrored": mirrored,
            "display_turn": display_turn,
            "intrinsics": {"sdd_mm": scene.detector.sdd_mm, "pixel_spacing_mm": [scene.detector.pixel_mm] * 2,
                           "size_px": list(size_px)},
            "sod_mm": scene.detector.sod_mm, "levels": levels, "clicked": scene.clicked,
            "clicks_uv_px": [displayed_uv(uv, F).tolist() for uv in scene.clicks_uv_px],
            "distortion": scene.distortion}


def display_map(size_px: tuple[int, int], mirrored: bool, display_turn: str = "none"
                ) -> tuple[np.ndarray, tuple[int, int]]:
    """(F, displayed (columns, rows)): the 3 x 3 map of an acquired pixel (u, v, 1) (0-based centres, (column,
    row)) to where the display shows it, the mirror (u -> cols - 1 - u) first, then ``display_turn``."""
    cols, rows = size_px
    mirror = np.array([[-1.0, 0.0, cols - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) if mirrored else np.eye(3)
    turns = {"none": (np.eye(3), (cols, rows)),
             "turned-180": (np.array([[-1.0, 0.0, cols - 1.0], [0.0, -1.0, rows - 1.0], [0.0, 0.0, 1.0]]),
                            (cols, rows)),
             "flipped-up-down": (np.array([[1.0, 0.0, 0.0], [0.0, -1.0, rows - 1.0], [0.0, 0.0, 1.0]]), (cols, rows)),
             # a quarter turn counter-clockwise: displayed column = acquired row, displayed row = cols - 1 - u
             "turned-90": (np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, cols - 1.0], [0.0, 0.0, 1.0]]), (rows, cols))}
    turn, shown = turns[display_turn]
    return turn @ mirror, shown


def displayed_uv(uv, F: np.ndarray) -> np.ndarray:
    """Acquired pixel positions (..., 2) where the display shows them (``display_map``'s F)."""
    uv = np.array(uv, float)
    h = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], axis=-1) @ F.T
    return h[..., :2]


def turn_display(pixels: np.ndarray, display_turn: str) -> np.ndarray:
    """The stored image (rows, columns) turned as ``display_turn`` says (``display_map``'s pixel map)."""
    turned = {"none": pixels, "turned-180": pixels[::-1, ::-1], "flipped-up-down": pixels[::-1],
              "turned-90": pixels.T[::-1]}[display_turn]  # turned-90: shown[cols - 1 - u, v] = acquired[v, u]
    return np.ascontiguousarray(turned)


# ----------------------------------------------------------------------------------------------- appearance

def exp_kernel(length_px: float, step: int) -> np.ndarray:
    """Normalised exp(-r / length) on a grid of ``step`` px, reaching 4 lengths."""
    n = int(np.ceil(4 * length_px / step))
    yy, xx = np.mgrid[-n:n + 1, -n:n + 1] * float(step)
    k = np.exp(-np.hypot(xx, yy) / max(length_px, 1e-6))
    return k / k.sum()


def smooth_wide(image: np.ndarray, length_px: float, step: int = 8) -> np.ndarray:
    """exp-kernel convolution on ``step`` x ``step`` block means (zero outside), upsampled bilinearly."""
    rows, cols = image.shape
    pad = ((0, -rows % step), (0, -cols % step))
    blocks = np.pad(image, pad).reshape((rows + pad[0][1]) // step, step, (cols + pad[1][1]) // step, step)
    small = signal.fftconvolve(blocks.mean(axis=(1, 3)), exp_kernel(length_px, step), mode="same")
    grid = np.meshgrid(*[(np.arange(n) - (step - 1) / 2.0) / step for n in (rows, cols)], indexing="ij")
    return ndimage.map_coordinates(small, grid, order=1, mode="nearest")


def central_region(shape: tuple[int, int], fraction: float = 0.25) -> np.ndarray:
    rows, cols = shape
    vv, uu = np.mgrid[0:rows, 0:cols]
    return (np.abs(uu - (cols - 1) / 2.0) < fraction * cols) & (np.abs(vv - (rows - 1) / 2.0) < fraction * rows)


def detect(l_water: np.ndarray, l_bone: np.ndarray, field_img: np.ndarray, detector: Detector, look: Look,
           rng: np.random.Generator) -> np.ndarray:
    """Detected quanta per pixel (float64, (rows, cols)): module docstring steps 1 and 3."""
    d = detector.pixel_mm
    L = l_water.astype(np.float64) + (look.bone_factor - 1.0) * l_bone + look.table_line_integral \
        + MU_WATER_PER_MM * look.extra_water_mm
    L_eff = np.log1p(look.hardening * np.maximum(L, 0.0)) / look.hardening
    primary = np.exp(-L_eff) * field_img
    centre = central_region(primary.shape) & (field_img > 0.5)
    spread = smooth_wide(primary, look.scatter_length_mm / d)
    signal_ = primary + look.spr * spread * primary[centre].mean() / max(spread[centre].mean(), 1e-300)
    rows, cols = primary.shape
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    gain = 1.0 + look.heel * (vv - (rows - 1) / 2.0) / rows
    if detector.kind == "ii":
        radius_px = detector.field_diameter_mm / 2.0 / d
        r = np.hypot(uu - (cols - 1) / 2.0, vv - (rows - 1) / 2.0) / radius_px
        gain = gain / (1.0 + (look.falloff * r) ** 2) ** 2
    signal_ = signal_ * gain
    scale = look.photons / max(signal_[centre].mean(), 1e-300)
    quanta = rng.poisson(np.maximum(signal_ * scale, 0.0)).astype(np.float64)
    quanta += rng.normal(0.0, look.read_noise, quanta.shape)
    if detector.kind == "fp":
        quanta *= 1.0 + rng.normal(0.0, 0.01, quanta.shape)
    quanta = ndimage.gaussian_filter(quanta, detector.blur_mm / d)
    if look.glare > 0:
        quanta = (1.0 - look.glare) * quanta + look.glare * smooth_wide(quanta, 80.0 / d)
    return np.maximum(quanta, 0.0)


def store(quanta: np.ndarray, field_img: np.ndarray, detector: Detector, look: Look) -> np.ndarray:
    """Stored pixel values (uint16, or uint8 for 'display'): module docstring step 4. For 'linear' + bone
    bright the values are inverted unless the file is MONOCHROME1 (which the reader inverts)."""
    inside = field_img > 0.5
    d = detector.pixel_mm
    if look.storage == "linear":
        top = float(np.percentile(quanta[inside], 99.5))
        v = 120.0 + quanta * (0.7 * 65535.0 / max(top, 1e-9))
        if look.bone_bright and look.file != "dcm-mono1":
            v = 65535.0 - v
        out = v
    else:
        ref = float(np.median(quanta[central_region(quanta.shape) & inside]))
        att = -np.log(np.maximum(quanta, 0.5) / max(ref, 1e-9))  # bone bright
        y = att if look.bone_bright else -att
        if look.storage == "display":
            y = np.where(inside, y, float(np.median(y[inside])))
            y = y - look.compression * ndimage.gaussian_filter(y, 20.0 / d)
            y = y + look.usm_amount * (y - ndimage.gaussian_filter(y, look.usm_sigma_mm / d))
        lo, hi = np.percentile(y[inside], [0.5, 99.5]) if look.storage == "log" else np.percentile(y[inside], [1, 99])
        t = np.clip((y - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
        if look.storage == "display":
            t = t ** look.gamma
            out = 255.0 * t
        else:
            out = 65535.0 * (0.05 + 0.9 * t)
    if detector.kind == "ii":
        out = out * field_img
    elif look.storage == "display" or look.storage == "log":
        outside = (1.0 if look.bone_bright else 0.0) * (255.0 if look.storage == "display" else 65535.0)
        out = np.where(field_img > 0.5, out, outside)
    top = 255.0 if look.storage == "display" else 65535.0
    return np.round(np.clip(out, 0.0, top)).astype(np.uint8 if look.storage == "display" else np.uint16)


def burn_text(pixels: np.ndarray, lines: list[str]) -> np.ndarray:
    """Text at the top-left and bottom-right corners at the maximum value (in place)."""
    from PIL import Image, ImageDraw, ImageFont

    rows, cols = pixels.shape
    canvas = Image.new("L", (cols, rows), 0)
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default(size=max(9, rows // 48))
    draw.text((rows // 80, rows // 80), "\n".join(lines[:2]), fill=255, font=font)
    tail = "\n".join(lines[2:])
    box = draw.multiline_textbbox((0, 0), tail, font=font)
    draw.text((cols - box[2] - rows // 80, rows - box[3] - rows // 80), tail, fill=255, font=font)
    pixels[np.asarray(canvas) > 127] = np.iinfo(pixels.dtype).max
    return pixels


def render(scene: Scene, look: Look, rng: np.random.Generator) -> np.ndarray:
    """The stored image of ``scene`` with ``look`` (uint16 or uint8, mirrored and turned if asked, text burnt in)."""
    quanta = detect(scene.l_water, scene.l_bone, scene.field, scene.detector, look, rng)
    pixels = store(quanta, scene.field, scene.detector, look)
    if look.mirrored:
        pixels = np.ascontiguousarray(pixels[:, ::-1])
    pixels = turn_display(pixels, look.display_turn)
    return burn_text(pixels, ["ACME MOBILE C" if scene.detector.kind == "ii" else "FP-30 DIGITAL",
                              f"{look.kv:.0f} kV", "IMG 0001", "SPINE AP"])


# ----------------------------------------------------------------------------------------------- files

SUFFIX = {"png16": ".png", "tiff16": ".tif", "jpeg8": ".jpg", "dcm-sign": ".dcm", "dcm-nosign": ".dcm",
          "dcm-mono1": ".dcm"}


def write_xray(path_stem: Path, pixels: np.ndarray, detector: Detector, look: Look) -> Path:
    """Write the image as ``look.file`` says; returns the path (suffix added). PNG/TIFF/JPEG carry no geometry."""
    from PIL import Image

    path = Path(str(path_stem) + SUFFIX[look.file])
    path.parent.mkdir(parents=True, exist_ok=True)
    if look.file.startswith("dcm"):
        write_dicom(path, pixels, detector, look)
    elif look.file == "jpeg8":
        Image.fromarray(pixels.astype(np.uint8), "L").save(path, format="JPEG", quality=look.jpeg_quality)
    else:
        Image.fromarray(pixels.astype(np.uint16)).save(path, format="PNG" if look.file == "png16" else "TIFF")
    return path


def write_dicom(path: Path, pixels: np.ndarray, detector: Detector, look: Look) -> None:
    """A plain 16-bit DICOM of ``look.modality``: MONOCHROME1 for 'dcm-mono1'; PixelIntensityRelationship
    (LIN/LOG) and, except for 'dcm-nosign', its Sign (+1: lower stored values where less X-ray arrives)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    classes = {"XA": "1.2.840.10008.5.1.4.1.1.12.1", "RF": "1.2.840.10008.5.1.4.1.1.12.2",
               "DX": "1.2.840.10008.5.1.4.1.1.1.1"}
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = classes[look.modality]
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID, ds.SeriesInstanceUID = generate_uid(), generate_uid()
    ds.Modality, ds.PatientName, ds.PatientID = look.modality, "Bench^Appearance", "BENCH"
    ds.Rows, ds.Columns = int(pixels.shape[0]), int(pixels.shape[1])
    ds.SamplesPerPixel, ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 1, 16, 16, 15, 0
    ds.PhotometricInterpretation = "MONOCHROME1" if look.file == "dcm-mono1" else "MONOCHROME2"
    ds.PixelIntensityRelationship = "LIN" if look.storage == "linear" else "LOG"
    if look.file != "dcm-nosign":
        # +1: stored value rises with the X-ray reaching the detector (linear storage, or log shown bone dark)
        rises = look.storage == "linear" or not look.bone_bright
        ds.PixelIntensityRelationshipSign = 1 if rises else -1
    ds.DistanceSourceToDetector = f"{detector.sdd_mm:.1f}"
    ds.DistanceSourceToPatient = f"{detector.sod_mm:.1f}"
    ds.ImagerPixelSpacing = [f"{detector.pixel_mm:.4f}", f"{detector.pixel_mm:.4f}"]
    ds.KVP = f"{look.kv:.0f}"
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<u2").tobytes()
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    path.write_bytes(buffer.getvalue())
