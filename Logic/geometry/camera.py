"""The C-arm as a pinhole camera (method paper Eq. 1).

Frames
------
- LPS: the CT patient frame, mm (x -> patient Left, y -> Posterior, z -> Superior).
- camera: origin at the X-ray source; +z from the source toward the detector (principal axis);
  +x along detector columns (u), +y along detector rows (v). mm.
- detector pixels: (u, v) = (column, row), 0-based, pixel centres at integer coordinates, row 0 at the top.

Intrinsics ``K = [[sdd/du, 0, u0], [0, sdd/dv, v0], [0, 0, 1]]`` with ``sdd_mm`` the source-to-detector
distance, ``pixel_spacing_mm = (du, dv)`` (column, row) and the principal point ``(u0, v0)`` in px (the foot
of the perpendicular from the source on the detector). ``P = K [R | t]`` maps homogeneous LPS mm to
homogeneous (u, v) px.

Nominal AP pose (patient prone, method paper 3.1.3)
---------------------------------------------------
The source is anterior of the patient (under the table), the detector posterior; the principal ray passes
through the isocentre ``isocenter_lps_mm`` at ``sod_mm`` from the source. In the image, columns run toward the
patient's Left and rows toward Inferior (head at the top, patient's right on the viewer's left, the usual
radiological display). Hence camera x = +L, camera y = -S, camera z = +P.

The 6 pose parameters (paper: Tx, Ty, Tz, theta_x, theta_y, theta_z)
--------------------------------------------------------------------
A rigid motion of the whole C-arm (source and detector together) about the isocentre, in the nominal
C-arm axes, all expressed in LPS:

- ``tx_mm``: along the nominal source->detector axis (+P). Positive moves the source toward the patient,
  i.e. reduces the source-to-isocentre distance and increases magnification.
- ``ty_mm``: medio-lateral (+L).   ``tz_mm``: superior-inferior (+S).
- ``rx_deg``: about the source->detector axis (LPS y; in-plane rotation of the image).
- ``ry_deg``: about the medio-lateral axis (LPS x; cranio-caudal tilt).
- ``rz_deg``: about the superior-inferior axis (LPS z; LAO/RAO orbit).

``R_motion = R_y(rx) @ R_x(ry) @ R_z(rz)`` (right-handed rotations about the positive LPS axes) and a point
of the C-arm moves as ``q -> c + t + R_motion (q - c)`` with c the isocentre.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from carmreg.logic.errors import GeometryError
from carmreg.logic.geometry.distortion import REFERENCE_RADIUS_MM, RadialDistortion

# Rotation of the nominal AP camera: rows are camera x, y, z axes expressed in LPS.
NOMINAL_LPS_TO_CAMERA_ROTATION = np.array([[1.0, 0.0, 0.0],   # camera x = patient Left
                                           [0.0, 0.0, -1.0],  # camera y = Inferior
                                           [0.0, 1.0, 0.0]])  # camera z = Posterior (source -> detector)
POSE_NAMES = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg")


MAX_PIXEL_ASPECT = 3.0
"""Largest ratio of column to row spacing accepted (detector pixels are square or nearly)."""
MAX_DISTORTION_MM = 10.0
"""Largest ``distortion_mm`` accepted (shift at 100 mm from the centre; intensifiers: a few mm)."""
MAX_DISTORTION_FRACTION = 0.2
"""... and k r^2 at the detector's farthest corner at most this (the model's small-distortion range)."""
MAX_DETECTOR_MM = 600.0
"""Largest detector side accepted: flat panels reach 43 cm, image intensifiers 40 cm (Ø), so 60 cm leaves
margin while refusing a pixel-spacing typo (2.5 mm for 0.25) before it sizes a 2.5 m detector and its DRRs."""


@dataclass(frozen=True)
class CarmIntrinsics:
    """Detector and source-to-detector distance.

    sdd_mm: source-to-detector distance.
    pixel_spacing_mm: (du, dv) = (column spacing, row spacing) at the detector.
    size_px: (columns, rows).
    principal_point_px: (u0, v0); defaults to the detector centre ((columns-1)/2, (rows-1)/2).
    sources: where each value came from (e.g. {"sdd_mm": "DICOM (0018,1110)"}).
    distortion_mm: an image intensifier's radial (pincushion) distortion about the principal point, from the
        C-arm's calibration: how far (mm) an image point 100 mm from the centre lies outward of the pinhole's
        (``geometry.distortion``); 0 = none (a flat panel). DRRs are rendered through it (``drr.cpu``).
    """

    sdd_mm: float
    pixel_spacing_mm: tuple[float, float]
    size_px: tuple[int, int]
    principal_point_px: tuple[float, float] | None = None
    sources: dict = field(default_factory=dict, compare=False)
    distortion_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.principal_point_px is None:
            cols, rows = self.size_px
            object.__setattr__(self, "principal_point_px", ((cols - 1) / 2.0, (rows - 1) / 2.0))
        self.validate()

    def validate(self) -> None:
        """Raise GeometryError on physically impossible values."""
        sdd, (du, dv), (cols, rows) = self.sdd_mm, self.pixel_spacing_mm, self.size_px
        u0, v0 = self.principal_point_px
        if not (np.isfinite(sdd) and 100.0 <= sdd <= 3000.0):
            raise GeometryError(f"source-to-detector distance {sdd} mm is not plausible: give --sdd-mm "
                                "between 100 and 3000 (a C-arm is about 1000)")
        if not (np.isfinite(du) and np.isfinite(dv) and 0.01 <= du <= 10.0 and 0.01 <= dv <= 10.0):
            raise GeometryError(f"pixel spacing ({du}, {dv}) mm is not plausible: give --pixel-spacing-mm "
                                "between 0.01 and 10 (detector pixel size, not calibrated to the patient)")
        if max(du, dv) > MAX_PIXEL_ASPECT * min(du, dv):
            raise GeometryError(f"pixel spacing ({du:g}, {dv:g}) mm: columns and rows differ by "
                                f"{max(du, dv) / min(du, dv):.1f}x, but detector pixels are square or nearly: check "
                                "--pixel-spacing-mm (column, row) or the file's ImagerPixelSpacing (row\\column)")
        if cols < 2 or rows < 2:
            raise GeometryError(f"detector size {cols}x{rows} px: an X-ray needs at least 2 x 2 pixels; give the "
                                "image's own size (columns, rows)")
        width_mm, height_mm = cols * du, rows * dv
        if max(width_mm, height_mm) > MAX_DETECTOR_MM:
            raise GeometryError(f"pixel spacing ({du:g}, {dv:g}) mm makes the {cols}x{rows} px detector "
                                f"{width_mm:.0f} x {height_mm:.0f} mm, larger than any C-arm detector (at most "
                                f"{MAX_DETECTOR_MM:.0f} mm across): check --pixel-spacing-mm (detector pixels are "
                                "about 0.1-1 mm)")
        if not (np.isfinite(u0) and np.isfinite(v0) and -0.5 <= u0 <= cols - 0.5 and -0.5 <= v0 <= rows - 0.5):
            raise GeometryError(f"principal point ({u0}, {v0}) px lies off the {cols}x{rows} detector: "
                                "give --principal-point-px inside the image or omit it for the centre")
        self._validate_distortion()

    def _validate_distortion(self) -> None:
        """An intensifier's pincushion moves its rim by a few per cent; the model (``geometry.distortion``) holds
        while k r^2 stays small over the detector (r to its farthest corner)."""
        shift = self.distortion_mm
        if not (np.isfinite(shift) and abs(shift) <= self.max_distortion_mm):
            raise GeometryError(f"distortion {shift:g} mm at 100 mm from the centre is not plausible: give "
                                "--distortion-mm from the C-arm's calibration (an image intensifier's is a few mm; "
                                f"at most {MAX_DISTORTION_MM:g}, less on a detector this large), or 0")

    @property
    def max_distortion_mm(self) -> float:
        """The largest ``distortion_mm`` this detector accepts: ``MAX_DISTORTION_MM``, and k r^2 at most
        ``MAX_DISTORTION_FRACTION`` with r (mm) to its farthest corner (k = shift / 100^3)."""
        reach_mm = float(np.hypot(*(np.asarray(self.size_px) * np.asarray(self.pixel_spacing_mm)))) / 2.0
        return min(MAX_DISTORTION_MM, MAX_DISTORTION_FRACTION * REFERENCE_RADIUS_MM**3 / reach_mm**2)

    @property
    def distortion(self) -> RadialDistortion:
        """The radial distortion about the principal point (``distortion_mm``; k = 0 when there is none)."""
        return RadialDistortion.from_shift(self.distortion_mm, self.principal_point_px, self.pixel_spacing_mm)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix, camera mm -> homogeneous (u, v) px."""
        (du, dv), (u0, v0) = self.pixel_spacing_mm, self.principal_point_px
        return np.array([[self.sdd_mm / du, 0.0, u0], [0.0, self.sdd_mm / dv, v0], [0.0, 0.0, 1.0]])

    def binned(self, factor: int) -> CarmIntrinsics:
        """Intrinsics of the detector binned by ``factor`` x ``factor`` pixels (the image downsampled).

        New pixel centre u' covers old pixels [f u', f u' + f - 1], so u_old = f u' + (f - 1) / 2.
        """
        f = int(factor)
        cols, rows = self.size_px
        u0, v0 = self.principal_point_px
        du, dv = self.pixel_spacing_mm
        return replace(self, pixel_spacing_mm=(du * f, dv * f), size_px=(cols // f, rows // f),
                       principal_point_px=((u0 - (f - 1) / 2.0) / f, (v0 - (f - 1) / 2.0) / f))

    def scaled_to(self, size_px: tuple[int, int]) -> CarmIntrinsics:
        """Same detector area rendered at another pixel count (any factor, pixel edges aligned)."""
        cols, rows = self.size_px
        fu, fv = cols / size_px[0], rows / size_px[1]
        u0, v0 = self.principal_point_px
        du, dv = self.pixel_spacing_mm
        return replace(self, pixel_spacing_mm=(du * fu, dv * fv), size_px=tuple(int(s) for s in size_px),
                       principal_point_px=((u0 + 0.5) / fu - 0.5, (v0 + 0.5) / fv - 0.5))


@dataclass(frozen=True)
class CarmPose:
    """The paper's 6-DOF C-arm parameters about a nominal AP pose (see module docstring)."""

    tx_mm: float = 0.0
    ty_mm: float = 0.0
    tz_mm: float = 0.0
    rx_deg: float = 0.0
    ry_deg: float = 0.0
    rz_deg: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([getattr(self, n) for n in POSE_NAMES], dtype=np.float64)

    @classmethod
    def from_array(cls, values) -> CarmPose:
        return cls(*[float(v) for v in np.asarray(values, dtype=float).ravel()[:6]])

    def as_dict(self) -> dict:
        return {n: float(getattr(self, n)) for n in POSE_NAMES}


def rotation_matrix(axis: np.ndarray, angle_deg) -> np.ndarray:
    """Right-handed rotation(s) about a unit ``axis`` by ``angle_deg`` (scalar or (n,)). Returns (..., 3, 3).

    Rodrigues: R = cos(a) I + (1 - cos(a)) n n^T + sin(a) [n]_x, with [n]_x the cross-product matrix of n."""
    a = np.deg2rad(np.asarray(angle_deg, dtype=np.float64))
    x, y, z = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    c, s = np.cos(a)[..., None, None], np.sin(a)[..., None, None]
    outer = np.array([[x * x, x * y, x * z], [y * x, y * y, y * z], [z * x, z * y, z * z]])
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return c * np.eye(3) + (1.0 - c) * outer + s * cross


def motion_rotation(rx_deg, ry_deg, rz_deg) -> np.ndarray:
    """R_motion = R_y(rx) @ R_x(ry) @ R_z(rz) about the LPS axes; vectorised over leading dims."""
    return (rotation_matrix([0, 1, 0], rx_deg) @ rotation_matrix([1, 0, 0], ry_deg)
            @ rotation_matrix([0, 0, 1], rz_deg))


@dataclass(frozen=True)
class CarmGeometry:
    """Intrinsics plus the nominal AP placement: everything needed to turn a CarmPose into P.

    isocenter_lps_mm: the point the nominal principal ray passes through (paper: CT volume centre).
    sod_mm: nominal source-to-isocentre distance (paper: SDD / 2).
    """

    intrinsics: CarmIntrinsics
    isocenter_lps_mm: tuple[float, float, float]
    sod_mm: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sod_mm) and 0.0 < self.sod_mm < self.intrinsics.sdd_mm):
            raise GeometryError(f"source-to-isocentre distance {self.sod_mm} mm must lie between 0 and the "
                                f"source-to-detector distance {self.intrinsics.sdd_mm} mm")

    def with_intrinsics(self, intrinsics: CarmIntrinsics) -> CarmGeometry:
        return replace(self, intrinsics=intrinsics)

    def extrinsics(self, pose: CarmPose | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """lps_to_camera as (R (..., 3, 3), t (..., 3)): x_cam = R x_lps + t. Vectorised over poses (n, 6)."""
        p = pose.as_array() if isinstance(pose, CarmPose) else np.asarray(pose, dtype=np.float64)
        c = np.asarray(self.isocenter_lps_mm, dtype=np.float64)
        motion = motion_rotation(p[..., 3], p[..., 4], p[..., 5])
        translation = np.stack([p[..., 1], p[..., 0], p[..., 2]], -1)  # (ty->L, tx->P, tz->S)
        source0 = c - self.sod_mm * NOMINAL_LPS_TO_CAMERA_ROTATION[2]
        source = c + translation + np.einsum("...ij,j->...i", motion, source0 - c)
        rotation = NOMINAL_LPS_TO_CAMERA_ROTATION @ np.swapaxes(motion, -1, -2)
        t = -np.einsum("...ij,...j->...i", rotation, source)
        return rotation, t

    def projection_matrix(self, pose: CarmPose | np.ndarray) -> np.ndarray:
        """P = K [R | t], (..., 3, 4): homogeneous LPS mm -> homogeneous (u, v) px."""
        rotation, t = self.extrinsics(pose)
        rt = np.concatenate([rotation, t[..., None]], axis=-1)
        return self.intrinsics.K @ rt

    def source_lps_mm(self, pose: CarmPose | np.ndarray) -> np.ndarray:
        rotation, t = self.extrinsics(pose)
        return -np.einsum("...ji,...j->...i", rotation, t)

    def magnification(self, pose: CarmPose | np.ndarray, point_lps_mm=None) -> float:
        """SDD / (depth of ``point_lps_mm`` (default: isocentre) along the principal axis)."""
        rotation, t = self.extrinsics(pose)
        point = np.asarray(self.isocenter_lps_mm if point_lps_mm is None else point_lps_mm, dtype=float)
        depth = (rotation @ point + t)[..., 2]
        return self.intrinsics.sdd_mm / depth

    def detector_corners_lps_mm(self, pose: CarmPose) -> np.ndarray:
        """(4, 3) LPS positions of the detector's outer corners (for drawing the frustum)."""
        cols, rows = self.intrinsics.size_px
        uv = np.array([[-0.5, -0.5], [cols - 0.5, -0.5], [cols - 0.5, rows - 0.5], [-0.5, rows - 0.5]])
        return pixel_to_detector_lps(self, pose, uv)


DEFAULT_SOD_FRACTION = 0.6  # nominal source-to-isocentre distance / SDD when nothing says (a mobile C-arm)


def nominal_sod_mm(sdd_mm: float, sod_mm: float | None = None) -> float:
    """The source-to-isocentre distance to use: the known one, else ``DEFAULT_SOD_FRACTION`` x SDD."""
    return float(sod_mm) if sod_mm is not None else DEFAULT_SOD_FRACTION * float(sdd_mm)  # 0 is refused, not replaced


def nominal_geometry(intrinsics: CarmIntrinsics, volume, sod_mm: float | None = None) -> CarmGeometry:
    """The nominal AP C-arm for a CT ``volume``: isocentre at the volume centre (paper 3.1.3), SOD as known or
    ``nominal_sod_mm``."""
    return CarmGeometry(intrinsics, tuple(float(x) for x in volume.center_lps_mm()),
                        nominal_sod_mm(intrinsics.sdd_mm, sod_mm))


def in_detector(uv_px: np.ndarray, size_px: tuple[int, int]) -> bool:
    """Whether the pixel (column, row) lies on a detector of ``size_px`` (columns, rows): pixel centres at
    integers, so the detector spans -0.5 .. size - 0.5 along each axis."""
    return bool(-0.5 <= uv_px[0] <= size_px[0] - 0.5 and -0.5 <= uv_px[1] <= size_px[1] - 0.5)


def project(P: np.ndarray, points_lps_mm: np.ndarray) -> np.ndarray:
    """(u, v) px of (n, 3) LPS points under P (3, 4) or a batch (m, 3, 4) -> (n, 2) or (m, n, 2)."""
    pts = np.asarray(points_lps_mm, dtype=np.float64)
    h = np.einsum("...ij,nj->...ni", P[..., :, :3], pts) + P[..., None, :, 3]
    return h[..., :2] / h[..., 2:3]


def pixel_to_detector_lps(geometry: CarmGeometry, pose: CarmPose, uv_px: np.ndarray) -> np.ndarray:
    """LPS mm of detector pixel positions (n, 2) (u, v) on the detector plane."""
    rotation, t = geometry.extrinsics(pose)
    intr = geometry.intrinsics
    uv = np.atleast_2d(np.asarray(uv_px, dtype=np.float64))
    (du, dv), (u0, v0) = intr.pixel_spacing_mm, intr.principal_point_px
    cam = np.stack([(uv[:, 0] - u0) * du, (uv[:, 1] - v0) * dv, np.full(len(uv), intr.sdd_mm)], -1)
    return (cam - t) @ rotation  # R^T (cam - t)


def backproject(geometry: CarmGeometry, pose: CarmPose, uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through pixels: (source_lps_mm (3,), unit directions (n, 3) in LPS toward the detector)."""
    source = geometry.source_lps_mm(pose)
    points = pixel_to_detector_lps(geometry, pose, uv_px)
    d = points - source
    return source, d / np.linalg.norm(d, axis=1, keepdims=True)


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split a 3x4 P into K (upper triangular, positive diagonal), R (rotation) and t, P ~ K [R | t]."""
    from scipy.linalg import rq

    M = P[:, :3]
    k, r = rq(M)
    signs = np.diag(np.sign(np.diag(k)))
    k, r = k @ signs, signs @ r
    scale = k[2, 2]
    t = np.linalg.solve(k, P[:, 3])
    if np.linalg.det(r) < 0:
        r, t = -r, -t
    return k / scale, r, t
