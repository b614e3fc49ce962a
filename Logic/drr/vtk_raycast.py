"""VTK ray-cast DRR engine: vtkOpenGLGPUVolumeRayCastMapper in additive blend mode, offscreen.

The same physics and geometry as ``drr_cpu`` (line integrals ``L = integral of mu dl`` along the ray from the
X-ray source to each detector pixel centre, image[row, column], float32), computed by VTK's GPU ray caster so
that a workstation GPU (or Mesa's llvmpipe without one) does the work.

How the VTK pipeline is made to return physical line integrals
---------------------------------------------------------------
- Volume: mu (1/mm) as float32 point scalars of a vtkImageData whose points are the voxel centres, padded
  with one voxel of zeros on every side (VTK's volume box ends at the outer voxel *centres*; the padding puts
  the whole of every voxel inside it and makes the scalar range start at 0). The index axes are permuted and
  flipped (exactly, no resampling) so that the direction matrix is a proper rotation; an oblique grid keeps
  its rotation as the image's direction matrix. Nearest-neighbour sampling (default) is the voxel model of
  the CPU engine; ``interpolation="linear"`` samples trilinearly.
- Additive blending: VTK sums ``opacity(s) * s_norm`` over samples spaced ``sample_distance_mm`` along each
  ray, with ``s_norm = mu / mu_max`` (scalar range [0, mu_max]). The opacity is a constant ``c`` with its
  unit distance equal to the sample distance (no opacity correction), so ``L ~= sum * mu_max * ds / c``.
- Precision: VTK clamps the sum to [0, 1] and writes it to an 8- or 10-bit colour buffer. A fragment-shader
  replacement of ``//VTK::Shading::Exit`` scales the sum to [0, 1) and packs it into 24 bits (R, G, B as
  base-255 digits); the bytes are read back and decoded in float64. The scale is set from the longest
  possible path (the volume diagonal at mu_max), so the sum cannot saturate; resolution is about
  mu_max * diagonal / 2^24.
- Camera: position = X-ray source, focal point on the principal axis, view-up = -(camera y), and an explicit
  OpenGL projection matrix built from K (so non-square pixels and any principal point are exact). VTK's
  image origin is bottom-left: rows are flipped so row 0 is at the top.

Limits (measured numbers in Testing/Benchmarks/results_drr.md): the result is a sampled (not exact) path
integral, so values differ from the CPU engine by the sampling error of the voxel edges (falls with the sample
distance); the first render compiles shaders and uploads the volume (a fraction of a second to seconds);
with no GPU, Mesa's llvmpipe renders on the CPU, much slower than ``drr_cpu``. Needs an OpenGL context: a
display (X or Xvfb), or EGL / OSMesa offscreen (VTK's pip wheels pick EGL when $DISPLAY is unset). Use from
one thread.
"""

from __future__ import annotations

import ctypes.util
import os
import re
import subprocess
import sys
import threading
import weakref

import numpy as np

from carmreg.logic.errors import GeometryError, RegistrationError
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose
from carmreg.logic.geometry.volume import MuLevel

_OPACITY = 0.5
_EXIT_SHADER = """
  float carm_x = clamp(l_sumValue.x * carm_scale, 0.0, 0.99999994);
  vec3 carm_digits = fract(carm_x * vec3(1.0, 255.0, 65025.0));
  carm_digits.xy -= carm_digits.yz / 255.0;
  g_fragColor = vec4(carm_digits, 1.0);
"""


def _canonical_grid(mu: np.ndarray, ijk_to_lps: np.ndarray):
    """Permute/flip index axes so the direction matrix is a proper rotation near identity.

    Returns (mu view, spacing (3,), direction (3, 3) with unit columns, origin_lps_mm of the new voxel 0).
    Raises RegistrationError when the grid is not orthonormal (sheared), which VTK image data cannot hold.
    """
    m = np.asarray(ijk_to_lps, dtype=np.float64)
    spacing = np.linalg.norm(m[:3, :3], axis=0)
    direction = m[:3, :3] / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-5):
        raise RegistrationError("the CT voxel grid is sheared (non-orthogonal axes): the VTK DRR engine "
                                "cannot represent it; use the CPU DRR engine")
    perm = [int(np.argmax(np.abs(direction[row]))) for row in range(3)]
    if sorted(perm) != [0, 1, 2]:
        perm = [0, 1, 2]
    flips = [direction[row, perm[row]] < 0 for row in range(3)]
    new_dir = direction[:, perm] * np.where(flips, -1.0, 1.0)
    if np.linalg.det(new_dir) < 0:  # an oblique left-handed grid: flip the least aligned axis
        worst = int(np.argmin(np.abs(np.diag(new_dir))))
        flips[worst] = not flips[worst]
        new_dir[:, worst] *= -1.0
    view = np.transpose(mu, perm)
    shape = np.array(view.shape)
    start_index = np.zeros(3)
    for axis, flip in enumerate(flips):
        if flip:
            view = np.flip(view, axis=axis)
            start_index[axis] = shape[axis] - 1
    old_start = np.zeros(3)
    old_start[perm] = start_index
    origin = m[:3, :3] @ old_start + m[:3, 3]
    return view, spacing[perm], new_dir, origin


