"""The 3D view: bone surface of the CT, the CT centroids and, after registration, the C-arm.

Drawn with VTK through pyvista, in LPS mm. Three ways to show it, chosen at run time:

- ``interactive``: a pyvistaqt QtInteractor inside the window (needs an OpenGL display: a desktop or Xvfb);
- ``offscreen``: no display (Qt's offscreen platform), but VTK can render offscreen (EGL/OSMesa): the scene
  is rendered to an image shown in a label; drag to rotate, buttons for AP / lateral views;
- ``message``: no OpenGL at all: a message says so and the rest of the application works as usual.

The C-arm is drawn from ``geometry.source_lps_mm(pose)`` (a sphere) and ``geometry.detector_corners_lps_mm``
(the detector rectangle), joined by the four edges of the X-ray frustum.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import numpy as np
from qtpy import QtCore, QtGui, QtWidgets

from ..qt_common import is_offscreen

LOG = logging.getLogger("carmreg.gui")
BONE_HU = 250.0
_PROBE: dict[str, bool] = {}


def offscreen_vtk_available() -> bool:
    """Whether VTK can render without a display; probed once in a child process (a crash stays there)."""
    if "ok" not in _PROBE:
        if os.environ.get("CARMREG_NO_VTK"):
            _PROBE["ok"] = False
        else:
            code = ("import pyvista as pv; p = pv.Plotter(off_screen=True, window_size=(64, 64)); "
                    "p.add_mesh(pv.Sphere()); img = p.screenshot(); assert img.mean() > 0; p.close()")
            try:
                done = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
                _PROBE["ok"] = done.returncode == 0
            except (OSError, subprocess.TimeoutExpired):
                _PROBE["ok"] = False
    return _PROBE["ok"]


def choose_mode() -> str:
    if os.environ.get("CARMREG_NO_VTK"):
        return "message"
    if not is_offscreen():
        return "interactive"
    return "offscreen" if offscreen_vtk_available() else "message"


def bone_surface(volume, threshold_hu: float = BONE_HU, target_mm: float = 2.0, max_cells: int = 600_000):
    """Marching-cubes iso-surface at ``threshold_hu`` in LPS mm (pyvista PolyData), or None if empty.

    The CT is strided to about ``target_mm`` voxels and lightly smoothed (Gaussian, 0.7 voxel) so noise and
    small contrast-filled vessels make fewer islands; the stride grows until the surface has at most
    ``max_cells`` triangles (keeps the 3D view responsive on software OpenGL)."""
    import pyvista as pv
    from scipy import ndimage

    spacing = np.asarray(volume.spacing_mm, float)
    for factor in (1.0, 1.5, 2.0, 3.0):
        strides = np.maximum(1, np.round(factor * target_mm / spacing)).astype(int)
        hu = np.asarray(volume.hu[::strides[0], ::strides[1], ::strides[2]], np.float32)
        hu = ndimage.gaussian_filter(hu, 0.7)
        grid = pv.ImageData(dimensions=hu.shape)
        grid.point_data["hu"] = hu.ravel(order="F")
        surface = grid.contour([float(threshold_hu)], scalars="hu")
        if surface.n_cells <= max_cells:
            break
    if surface.n_points == 0:
        return None
    ijk = np.asarray(surface.points) * strides.astype(float)
    surface.points = ijk @ volume.ijk_to_lps[:3, :3].T + volume.ijk_to_lps[:3, 3]
    return surface.compute_normals(cell_normals=False, auto_orient_normals=False)


def build_scene(plotter, surface, points: list[tuple[str, np.ndarray]], carm: dict | None,
                selected: str | None = None, ct_corners_lps_mm: np.ndarray | None = None) -> None:
    """Fill a pyvista plotter with bone, the CT's outline, named centroids and the C-arm frustum (LPS mm)."""
    import pyvista as pv

    plotter.clear_actors()  # not clear(): that also removes the lights
    plotter.set_background("#15181c", top="#2b3038")
    if ct_corners_lps_mm is not None:
        # corners are ordered i-major (see Volume.corners_lps_mm): edges join corners differing in one index
        edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
        outline = pv.PolyData(np.asarray(ct_corners_lps_mm, float),
                              lines=np.hstack([[2, a, b] for a, b in edges]))
        plotter.add_mesh(outline, color="#6c757d", line_width=1, name="ct_outline", render=False)
    if surface is not None:
        plotter.add_mesh(surface, color="#e9dfc8", specular=0.25, name="bone", render=False)  # normals precomputed
    if points:
        coords = np.array([p for _, p in points], float)
        colors = ["#ffd43b" if name == selected else "#39d0ff" for name, _ in points]
        for (name, p), color in zip(points, colors, strict=True):
            plotter.add_mesh(pv.Sphere(radius=4.0, center=p), color=color, name=f"pt_{name}", render=False)
        plotter.add_point_labels(coords, [n for n, _ in points], font_size=14, text_color="white",
                                 shape_color="#1c2530", shape_opacity=0.7, point_size=1, show_points=False,
                                 always_visible=True, name="labels", render=False)
    if carm is not None:
        source, corners = np.asarray(carm["source_lps_mm"], float), np.asarray(carm["detector_lps_mm"], float)
        plotter.add_mesh(pv.Sphere(radius=12.0, center=source), color="#ff6b6b", name="source", render=False)
        quad = pv.PolyData(corners, faces=[4, 0, 1, 2, 3])
        plotter.add_mesh(quad, color="#74c0fc", opacity=0.35, name="detector", render=False)
        plotter.add_mesh(quad.extract_all_edges(), color="#74c0fc", line_width=2, name="detector_edges", render=False)
        lines = pv.PolyData(np.vstack([source[None], corners]),
                            lines=np.hstack([[2, 0, i] for i in range(1, 5)]))
        plotter.add_mesh(lines, color="#ffa94d", line_width=1.5, name="frustum", render=False)
        centre = corners.mean(0)
        axis = pv.Line(source, centre)
        plotter.add_mesh(axis, color="#ffa94d", line_width=1, opacity=0.6, name="axis", render=False)
    if not getattr(plotter, "_carmreg_axes", False):
        plotter.add_axes(xlabel="L", ylabel="P", zlabel="S")
        plotter._carmreg_axes = True


