"""The desktop application in the shape of a 3D Slicer scripted module: Module / Widget / Logic / Test.

(The genuine 3D Slicer module is ``CarmReg.py`` at the repository top; this file is the PySide6 application's.)

- ``CarmReg``: the module's description (title, category, help, acknowledgement);
- ``CarmRegWidget``: the desktop window (``main_window``); it calls the logic and turns its errors into dialogs;
- ``CarmRegLogic``: the headless registration (``carmreg.logic.registration.pipeline``), usable without Qt;
- ``CarmRegTest``: a self-test that drives the logic on the embedded sample case.
"""

from __future__ import annotations

import unittest

from . import about
from .main_window import CarmRegWidget

__all__ = ["CarmReg", "CarmRegWidget", "CarmRegTest"]  # and CarmRegLogic, imported lazily


class CarmReg:
    """Module description of the desktop application (the 3D Slicer module is ``CarmReg.py`` at the repository
    top: its ``ScriptedLoadableModule`` sets the same texts, from ``carmreg.about``, on ``self.parent``)."""

    title = about.TITLE
    categories = list(about.CATEGORIES)
    dependencies: list[str] = []
    contributors = list(about.CONTRIBUTORS)
    helpText = about.HELP_TEXT  # noqa: N815 - Slicer's name
    acknowledgementText = about.ACKNOWLEDGEMENT_TEXT  # noqa: N815 - Slicer's name


def __getattr__(name):
    if name == "CarmRegLogic":
        from carmreg.logic.registration.pipeline import CarmRegLogic
        return CarmRegLogic
    raise AttributeError(name)


class CarmRegTest(unittest.TestCase):
    """Self-test on the sample case: the logic registers it and every fitted level is within 5 mm PDE."""

    def runTest(self):  # noqa: N802 - Slicer's name
        self.test_sample_case()

    def test_sample_case(self):
        from carmreg.logic.io.landmarks import read_landmarks_2d, read_landmarks_3d
        from carmreg.logic.io.volumes import load_volume
        from carmreg.logic.io.xray import load_xray
        from carmreg.logic.registration.pipeline import CarmRegLogic
        from carmreg.logic.resources import sample_case

        paths = sample_case()
        result = CarmRegLogic().register(load_volume(paths["ct"]), read_landmarks_3d(paths["ct_landmarks"]),
                                         load_xray(paths["xray"]), read_landmarks_2d(paths["xray_landmarks"]))
        self.assertTrue(result.ok, result.warnings)
        fitted = [lv["pde_mm"] for lv in result.levels if lv["fitted"]]
        self.assertGreaterEqual(len(fitted), 3)
        self.assertLess(max(fitted), 5.0)
