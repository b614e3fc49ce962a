"""Front doors of the desktop application: ``run_gui`` (interactive) and ``export_screenshots`` (headless).

The lead's CLI calls these for ``carmreg gui [...]`` and ``carmreg screenshot --out DIR``.
Without a display (no $DISPLAY on Linux) Qt runs on its offscreen platform; the 3D views then render through
VTK's offscreen (EGL/OSMesa) path or show a message, and everything else works the same.
"""

from __future__ import annotations

import logging
from pathlib import Path

from carmreg.logic.errors import CarmRegError, InputFileError

from .qt_common import ScriptedDialogs, ensure_app, process_events

LOG = logging.getLogger("carmreg.gui")
DEFAULT_VIEWS = ("window", "window_ct", "window_xray", "ct", "xray", "overlay", "3d")
WINDOW_STEPS = {"window": None, "window_data": 0, "window_ct": 1, "window_xray": 2, "window_register": 3,
                "window_check": 4}


def check_display() -> None:
    """Raise a CarmRegError (one line) unless a window can be shown: no display at all ($DISPLAY /
    $WAYLAND_DISPLAY unset), or Qt unable to start on it (a missing xcb/OpenGL system library aborts the
    process, so it is tried in a child process first)."""
    import os
    import subprocess
    import sys

    from .qt_common import headless

    if os.environ.get("QT_QPA_PLATFORM", "").startswith("offscreen"):
        raise CarmRegError("QT_QPA_PLATFORM=offscreen: the window would be invisible; unset it to open the "
                           "window, or use carmreg screenshot --out DIR for pictures without a display")
    if headless():
        raise CarmRegError("no display ($DISPLAY is not set): carmreg gui needs a desktop session (over SSH: "
                           "ssh -X; for tests: xvfb-run -a carmreg gui); carmreg screenshot --out DIR works "
                           "without one")
    code = "from qtpy import QtWidgets; QtWidgets.QApplication([])"
    try:
        probe = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CarmRegError(f"Qt could not be started to test the display ({exc})") from None
    if probe.returncode != 0:
        lines = [ln.strip() for ln in probe.stderr.splitlines() if ln.strip()]
        why = next((ln for ln in lines if "xcb" in ln or "plugin" in ln), lines[-1] if lines else "no message")
        raise CarmRegError(f"Qt cannot open a window on this display ({why[:160]}); install the system "
                           "libraries with scripts/install-system-deps.sh (Debian/Ubuntu, needs root)")


def run_gui(ct=None, xray=None, ct_landmarks=None, xray_landmarks=None, sample: bool = False,
            session=None, geometry: dict | None = None) -> int:
    """Open the CarmReg window, optionally with data; returns the application's exit code.

    ct / xray: paths of a CT (DICOM folder, NIfTI, NRRD, MetaImage) and an X-ray (DICOM, PNG, TIFF, JPEG);
    ct_landmarks / xray_landmarks: .mrk.json (or plain JSON) centroids; sample: load the embedded sample case;
    session: a saved session file (data, points and the last result); geometry: the X-ray's geometry
    overrides ({"sdd_mm": mm, "pixel_spacing_mm": (column, row) mm}) for a file that does not give it.
    Errors in these inputs are shown as dialogs; the window stays open. Call ``check_display`` first.
    """
    from .main_window import CarmRegWidget
    from .qt_signals import quit_window_on_signals

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    app = ensure_app(offscreen=False)
    window = CarmRegWidget()
    quit_window_on_signals(app, window)
    window.show()
    process_events()
    if not any((ct, xray, ct_landmarks, xray_landmarks, sample, session)):
        window.offer_recovery()
    if session:
        _load_steps(window, [(f"session {session}", lambda: window.open_session(session))])
    _load_inputs(window, ct, xray, ct_landmarks, xray_landmarks, sample, geometry)
    if window.quit_code is not None:  # a termination signal while loading (``qt_signals``)
        return window.quit_code
    return int(app.exec())


def _load_inputs(window, ct, xray, ct_landmarks, xray_landmarks, sample: bool, geometry: dict | None = None
                 ) -> None:
    steps = []
    if sample:
        steps.append(("sample case", window.load_sample_case))
    if ct:
        steps.append((f"CT {ct}", lambda: window.load_ct(ct)))
    if xray:
        steps.append((f"X-ray {xray}", lambda: window.load_xray(xray, dict(geometry or {}))))
    if ct_landmarks:
        steps.append((f"CT landmarks {ct_landmarks}", lambda: window.import_ct_landmarks(ct_landmarks, False)))
    if xray_landmarks:
        steps.append((f"X-ray landmarks {xray_landmarks}",
                      lambda: window.import_xray_landmarks(xray_landmarks, False)))
    _load_steps(window, steps)
    window.undo_stack.clear()


