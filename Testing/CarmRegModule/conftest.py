"""Fixtures for the GUI tests: a Qt application (skipped cleanly when Qt cannot start), a synthetic spine case
written to files, and a CarmReg window with scripted dialogs and a private autosave folder.

Plain-Qt tests run on the offscreen platform when there is no display; under ``xvfb-run`` they use the
virtual display, and the interactive 3D view tests run too.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from gui_case import FAST_PARAMETERS, LEVELS, TRUE_POSE, SyntheticCase, make_volume

GUI_TIMEOUT_S = 60


def _qt_can_start() -> bool:
    """Probe Qt in a child process: a missing platform plugin aborts the process, not just raises."""
    code = "from qtpy import QtWidgets; app = QtWidgets.QApplication([]); w = QtWidgets.QLabel('x'); w.show()"
    try:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=GUI_TIMEOUT_S,
                              env=os.environ.copy()).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.fixture(scope="session")
def qapp():
    try:
        import qtpy  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - no Qt binding at all
        pytest.skip(f"Qt is not available: {exc}")
    if os.environ.get("DISPLAY") and os.environ.get("QT_QPA_PLATFORM") is None and not _qt_can_start():
        os.environ["QT_QPA_PLATFORM"] = "offscreen"  # the display is unusable: plain Qt still works
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    if not _qt_can_start():
        pytest.skip("Qt cannot start on this machine")
    from carmreg.qt_common import ensure_app
    return ensure_app()


@pytest.fixture(scope="session")
def synthetic_case(tmp_path_factory) -> SyntheticCase:
    from carmreg.logic.drr.cpu import render_line_integrals
    from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
    from carmreg.logic.geometry.volume import MuPyramid
    from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, write_landmarks_2d, write_landmarks_3d
    from carmreg.logic.io.volumes import write_volume_nrrd
    from carmreg.logic.io.xray import write_png16, write_xray_dicom

    folder = tmp_path_factory.mktemp("synthetic_case")
    volume, centres = make_volume()
    intr = CarmIntrinsics(1000.0, (0.9, 0.9), (256, 256))
    geometry = CarmGeometry(intr, tuple(volume.center_lps_mm()), 600.0)
    pose = CarmPose(*TRUE_POSE)
    line = render_line_integrals(MuPyramid(volume).level(None), geometry, pose)
    intensity = np.exp(-line)  # bone dark, like fluoroscopy
    pixels = np.round(200 + 3800 * intensity / intensity.max()).astype(np.uint16)
    uv = project(geometry.projection_matrix(pose), centres)
    paths = SyntheticCase(
        ct_path=write_volume_nrrd(folder / "ct.nrrd", volume),
        xray_path=write_xray_dicom(folder / "xray.dcm", pixels, intr, sod_mm=600.0),
        png_path=write_png16(folder / "xray.png", pixels),
        ct_landmarks_path=write_landmarks_3d(folder / "ct.mrk.json", Landmarks3D(list(LEVELS), centres)),
        xray_landmarks_path=write_landmarks_2d(folder / "xray.mrk.json",
                                               Landmarks2D(list(LEVELS[1:4]), uv[1:4]), (0.9, 0.9)),
        centroids_lps_mm=centres, uv_px=uv, labels=LEVELS, sdd_mm=1000.0, pixel_spacing_mm=0.9,
        size_px=(256, 256))
    return paths




@pytest.fixture()
def window(qapp, tmp_path):
    """A CarmReg window: scripted dialogs, autosave into tmp_path/state, no 3D (plain Qt)."""
    from carmreg.main_window import CarmRegWidget
    from carmreg.qt_common import ScriptedDialogs, process_events

    win = CarmRegWidget(dialogs=ScriptedDialogs(), autosave=True, state_folder=tmp_path / "state",
                        view3d_mode="message")
    win.parameter_overrides = dict(FAST_PARAMETERS)
    win.resize(1400, 900)
    win.show()
    process_events(20)
    yield win
    win.discard_and_close()
    process_events()


@pytest.fixture()
def xray_window(window):
    """The window with a 400 x 300 px in-memory X-ray (geometry known) on the X-ray step."""
    from gui_helpers import ready

    from carmreg.logic.geometry.camera import CarmIntrinsics
    from carmreg.logic.io.xray import XrayImage

    rows, cols = 300, 400
    pixels = np.add.outer(np.arange(rows), np.arange(cols)).astype(np.float32)
    xray = XrayImage(pixels, CarmIntrinsics(1000.0, (0.3, 0.3), (cols, rows)), 600.0, True, "", {})
    window.set_xray_image(xray)
    window.set_step(2)
    ready(window.xray_view)
    return window