def set_view(plotter, name: str, bounds_centre: np.ndarray, distance: float) -> None:
    """Camera presets in LPS: AP (from anterior), lateral (from the patient's left), oblique."""
    direction = {"AP": (0, -1, 0), "Lateral": (1, 0, 0), "Oblique": (0.6, -0.7, 0.35),
                 "Superior": (0, 0, 1)}[name]
    up = (0, 1, 0) if name == "Superior" else (0, 0, 1)
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    plotter.camera_position = [tuple(bounds_centre + distance * d), tuple(bounds_centre), up]


class View3D(QtWidgets.QWidget):
    """3D scene widget that degrades gracefully without OpenGL (see module docstring)."""

    def __init__(self, parent=None, mode: str | None = None):
        super().__init__(parent)
        self.setObjectName("view3d")
        self.mode = mode or choose_mode()
        self._volume = None
        self._surface = None
        self._points: list[tuple[str, np.ndarray]] = []
        self._carm: dict | None = None
        self._selected: str | None = None
        self._view_name = "Oblique"
        self._plotter = None
        self._drag_origin = None
        self._build_ui()

    # ------------------------------------------------------------------------------------- UI
    def _build_ui(self) -> None:
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.setSpacing(0)
        bar = QtWidgets.QHBoxLayout()
        bar.setContentsMargins(4, 2, 4, 2)
        title = QtWidgets.QLabel("3D")
        title.setStyleSheet("font-weight: 600;")
        bar.addWidget(title)
        bar.addStretch(1)
        for name, short in (("AP", "AP"), ("Lateral", "Lat"), ("Oblique", "Obl"), ("Superior", "Sup")):
            button = QtWidgets.QToolButton()
            button.setText(short)
            button.setToolTip(f"{name} view")
            button.clicked.connect(lambda _=False, n=name: self.show_view(n))
            bar.addWidget(button)
        self.bone_check = QtWidgets.QCheckBox("Bone \u2265")
        self.bone_check.setChecked(True)
        self.bone_check.toggled.connect(lambda _: self.refresh())
        bar.addWidget(self.bone_check)
        self.threshold_spin = QtWidgets.QSpinBox()
        self.threshold_spin.setRange(-1000, 3000)
        self.threshold_spin.setSingleStep(50)
        self.threshold_spin.setValue(int(BONE_HU))
        self.threshold_spin.setSuffix(" HU")
        self.threshold_spin.setKeyboardTracking(False)
        self.threshold_spin.setToolTip("Iso-surface threshold; raise it (e.g. 400) if contrast-filled vessels "
                                       "hide the spine")
        self.threshold_spin.valueChanged.connect(lambda _v: self.set_volume(self._volume))
        bar.addWidget(self.threshold_spin)
        holder = QtWidgets.QWidget()  # the bar never sets the view's minimum width (it clips when narrow)
        holder.setLayout(bar)
        holder.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Fixed)
        layout.addWidget(holder)
        self.stack = QtWidgets.QStackedWidget()
        self.image_label = _DragLabel(self)
        self.image_label.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.image_label.setStyleSheet("background: #15181c; color: #9aa0a6;")
        self.image_label.setMinimumSize(160, 160)
        self.image_label.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Ignored)
        self.stack.addWidget(self.image_label)
        layout.addWidget(self.stack, 1)
        if self.mode == "interactive":
            try:
                from pyvistaqt import QtInteractor
                # auto_update=False: pyvistaqt's default re-renders 5 times a second forever (an idle window
                # then holds a core busy); this view renders when its content or the camera changes
                self._plotter = QtInteractor(self.stack, auto_update=False)
                self.stack.addWidget(self._plotter.interactor)
                self.stack.setCurrentWidget(self._plotter.interactor)
            except Exception as exc:  # noqa: BLE001 - no OpenGL: fall back, keep the app running
                LOG.warning("interactive 3D view unavailable (%s); rendering offscreen", exc)
                self._plotter = None
                self.mode = "offscreen" if offscreen_vtk_available() else "message"
        if self.mode == "message":
            self.image_label.setText("3D view unavailable: no OpenGL on this display.\n"
                                     "Slices, X-ray, registration and overlay work as usual.")

    def _offscreen_plotter(self):
        if self._plotter is None:
            import pyvista as pv
            self._plotter = pv.Plotter(off_screen=True, window_size=self._render_size())
        return self._plotter

    def _render_size(self) -> tuple[int, int]:
        size = self.stack.size()
        return max(320, size.width()), max(240, size.height())

    # ------------------------------------------------------------------------------------- content
    def surface(self):
        """The bone surface (pyvista PolyData) or None; share it with another View3D of the same CT."""
        return self._surface

    def set_volume(self, volume, surface=None) -> None:
        self._volume = volume
        self._surface = surface
        if volume is not None and surface is None and self.mode != "message":
            try:
                self._surface = bone_surface(volume, float(self.threshold_spin.value()))
            except Exception as exc:  # noqa: BLE001 - the 3D view is optional
                LOG.warning("bone surface failed: %s", exc)
        self.refresh(reset_camera=True)

    def set_points(self, points: list[tuple[str, np.ndarray]], selected: str | None = None) -> None:
        self._points = [(n, np.asarray(p, float)) for n, p in points]
        self._selected = selected
        self.refresh()

    def set_carm(self, source_lps_mm, detector_corners_lps_mm) -> None:
        self._carm = None if source_lps_mm is None else {"source_lps_mm": source_lps_mm,
                                                          "detector_lps_mm": detector_corners_lps_mm}
        self.refresh(reset_camera=True)

    def has_carm(self) -> bool:
        return self._carm is not None

    def show_view(self, name: str) -> None:
        self._view_name = name
        self.refresh(reset_camera=True)

    def refresh(self, reset_camera: bool = False) -> None:
        if self.mode == "message" or (self.mode == "interactive" and self._plotter is None):
            return  # no 3D, or its plotter closed with the window (``close_plotter``)
        try:
            plotter = self._plotter if self.mode == "interactive" else self._offscreen_plotter()
            camera = None if reset_camera else plotter.camera_position
            corners = self._volume.corners_lps_mm() if self._volume is not None else None
            build_scene(plotter, self._surface if self.bone_check.isChecked() else None, self._points,
                        self._carm, self._selected, corners)
            if reset_camera or camera is None or self._volume is None:
                self._apply_view(plotter)
            else:
                plotter.camera_position = camera
            if self.mode == "interactive":
                plotter.render()
            else:
                self._show_offscreen(plotter)
        except Exception as exc:  # noqa: BLE001 - the 3D view is optional
            LOG.warning("3D view failed: %s", exc, exc_info=True)
            self.mode = "message"
            self.stack.setCurrentWidget(self.image_label)
            self.image_label.setText(f"3D view unavailable ({exc.__class__.__name__}).\nThe rest of CarmReg works.")

    def _apply_view(self, plotter) -> None:
        """Look from the chosen direction and fit every actor (CT, points, C-arm) in the view."""
        if self._volume is None and self._carm is None:
            plotter.reset_camera()
            return
        centre = self._volume.center_lps_mm() if self._volume is not None else self._carm["source_lps_mm"]
        set_view(plotter, self._view_name, np.asarray(centre, float), 1000.0)
        plotter.reset_camera()  # fits the bounding sphere vertically; narrow views need more room
        width, height = self._render_size() if self.mode != "interactive" else (self.width(), self.height())
        # the bounding sphere of the long C-arm frustum leaves most of the view empty: come closer with it
        plotter.camera.zoom((1.5 if self._carm is not None else 1.1) * min(1.0, width / max(height, 1)))
        plotter.reset_camera_clipping_range()

    def _show_offscreen(self, plotter) -> None:
        size = self._render_size()
        if tuple(plotter.window_size) != size:
            plotter.window_size = size
        plotter.render()  # screenshot() alone may return the previous frame
        image = np.ascontiguousarray(plotter.screenshot(return_img=True))
        rows, cols = image.shape[:2]
        qimage = QtGui.QImage(image.data, cols, rows, 3 * cols, QtGui.QImage.Format.Format_RGB888).copy()
        self.image_label.setPixmap(QtGui.QPixmap.fromImage(qimage))

    def rotate(self, d_azimuth: float, d_elevation: float) -> None:
        if self._plotter is None or self.mode != "offscreen":
            return
        camera = self._plotter.camera
        camera.Azimuth(float(d_azimuth))
        camera.Elevation(float(d_elevation))
        camera.OrthogonalizeViewUp()
        self._plotter.reset_camera_clipping_range()
        self._plotter.render()
        self._show_offscreen(self._plotter)

    def render_image(self) -> np.ndarray | None:
        """RGB (rows, cols, 3) uint8 of the current 3D scene, or None without OpenGL."""
        if self.mode == "message" or self._plotter is None:
            return None
        self._plotter.render()
        return np.asarray(self._plotter.screenshot(return_img=True))

    def prepare_grab(self) -> None:
        """Before a widget grab: show a rendered image, since an OpenGL widget grabs black."""
        if self.mode == "interactive":
            image = self.render_image()
            if image is not None:
                image = np.ascontiguousarray(image[..., :3])
                rows, cols = image.shape[:2]
                qimage = QtGui.QImage(image.data, cols, rows, 3 * cols, QtGui.QImage.Format.Format_RGB888)
                self.image_label.setPixmap(QtGui.QPixmap.fromImage(qimage.copy()))
                self.stack.setCurrentWidget(self.image_label)

    def finish_grab(self) -> None:
        if self.mode == "interactive" and self._plotter is not None:
            self.stack.setCurrentWidget(self._plotter.interactor)

    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        if self.mode != "message" and self._plotter is not None:
            QtCore.QTimer.singleShot(0, lambda: self.refresh(reset_camera=True))

    def close_plotter(self) -> None:
        if self._plotter is not None:
            try:
                self._plotter.close()
            except Exception:  # noqa: BLE001
                pass
            self._plotter = None


class _DragLabel(QtWidgets.QLabel):
    """Image label that turns mouse drags into camera rotations (offscreen mode)."""

    def __init__(self, view: View3D):
        super().__init__()
        self._view = view
        self._last = None

    def mousePressEvent(self, event) -> None:
        self._last = event.position()

    def mouseMoveEvent(self, event) -> None:
        if self._last is not None:
            delta = event.position() - self._last
            self._last = event.position()
            self._view.rotate(-delta.x() * 0.4, delta.y() * 0.4)

    def mouseReleaseEvent(self, event) -> None:
        self._last = None