def _load_steps(window, steps) -> None:
    """Run (what, callable) loading steps; a failure is a dialog, the window stays."""
    for what, step in steps:
        try:
            step()
        except CarmRegError as exc:
            window.dialogs.error("CarmReg", str(exc))
        except Exception as exc:  # noqa: BLE001 - show, log, keep the window
            import traceback
            details = traceback.format_exc()
            LOG.error("loading %s failed\n%s", what, details)
            window.dialogs.error("CarmReg - unexpected error", f"Loading {what} failed: {exc}", details)


def export_screenshots(out_dir, sample: bool = True, views=DEFAULT_VIEWS, register: bool = True,
                       size=(1600, 1000), parameters: dict | None = None, inputs: dict | None = None,
                       session=None, notes: list | None = None) -> list[Path]:
    """Headless PNG screenshots of the window and its views; returns the written paths.

    views: any of "window" (the state after loading/registering), "window_data", "window_ct", "window_xray",
    "window_register", "window_check" (the whole window at that workflow step), "axial", "coronal",
    "sagittal", "ct" (the four CT views), "xray", "overlay", "3d", "result" (overlay + 3D with the C-arm).
    sample: load the embedded sample case first; inputs: {"ct", "xray", "ct_landmarks", "xray_landmarks": path,
    "geometry": the X-ray's geometry overrides} to load instead; session: a session file to open instead;
    register: run the registration when a view needs it (and the data allow it); parameters:
    RegistrationParameters fields to override (e.g. a smaller search range); notes: a list that receives, in
    words, why the views show no result when one was asked for.
    Files are named ``carmreg_<view>.png``. Raises CarmRegError on bad arguments or a failed load.
    """
    from .main_window import SCREENSHOT_VIEWS, CarmRegWidget

    unknown = [v for v in views if v not in SCREENSHOT_VIEWS and v not in WINDOW_STEPS]
    if unknown:
        raise InputFileError(f"unknown screenshot view(s) {', '.join(unknown)}; choose from "
                             f"{', '.join(list(WINDOW_STEPS) + [v for v in SCREENSHOT_VIEWS if v != 'window'])}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ensure_app()
    dialogs = ScriptedDialogs()
    window = CarmRegWidget(dialogs=dialogs, autosave=False)
    window.parameter_overrides = dict(parameters or {})
    window.resize(*size)
    window.show()
    process_events(50)
    try:
        if session:
            window.open_session(session)
        elif inputs:
            _load_inputs(window, inputs.get("ct"), inputs.get("xray"), inputs.get("ct_landmarks"),
                         inputs.get("xray_landmarks"), False, inputs.get("geometry"))
            failed = [m for m in dialogs.messages]
            if failed:
                raise InputFileError(failed[0][1])
        elif sample:
            window.load_sample_case()
        window.ct_store.select(None)
        _focus_first_point(window)
        wants_result = any(v in ("window", "window_register", "window_check", "overlay", "result") for v in views)
        loaded = sample or inputs or session
        said = notes if notes is not None else []
        if loaded and register and wants_result and not window.registration_panel.run_button.isEnabled():
            said.append(f"not registered, the views show no result: {window.registration_panel.ready_label.text()}")
        elif loaded and register and wants_result:
            window.run_registration(wait=True)
            errors = [m for m in dialogs.messages if "error" in m[0].lower() or "registration" in m[0].lower()]
            if errors:
                said.append(f"the registration failed, the views show no result: {errors[-1][1]}")
        paths = []
        for view in views:
            path = out / f"carmreg_{view}.png"
            if view in WINDOW_STEPS:
                step = WINDOW_STEPS[view]
                if step is not None:
                    window.set_step(step)
                process_events(100)
                paths.append(window.save_screenshot(path, "window"))
            else:
                process_events(50)
                paths.append(window.save_screenshot(path, view))
        return paths
    finally:
        window.discard_and_close()


def _focus_first_point(window) -> None:
    points = [p for p in window.ct_store.points() if p.label]
    if points:
        window._go_to(points[len(points) // 2].position)
