"""The front door ``run_gui``: opens the window with the files given on the command line and returns the exit
code; the module shape (Module / Widget / Logic / Test) is importable."""

import pytest
from qtpy import QtCore, QtWidgets

pytestmark = pytest.mark.gui


def test_run_gui_loads_command_line_files_and_returns_the_exit_code(qapp, synthetic_case, tmp_path, monkeypatch):
    from carmreg import app
    from carmreg.main_window import CarmRegWidget

    monkeypatch.setenv("CARMREG_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("CARMREG_NO_VTK", "1")  # keep it fast: no 3D
    seen = {}

    def close_when_loaded(tries=[0]):  # noqa: B006 - a counter shared by the re-armed timer
        tries[0] += 1
        windows = [w for w in QtWidgets.QApplication.topLevelWidgets()
                   if isinstance(w, CarmRegWidget) and w.isVisible()]
        win = windows[-1] if windows else None
        if win is not None and (len(win.xray_store) == 3 or tries[0] > 100):
            seen.update(ct=win.ct_store.labels(), xray=win.xray_store.labels(), title=win.windowTitle(),
                        sdd=win.xray.intrinsics.sdd_mm if win.xray else None)
            win.discard_and_close()
            QtWidgets.QApplication.instance().exit(0)
        else:
            QtCore.QTimer.singleShot(100, close_when_loaded)

    QtCore.QTimer.singleShot(100, close_when_loaded)
    code = app.run_gui(ct=str(synthetic_case.ct_path), xray=str(synthetic_case.xray_path),
                       ct_landmarks=str(synthetic_case.ct_landmarks_path),
                       xray_landmarks=str(synthetic_case.xray_landmarks_path))
    assert code == 0
    assert seen["ct"] == list(synthetic_case.labels)
    assert seen["xray"] == ["T12", "L1", "L2"]
    assert seen["sdd"] == 1000.0
    assert seen["title"].startswith("CarmReg - untitled session")


def test_module_shape_matches_a_slicer_scripted_module(qapp):
    from carmreg import CarmReg

    assert CarmReg.CarmReg.title == "CarmReg" and "Registration" in CarmReg.CarmReg.categories
    assert CarmReg.CarmRegWidget.__name__ == "CarmRegWidget"
    from carmreg.logic.registration.pipeline import CarmRegLogic
    assert CarmReg.CarmRegLogic is CarmRegLogic
    assert hasattr(CarmReg.CarmRegTest, "runTest")