def _opengl_projection(intr: CarmIntrinsics, near_mm: float, far_mm: float) -> np.ndarray:
    """4x4 OpenGL projection (VTK eye coordinates -> clip) equivalent to K on a cols x rows viewport.

    Eye coordinates: x = camera x, y = -camera y, z = -camera z. Pixel u (centre at integer u, edges at
    u +- 0.5) maps to NDC x = 2 (u + 0.5) / cols - 1; row v maps to NDC y = 1 - 2 (v + 0.5) / rows.
    """
    (cols, rows), K = intr.size_px, intr.K
    fx, fy, u0, v0 = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n, f = near_mm, far_mm
    return np.array([
        [2.0 * fx / cols, 0.0, 1.0 - 2.0 * (u0 + 0.5) / cols, 0.0],
        [0.0, 2.0 * fy / rows, 2.0 * (v0 + 0.5) / rows - 1.0, 0.0],
        [0.0, 0.0, -(f + n) / (f - n), -2.0 * f * n / (f - n)],
        [0.0, 0.0, -1.0, 0.0],
    ])


def _new_render_window():
    """An offscreen render window: X/GLX when $DISPLAY is set, otherwise EGL (then OSMesa) if available."""
    from vtkmodules import vtkRenderingOpenGL2  # registers the OpenGL implementation of vtkRenderWindow
    from vtkmodules.vtkRenderingCore import vtkRenderWindow

    has_osmesa = ctypes.util.find_library("OSMesa") is not None  # VTK's OSMesa window claims support without it
    candidates = []
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        names = ["vtkEGLRenderWindow"] + (["vtkOSOpenGLRenderWindow"] if has_osmesa else [])
        candidates = [getattr(vtkRenderingOpenGL2, n) for n in names if hasattr(vtkRenderingOpenGL2, n)]
    for cls in candidates + [vtkRenderWindow]:
        window = cls()
        window.SetOffScreenRendering(1)
        if window.GetClassName() == "vtkOSOpenGLRenderWindow" and not has_osmesa:
            continue
        if window.SupportsOpenGL():
            return window
    raise RegistrationError("VTK could not create an OpenGL context for the VTK DRR engine (no display, EGL "
                            "or OSMesa): run under a display or xvfb-run, or use the CPU DRR engine")


