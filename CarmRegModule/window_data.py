"""The window's data: loading the CT and the X-ray (with geometry overrides), the sample case, and the CT and
X-ray centroids (import, export, proposal from a vertebra label map, spine-order check). A mixin of
``CarmRegWidget``; every computation is a call into the logic."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
from qtpy import QtGui

from carmreg.logic.errors import InputFileError, LandmarkError
from carmreg.logic.image.turn import orient_uv, stored_uv
from carmreg.logic.io import session as session_io
from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d, write_landmarks_2d, write_landmarks_3d

LOG = logging.getLogger("carmreg.gui")
SCREENSHOT_VIEWS = ("window", "axial", "coronal", "sagittal", "ct", "xray", "overlay", "3d", "result")


class WindowData:
    """Mixin of CarmRegWidget: the data and the landmarks."""

    # =========================================================================================== data
    def load_ct(self, path: str | Path) -> None:
        """Load a CT through ``carmreg.logic.io.volumes.load_volume`` (raises CarmRegError on bad input)."""
        from carmreg.logic.io.volumes import load_volume

        self._busy(f"Loading CT {Path(path).name}...")
        try:
            volume = load_volume(path)
        finally:
            self._idle()
        self.set_ct_volume(volume, str(path))

    def set_ct_volume(self, volume, path: str | None = None) -> None:
        self.ct_volume, self.ct_path = volume, path
        for view in self.slice_views:
            view.set_volume(volume)
        self._busy("Building the bone surface for the 3D view...")
        try:
            self.view3d.set_volume(volume)
            self.view3d_result.set_volume(volume, surface=self.view3d.surface())
        finally:
            self._idle()
        self._update_3d_points()
        if volume is not None:
            n = volume.shape
            sp = volume.spacing_mm
            self.ct_info.setText(f"{Path(path).name if path else 'CT (in memory)'}<br>"
                                 f"{n[0]} x {n[1]} x {n[2]} voxels, {sp[0]:.2f} x {sp[1]:.2f} x {sp[2]:.2f} mm<br>"
                                 f"HU {float(np.min(volume.hu)):.0f} to {float(np.max(volume.hu)):.0f}")
        else:
            self.ct_info.setText("No CT loaded")
        self._inputs_changed()

    def load_xray(self, path: str | Path, overrides: dict | None = None) -> None:
        """Load an X-ray (``carmreg.logic.io.xray.load_xray``) with the geometry overrides (raises CarmRegError)."""
        from carmreg.logic.io.xray import load_xray

        overrides = dict(self.geometry_overrides if overrides is None else overrides)
        xray = load_xray(path, **_geometry_kwargs(overrides))
        self.set_xray_image(xray, str(path), overrides)

    def set_xray_image(self, xray, path: str | None = None, overrides: dict | None = None) -> None:
        """Show ``xray`` (read from ``path``, as stored) with its geometry, turned by the X-ray orientation
        (``set_xray_orientation``). Another X-ray file than the one shown takes the clicks of the previous image away
        (``_drop_clicks_of_previous_xray``) and is shown as stored; the file a session named but could not find,
        found again, is shown turned as the session had it (its points, kept as stored, turn with it)."""
        first = self.xray_as_stored is None or self.xray_path != path
        if first and self.xray_as_stored is not None and path is not None:  # another file replaces the one shown
            self._drop_clicks_of_previous_xray()
        missed = self.xray_orientation if self.xray_as_stored is None and path and path == self.xray_path else None
        if first:
            self.xray_orientation = "as-stored"
        self.xray_as_stored, self.xray_path = xray, path
        self.geometry_overrides = dict(overrides or {})
        self.geometry_panel.set_xray(xray, self.geometry_overrides)
        self._show_xray(pixels_changed=first or xray is None)
        if missed is not None and xray is not None:
            self._apply_orientation(missed)

    def _show_xray(self, pixels_changed: bool) -> None:
        """``self.xray``: the stored X-ray turned by ``self.xray_orientation``: what the view shows, the clicks lie on
        and the registration gets."""
        from carmreg.logic.image.turn import turned_xray

        stored = self.xray_as_stored
        self.xray = None if stored is None else turned_xray(stored, self.xray_orientation)
        if pixels_changed:
            self.xray_view.set_pixels(None if self.xray is None else self.xray.pixels)
        intr = getattr(self.xray, "intrinsics", None)
        self.xray_view.pixel_spacing_mm = intr.pixel_spacing_mm if intr else None
        self.orientation_combo.blockSignals(True)
        self.orientation_combo.setCurrentIndex(max(self.orientation_combo.findData(self.xray_orientation), 0))
        self.orientation_combo.blockSignals(False)
        self.orientation_combo.setEnabled(stored is not None)
        if stored is not None:
            cols, rows = stored.size_px
            modality = stored.meta.get("modality", "") if isinstance(stored.meta, dict) else ""
            geometry = (f"SDD {intr.sdd_mm:.0f} mm, {intr.pixel_spacing_mm[0]:.3f} mm pixels"
                        if intr else "<span style='color:#ffa94d'>geometry incomplete: see below</span>")
            turned = ("" if self.xray_orientation == "as-stored" else
                      f"<br><span style='color:#ffa94d'>shown {self.xray_orientation.replace('-', ' ')}</span>")
            self.xray_info.setText(f"{Path(self.xray_path).name if self.xray_path else 'X-ray (in memory)'}  "
                                   f"{modality}<br>{cols} x {rows} px, bone {'dark' if stored.bone_dark else 'bright'}"
                                   f"<br>{geometry}{turned}")
        else:
            self.xray_info.setText("No X-ray loaded")
        self._inputs_changed()

    def set_xray_orientation(self, name: str) -> None:
        """Show, click and register the X-ray turned by ``name`` (``image.turn.ORIENTATIONS``): a display stored
        mirrored or rotated, turned back as a refusal names it. The placed points turn with the image (one undo step,
        "Show the X-ray ..."); exports and sessions keep them on the image as stored."""
        from carmreg.logic.image.turn import ORIENTATIONS

        if name not in ORIENTATIONS:
            raise InputFileError(f"X-ray orientation '{name}' is not one of: {', '.join(ORIENTATIONS)}")
        if self.xray_as_stored is None:
            raise InputFileError("load an X-ray before turning it")
        if name != self.xray_orientation:
            self.undo_stack.push(_TurnXray(self, self.xray_orientation, name))

    def _apply_orientation(self, name: str) -> None:
        """Turn the shown X-ray to ``name`` and move the X-ray points with it (``_TurnXray`` does and undoes this;
        reopening a session, already so turned: nothing to do)."""
        if name == self.xray_orientation:
            return
        old, size = self.xray_orientation, self.xray_as_stored.size_px
        self.xray_orientation = name
        self.xray_store.map_positions(lambda uv: orient_uv(stored_uv(uv, old, size), name, size))
        self._show_xray(pixels_changed=True)

    def xray_uv_as_stored(self, uv_px) -> np.ndarray:
        """X-ray points (u, v) where the window shows them (turned by the X-ray orientation) on the image as stored."""
        return stored_uv(uv_px, self.xray_orientation, self.xray_as_stored.size_px)

    def xray_uv_as_shown(self, uv_px) -> np.ndarray:
        """X-ray points (u, v) on the image as stored where the window shows them (the inverse of
        ``xray_uv_as_stored``)."""
        return orient_uv(uv_px, self.xray_orientation, self.xray_as_stored.size_px)

    def _drop_clicks_of_previous_xray(self) -> None:
        """Clicks placed on one X-ray are not the vertebrae of another (even of the same size, where they would
        otherwise register silently): removed in one undoable step, said in the status bar."""
        n = len(self.xray_store)
        if n:
            self.xray_store.replace_all([], [], text="Remove the previous X-ray's points")
            self.statusBar().showMessage(f"Another X-ray: the {n} point(s) placed on the previous image were removed "
                                         "(Edit > Undo brings them back)", 15000)

    def apply_geometry(self, overrides: dict) -> None:
        """Re-read the X-ray with new geometry overrides (the logic decides and records the sources)."""
        if self.xray_as_stored is None:
            raise InputFileError("load an X-ray before setting its geometry")
        if self.xray_path:
            self.load_xray(self.xray_path, overrides)
            return
        from carmreg.logic.geometry.camera import (
            CarmIntrinsics,  # in-memory image (tests, scripts): same rules, no file
        )

        stored = self.xray_as_stored
        intr = stored.intrinsics
        kw = _geometry_kwargs(overrides)
        spacing = kw.get("pixel_spacing_mm") or (intr.pixel_spacing_mm if intr else None)
        sdd = kw.get("sdd_mm") or (intr.sdd_mm if intr else None)
        new_intr = None
        if spacing is not None and sdd is not None:
            new_intr = CarmIntrinsics(float(sdd), tuple(spacing), stored.size_px, kw.get("principal_point_px"),
                                      sources={k: "manual" for k in kw},
                                      distortion_mm=kw.get("distortion_mm", 0.0))
        xray = dataclasses.replace(stored, intrinsics=new_intr, sod_mm=kw.get("sod_mm", stored.sod_mm))
        self.set_xray_image(xray, None, overrides)

    def measure_distortion(self, path: str | Path):
        """The pincushion measured on a bead-grid X-ray of this C-arm (``grid_calibration.calibrate_for_detector``:
        the grid image's own pixel spacing, else the X-ray's), set as the X-ray's ``distortion_mm`` override. The
        grid is taken as stored, like the X-ray file (same field size and orientation)."""
        from carmreg.logic.image.grid_calibration import calibrate_for_detector
        from carmreg.logic.io.xray import load_xray

        stored = self.xray_as_stored
        if stored is None or stored.intrinsics is None:
            raise InputFileError("load the X-ray and complete its geometry before measuring its pincushion")
        grid = load_xray(path)
        cal = calibrate_for_detector(grid.pixels, grid.intrinsics.pixel_spacing_mm if grid.intrinsics else None,
                                     stored.intrinsics, str(path))
        self.geometry_panel.set_value("distortion_mm", round(cal.distortion_mm, 2))
        return cal

    def load_sample_case(self) -> None:
        """Load the embedded sample: CT, X-ray (DICOM with geometry) and the centroids on both."""
        from carmreg.logic.resources import sample_case

        paths = sample_case()
        self.new_session(ask=False)
        self.load_ct(paths["ct"])
        self.geometry_overrides = {}
        self.load_xray(paths["xray"], {})
        self.import_ct_landmarks(paths["ct_landmarks"], undoable=False)
        self.import_xray_landmarks(paths["xray_landmarks"], undoable=False)
        self.undo_stack.clear()
        self._dirty = False
        self._update_title()
        self.statusBar().showMessage("Sample case loaded: CT, simulated C-arm X-ray and centroids on both", 8000)

    # =========================================================================================== landmarks
    def import_ct_landmarks(self, path: str | Path, undoable: bool = True) -> None:
        marks = read_landmarks_3d(path)
        self.ct_store.replace_all(marks.labels, marks.points_lps_mm, f"Import {Path(path).name}", undoable)

    def import_xray_landmarks(self, path: str | Path, undoable: bool = True) -> None:
        """X-ray points from a file, given on the image as stored (as ``carmreg register`` takes them), shown where
        the turned X-ray shows them."""
        stored = self.xray_as_stored
        spacing = stored.intrinsics.pixel_spacing_mm if getattr(stored, "intrinsics", None) else None
        marks = read_landmarks_2d(path, spacing)
        uv_px = marks.uv_px if stored is None else self.xray_uv_as_shown(marks.uv_px)
        self.xray_store.replace_all(marks.labels, uv_px, f"Import {Path(path).name}", undoable)

    def export_ct_landmarks(self, path: str | Path) -> Path:
        marks = self.ct_store.to_landmarks()
        if not marks.labels:
            raise LandmarkError("there are no named CT centroids to export; place some first (step 2)")
        return write_landmarks_3d(path, marks)

    def export_xray_landmarks(self, path: str | Path) -> Path:
        """The X-ray points on the image as stored (whatever turn the window shows it in)."""
        marks = self.xray_store.to_landmarks()
        if not len(marks.labels):
            raise LandmarkError("there are no X-ray centroids to export; place some first (step 3)")
        stored = self.xray_as_stored
        spacing = stored.intrinsics.pixel_spacing_mm if getattr(stored, "intrinsics", None) else None
        if stored is not None:
            marks = dataclasses.replace(marks, uv_px=self.xray_uv_as_stored(marks.uv_px))
        return write_landmarks_2d(path, marks, spacing)

    def propose_centroids(self, label_map_path: str | Path, mode: str = "replace") -> list[str]:
        """Centroids of the complete vertebrae of a label map on this CT (``carmreg.logic.geometry.vertebrae``)."""
        from carmreg.logic.geometry.vertebrae import (
            CARMREG_VERTEBRAE,
            TOTALSEGMENTATOR_V2_VERTEBRAE,
            centroids_from_labels,
        )
        from carmreg.logic.io.volumes import load_volume

        labels_volume = load_volume(label_map_path)
        labels = np.rint(np.asarray(labels_volume.hu, np.float32)).astype(np.int32)
        convention = CARMREG_VERTEBRAE if labels.max() <= max(CARMREG_VERTEBRAE) else TOTALSEGMENTATOR_V2_VERTEBRAE
        marks = centroids_from_labels(labels, labels_volume.ijk_to_lps, convention, source=str(label_map_path))
        if mode == "add":
            have = set(self.ct_store.labels())
            existing = [(p.label, p.position) for p in self.ct_store.points()]
            new = [(lb, p) for lb, p in zip(marks.labels, marks.points_lps_mm, strict=True) if lb not in have]
            merged = existing + new
            self.ct_store.replace_all([m[0] for m in merged], [m[1] for m in merged], "Add proposed centroids")
        else:
            self.ct_store.replace_all(marks.labels, marks.points_lps_mm, "Propose centroids from label map")
        return list(marks.labels)

    def set_place_mode(self, on: bool) -> None:
        for panel in (self.ct_panel, self.xray_panel):
            panel.place_check.setChecked(bool(on))
        self.act_place.setChecked(bool(on))

    def set_ct_window(self, name: str) -> None:
        for view in self.slice_views:
            view.set_window_preset(name)

    def _landmarks_changed(self) -> None:
        self._points3d_timer.start()
        self._check_spine_order()
        self._inputs_changed(reset_overlay=False)
        if self.result is not None:
            self.overlay_view.clicks = self.shown_clicks()
            self.overlay_view.refresh_markers()
        self._update_accept_names()

    def _check_spine_order(self) -> None:
        """Warn (not refuse) when the named points break the spine's order or spacing
        (``io.landmarks.spine_order_warnings``): an "L2" placed above L1, a point in the wrong organ."""
        from carmreg.logic.io.landmarks import spine_order_warnings

        ct = self.ct_store.to_landmarks()
        ct_notes = spine_order_warnings(ct) if len(ct.labels) >= 2 else []
        xray = self.xray_store.to_landmarks()
        named = [lb for lb in xray.labels if lb]
        both = spine_order_warnings(ct, xray) if len(named) >= 2 and len(ct.labels) >= 2 else ct_notes
        self.ct_panel.set_warnings(ct_notes)
        self.xray_panel.set_warnings([w for w in both if w not in ct_notes])

    def _ct_selected(self, point_id) -> None:
        point = self.ct_store.get(point_id) if point_id is not None else None
        if point is not None:
            self._go_to(point.position)
        self._points3d_timer.start()

    def _go_to(self, lps) -> None:
        for view in self.slice_views:
            view.go_to(lps)

    def _update_3d_points(self) -> None:
        points = [(p.label, p.position) for p in self.ct_store.points() if p.label]
        sel = self.ct_store.get(self.ct_store.selected) if self.ct_store.selected else None
        self.view3d.set_points(points, sel.label if sel else None)


class _TurnXray(QtGui.QUndoCommand):
    """The X-ray shown turned from one orientation to another, its points with it (``_apply_orientation``)."""

    def __init__(self, window, old: str, new: str):
        super().__init__(f"Show the X-ray {new.replace('-', ' ')}")
        self.window, self.old, self.new, self.path = window, old, new, window.xray_path

    def redo(self):
        self._turn(self.new)

    def undo(self):
        self._turn(self.old)

    def _turn(self, name: str) -> None:
        """Turn the X-ray this step turned; another X-ray file loaded since makes the step obsolete (nothing done)."""
        if self.window.xray_as_stored is None or self.window.xray_path != self.path:
            self.setObsolete(True)
            return
        self.window._apply_orientation(name)


def _geometry_kwargs(overrides: dict) -> dict:
    """The override fields ``load_xray`` takes (presets and bookkeeping keys left out)."""
    out = {}
    for name in session_io.GEOMETRY_FIELDS:
        value = overrides.get(name)
        if value is not None:
            out[name] = tuple(float(x) for x in value) if isinstance(value, (list, tuple)) else float(value)
    return out
