"""What the simulated C-arm looks at (``simulator`` steps 2-3): a random pose about a level of the spine, each
vertebra's rigid motion about its centroid (``M_k: x -> R_k (x - c_k) + c_k + t_k``, LPS mm), and K-wires
(steel cylinders; exact chord length of each pixel ray through them, mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry, CarmPose, rotation_matrix
from carmreg.logic.geometry.vertebrae import level_ordinals
from carmreg.logic.io.landmarks import (
    Landmarks3D,
    level_index,
    normalize_level_name,
)
from carmreg.logic.simulation.options import SimulationOptions

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