class VtkDrrRenderer:
    """Keeps the VTK pipeline of one attenuation level for repeated renders (texture uploaded once).

    sample_distance_mm: ray sampling step (default: half the smallest voxel spacing).
    interpolation: "nearest" (the CPU engine's voxel model) or "linear".
    """

    def __init__(self, level: MuLevel, *, sample_distance_mm: float | None = None,
                 interpolation: str = "nearest"):
        from vtkmodules import vtkRenderingVolumeOpenGL2  # noqa: F401  (registers the OpenGL mapper)
        from vtkmodules.util import numpy_support
        from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPiecewiseFunction
        from vtkmodules.vtkCommonMath import vtkMatrix3x3
        from vtkmodules.vtkRenderingCore import (
            vtkColorTransferFunction,
            vtkRenderer,
            vtkVolume,
            vtkVolumeProperty,
        )
        from vtkmodules.vtkRenderingVolumeOpenGL2 import vtkOpenGLGPUVolumeRayCastMapper

        if interpolation not in ("nearest", "linear"):
            raise ValueError(f"interpolation must be 'nearest' or 'linear', not {interpolation!r}")
        view, spacing, direction, origin = _canonical_grid(level.mu_per_mm, level.ijk_to_lps)
        self.sample_distance_mm = float(sample_distance_mm or 0.5 * spacing.min())
        padded = np.pad(np.asarray(view, dtype=np.float32), 1)
        self.mu_max = float(padded.max()) or 1.0
        box_mm = np.array(padded.shape) * spacing
        self._corners_lps = self._box_corners(origin, spacing, direction, np.array(view.shape))
        n_samples_max = float(np.linalg.norm(box_mm)) / self.sample_distance_mm + 2.0
        self._scale = 1.0 / (_OPACITY * n_samples_max)  # the sum cannot exceed 1 after scaling

        image = vtkImageData()
        image.SetDimensions(*padded.shape)
        image.SetSpacing(*spacing)
        image.SetOrigin(*(origin - direction @ spacing))  # the padding voxel before index 0
        if not np.allclose(direction, np.eye(3)):
            matrix = vtkMatrix3x3()
            for r in range(3):
                for c in range(3):
                    matrix.SetElement(r, c, direction[r, c])
            image.SetDirectionMatrix(matrix)
        scalars = numpy_support.numpy_to_vtk(padded.ravel(order="F"), deep=True)
        image.GetPointData().SetScalars(scalars)

        mapper = vtkOpenGLGPUVolumeRayCastMapper()
        mapper.SetInputData(image)
        mapper.SetBlendModeToAdditive()
        mapper.AutoAdjustSampleDistancesOff()
        mapper.LockSampleDistanceToInputSpacingOff()
        mapper.SetSampleDistance(self.sample_distance_mm)
        mapper.SetImageSampleDistance(1.0)
        mapper.UseJitteringOff()

        prop = vtkVolumeProperty()
        if interpolation == "nearest":
            prop.SetInterpolationTypeToNearest()
        else:
            prop.SetInterpolationTypeToLinear()
        opacity = vtkPiecewiseFunction()
        opacity.AddPoint(0.0, _OPACITY)
        opacity.AddPoint(self.mu_max, _OPACITY)
        prop.SetScalarOpacity(opacity)
        prop.SetScalarOpacityUnitDistance(self.sample_distance_mm)
        colour = vtkColorTransferFunction()
        colour.AddRGBPoint(0.0, 1.0, 1.0, 1.0)
        colour.AddRGBPoint(self.mu_max, 1.0, 1.0, 1.0)
        prop.SetColor(colour)
        prop.ShadeOff()

        volume = vtkVolume()
        volume.SetMapper(mapper)
        volume.SetProperty(prop)
        shader = volume.GetShaderProperty()
        shader.AddFragmentShaderReplacement("//VTK::Shading::Exit", True, _EXIT_SHADER, False)
        shader.GetFragmentCustomUniforms().SetUniformf("carm_scale", self._scale)

        renderer = vtkRenderer()
        renderer.SetBackground(0.0, 0.0, 0.0)
        renderer.AddVolume(volume)
        window = _new_render_window()
        window.SetMultiSamples(0)
        window.AddRenderer(renderer)
        self._image, self._mapper, self._volume, self._renderer, self._window = (
            image, mapper, volume, renderer, window)
        self._numpy_support = numpy_support
        self._thread = threading.get_ident()

    @staticmethod
    def _box_corners(origin, spacing, direction, shape) -> np.ndarray:
        """(8, 3) LPS corners of the voxel box (voxel edges) of the canonical grid."""
        lo, hi = -0.5 * np.ones(3), shape - 0.5
        ijk = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
        return (ijk * spacing) @ direction.T + origin

    def render(self, geometry: CarmGeometry, pose: CarmPose | np.ndarray,
               intrinsics: CarmIntrinsics | None = None) -> np.ndarray:
        """Line integrals (rows, cols) float32 for one pose, image[row, column], row 0 at the top."""
        from vtkmodules.vtkCommonCore import vtkUnsignedCharArray
        from vtkmodules.vtkCommonMath import vtkMatrix4x4

        if threading.get_ident() != self._thread:
            raise RuntimeError("VtkDrrRenderer must be used from the thread that created it")
        intr = intrinsics or geometry.intrinsics
        pose_arr = pose.as_array() if isinstance(pose, CarmPose) else np.asarray(pose, dtype=np.float64)
        rotation, t = geometry.extrinsics(pose_arr)
        source = -rotation.T @ t
        depths = (self._corners_lps @ rotation.T + t)[:, 2]
        near = max(1.0, 0.9 * depths.min())
        far = max(near + 1.0, 1.1 * depths.max())

        camera = self._renderer.GetActiveCamera()
        camera.SetPosition(*source)
        camera.SetFocalPoint(*(source + rotation[2] * intr.sdd_mm))
        camera.SetViewUp(*(-rotation[1]))
        camera.SetClippingRange(near, far)
        projection = vtkMatrix4x4()
        gl = _opengl_projection(intr, near, far)
        for r in range(4):
            for c in range(4):
                projection.SetElement(r, c, gl[r, c])
        camera.SetExplicitProjectionTransformMatrix(projection)
        camera.UseExplicitProjectionTransformMatrixOn()

        cols, rows = intr.size_px
        self._window.SetSize(int(cols), int(rows))
        self._window.Render()
        buffer = vtkUnsignedCharArray()
        self._window.GetRGBACharPixelData(0, 0, int(cols) - 1, int(rows) - 1, 0, buffer)
        rgba = self._numpy_support.vtk_to_numpy(buffer).reshape(int(rows), int(cols), 4)[::-1]
        digits = rgba[..., :3].astype(np.float64) / 255.0
        packed = digits[..., 0] + digits[..., 1] / 255.0 + digits[..., 2] / 65025.0
        line_integral = packed / (self._scale * _OPACITY) * self.mu_max * self.sample_distance_mm
        return line_integral.astype(np.float32)

    def close(self) -> None:
        """Release the OpenGL resources."""
        if self._window is not None:
            self._window.Finalize()
            self._window = None

    def __enter__(self) -> VtkDrrRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_cache: dict = {}
_cache_lock = threading.Lock()


def render_line_integrals_vtk(level: MuLevel, geometry: CarmGeometry, pose_or_poses,
                              intrinsics: CarmIntrinsics | None = None, *,
                              sample_distance_mm: float | None = None,
                              interpolation: str = "nearest") -> np.ndarray:
    """Line integrals L (float32) by VTK GPU ray casting (see module docstring).

    One pose (CarmPose or (6,)) -> (rows, cols); poses (b, 6) -> (b, rows, cols), rendered one after another.
    The VTK pipeline of the most recent (level, settings, thread) is kept for the next call. A pinhole camera
    only: a detector with radial distortion (``CarmIntrinsics.distortion_mm``) is refused (``drr.cpu`` renders it).
    """
    if (intrinsics or geometry.intrinsics).distortion_mm:
        raise GeometryError("the VTK ray caster renders a pinhole camera; a detector with distortion is rendered "
                            "by the CPU engine (--engine cpu)")
    key = (id(level.mu_per_mm), sample_distance_mm, interpolation, threading.get_ident())
    with _cache_lock:
        hit = _cache.get("renderer")
        if hit is None or hit[0] != key or hit[1]() is not level.mu_per_mm:
            if hit is not None:
                hit[2].close()
            _cache["renderer"] = (key, weakref.ref(level.mu_per_mm),
                                  VtkDrrRenderer(level, sample_distance_mm=sample_distance_mm,
                                                 interpolation=interpolation))
        renderer = _cache["renderer"][2]
    if isinstance(pose_or_poses, CarmPose) or np.asarray(pose_or_poses).ndim == 1:
        return renderer.render(geometry, pose_or_poses, intrinsics)
    return np.stack([renderer.render(geometry, p, intrinsics) for p in np.asarray(pose_or_poses, float)])


def release_vtk_renderer() -> None:
    """Close the cached VTK pipeline (frees the volume texture and the OpenGL context)."""
    with _cache_lock:
        hit = _cache.pop("renderer", None)
    if hit is not None:
        hit[2].close()


_PROBE = """
import numpy as np
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose
from carmreg.logic.geometry.volume import MuLevel
from carmreg.logic.drr.vtk_raycast import render_line_integrals_vtk
mu = np.zeros((8, 8, 8), np.float32); mu[2:6, 2:6, 2:6] = 0.02
level = MuLevel(mu, np.diag([4.0, 4.0, 4.0, 1.0]), None)
g = CarmGeometry(CarmIntrinsics(1000.0, (2.0, 2.0), (16, 16)), (14.0, 14.0, 14.0), 500.0)
img = render_line_integrals_vtk(level, g, CarmPose())
print("OK" if abs(float(img[7, 7]) - 0.32) < 0.02 else f"BAD {img[7, 7]}")
"""


def vtk_rendering_status(timeout_s: float = 60.0) -> tuple[bool, str]:
    """Whether the VTK engine works here, checked in a subprocess (a failing OpenGL driver cannot crash us).

    Returns (ok, message). Cached for the process.
    """
    if "probe" not in _cache:
        try:
            done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                                  timeout=timeout_s)
            tail = (done.stdout.strip().splitlines() or [""])[-1]
            ok = done.returncode == 0 and tail == "OK"
            errors = [re.sub(r"\x1b\[[0-9;]*m", "", line) for line in done.stderr.splitlines()
                      if line.strip() and "WARN" not in line]
            message = "ok" if ok else (tail or (errors or [f"exit code {done.returncode}"])[-1])
        except (OSError, subprocess.TimeoutExpired) as exc:
            ok, message = False, f"probe failed: {exc}"
        _cache["probe"] = (ok, str(message))
    return _cache["probe"]
