"""CarmReg as a 3D Slicer scripted module: ``CarmReg`` (ScriptedLoadableModule), ``CarmRegWidget``,
``CarmRegLogic``, ``CarmRegTest``, in the shape of Slicer's template (Utilities/Templates/Modules/Scripted).

Where Slicer finds it
---------------------
Slicer takes every ``*.py`` at the top of a module path for a module, and imports it as a *top-level* module (no
relative imports here). This file is the only ``*.py`` at the top of the repository, so the repository folder is
the module folder: add it to Edit > Application Settings > Modules > Additional module paths, or build the
extension (``CMakeLists.txt``), which installs this file with ``CarmRegModule/``, ``Logic/`` and ``Resources/``
beside it. Its icon is ``Resources/Icons/CarmReg.png`` (found by ScriptedLoadableModule).

How ``carmreg`` becomes importable inside Slicer
------------------------------------------------
``import_carmreg()`` loads the packages from the folders beside this file with the mapping of pyproject.toml
(``carmreg`` = CarmRegModule/, ``carmreg.logic`` = Logic/, ``carmreg.resources`` = Resources/), so Slicer runs
the code this module ships with; nothing is pip-installed for CarmReg itself. The Python packages Slicer lacks
(numba, nibabel, ...: ``Resources/requirements.txt``, pyproject's list without vtk) are installed on first
use with ``slicer.packaging.pip_ensure`` (``slicer.util.pip_install`` on Slicer versions without it); never vtk
or a Qt binding. The registration runs in ``carmreg.logic`` (no Qt); the desktop application (PySide6) is not
used inside Slicer.

What lives where
----------------
The conversions between MRML nodes and CarmReg's objects live in ``carmreg.slicer_nodes`` (``slicer_nodes()``
imports it): VTK and numpy only, so the tests run them against ``slicer-core``'s real MRML nodes outside Slicer.
This file keeps the import set-up, the Python dependencies and the Slicer classes. The classes need Slicer's
application (``slicer.ScriptedLoadableModule``, qt, ctk): imported elsewhere, their bases are ``_NeedsSlicer``,
which refuses to be instantiated.

Frames: Slicer's world is RAS; CarmReg's is the CT's LPS (RAS = diag(-1, -1, 1) LPS). The X-ray volume's voxel
(i, j, 0) is detector pixel (u, v) = (column, row); the DRR, the overlay and the projected levels are laid on the
X-ray volume's grid (so they line up with it in the slice views), the C-arm transform maps the camera frame to
the CT's RAS (its translation is the X-ray source).
"""

import importlib.util
import os
import sys

MODULE_DIR = os.path.dirname(os.path.abspath(__file__))
PACKAGE_DIRS = {"carmreg": "CarmRegModule", "carmreg.logic": "Logic", "carmreg.resources": "Resources"}
"""pyproject.toml's [tool.setuptools.package-dir]: the import root over the design's top-level folders."""
FORBIDDEN_IN_SLICER = ("vtk", "pyside6", "pyside6-essentials", "pyqt5", "pyqt6", "qtpy")

try:
    from slicer.ScriptedLoadableModule import (
        ScriptedLoadableModule,
        ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest,
        ScriptedLoadableModuleWidget,
    )

    IN_SLICER = True
except ImportError:  # outside 3D Slicer (tests, documentation; slicer-core has no ScriptedLoadableModule)
    IN_SLICER = False

    class _NeedsSlicer:
        """Base of the module's classes outside 3D Slicer: they can be inspected, not run."""

        def __init__(self, *args, **kwargs):
            raise RuntimeError(f"{type(self).__name__} runs inside 3D Slicer only; outside it use the carmreg "
                               "command line or desktop application")

    ScriptedLoadableModule = ScriptedLoadableModuleWidget = ScriptedLoadableModuleLogic = _NeedsSlicer
    ScriptedLoadableModuleTest = _NeedsSlicer


# ------------------------------------------------------------------------------------------ import and set-up

def import_carmreg(root=MODULE_DIR):
    """Make ``carmreg`` importable from the folders beside this file (PACKAGE_DIRS) and return it.

    Keeps an already imported ``carmreg`` (e.g. pip-installed and imported first). The three package modules
    are registered before any of them runs, so their imports of each other resolve.
    """
    if "carmreg" in sys.modules:
        return sys.modules["carmreg"]
    modules = []
    for name, folder in PACKAGE_DIRS.items():
        path = os.path.join(root, folder)
        spec = importlib.util.spec_from_file_location(name, os.path.join(path, "__init__.py"),
                                                      submodule_search_locations=[path])
        if spec is None or not os.path.isfile(spec.origin):
            raise ImportError(f"CarmReg: {path} is missing from the module folder {root}; reinstall the module")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        parent, _, child = name.rpartition(".")
        if parent:
            setattr(sys.modules[parent], child, module)
        modules.append((spec, module))
    for spec, module in modules:
        spec.loader.exec_module(module)
    return sys.modules["carmreg"]


def slicer_nodes():
    """``carmreg.slicer_nodes`` (MRML nodes <-> CarmReg's objects), with ``carmreg`` imported from beside this file."""
    import_carmreg()
    import carmreg.slicer_nodes

    return carmreg.slicer_nodes


def xray_settings():
    """``carmreg.xray_settings`` (the X-ray settings' keys and words, as the window shows them)."""
    import_carmreg()
    import carmreg.xray_settings

    return carmreg.xray_settings


def read_requirements(path):
    """Requirement lines of a requirements.txt (no comments, blanks or pip options)."""
    with open(path, encoding="utf-8") as f:
        lines = (line.split("#", 1)[0].strip() for line in f)
        return [line for line in lines if line and not line.startswith("-")]


def requirement_name(requirement):
    """The distribution name of a requirement line ("pylibjpeg-libjpeg>=2.1" -> "pylibjpeg-libjpeg")."""
    for i, ch in enumerate(requirement):
        if ch in "<>=!~;[ (":
            return requirement[:i].strip()
    return requirement.strip()


def missing_requirements(requirements):
    """The requirements whose distribution is not installed (version bounds are pip_ensure's business)."""
    from importlib import metadata

    missing = []
    for requirement in requirements:
        try:
            metadata.version(requirement_name(requirement))
        except metadata.PackageNotFoundError:
            missing.append(requirement)
    return missing


def ensure_python_dependencies(requirements_path=None):
    """Inside Slicer: install the packages of ``Resources/requirements.txt`` that are missing (asks first)."""
    import slicer

    path = requirements_path or os.path.join(MODULE_DIR, "Resources", "requirements.txt")
    requirements = read_requirements(path)
    forbidden = [r for r in requirements if requirement_name(r).lower() in FORBIDDEN_IN_SLICER]
    if forbidden:
        raise RuntimeError(f"CarmReg: {path} lists {', '.join(forbidden)}; Slicer's own VTK and Qt must never "
                           "be replaced: remove them from the file")
    try:
        import slicer.packaging as packaging
    except ImportError:
        packaging = None
    if packaging is not None and hasattr(packaging, "pip_ensure"):
        packaging.pip_ensure(requirements, requester="CarmReg", skip_in_testing=False)
        return
    missing = missing_requirements(requirements)
    if missing:
        slicer.util.pip_install(" ".join(f'"{r}"' for r in missing))



# ------------------------------------------------------------------------------------------ the Slicer module

class CarmReg(ScriptedLoadableModule):
    """Module description (texts from ``carmreg.about``, shared with the desktop application)."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        import_carmreg()
        about = importlib.import_module("carmreg.about")
        self.parent.title = about.TITLE
        self.parent.categories = list(about.CATEGORIES)
        self.parent.dependencies = []
        self.parent.contributors = list(about.CONTRIBUTORS)
        self.parent.helpText = about.HELP_TEXT
        self.parent.acknowledgementText = about.ACKNOWLEDGEMENT_TEXT


class CarmRegWidget(ScriptedLoadableModuleWidget):
    """The panel: inputs (CT, CT points, X-ray, X-ray clicks), C-arm geometry, registration, outputs. State lives
    in the parameter node; errors become a dialog (``slicer.util.tryWithErrorDisplay``)."""

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        self.logic = None
        self._parameterNode = None
        self._observer = None
        self._updating = False

    def setup(self):
        ScriptedLoadableModuleWidget.setup(self)
        self.logic = CarmRegLogic()
        self.ui = self._build_panel()
        import slicer

        self._scene_observers = [slicer.mrmlScene.AddObserver(slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)]
        self.setParameterNode(self.logic.getParameterNode())

    def _node_selector(self, form, role, label, none_enabled=True, add_enabled=False):
        import slicer

        selector = slicer.qMRMLNodeComboBox()
        selector.nodeTypes = [slicer_nodes().NODE_ROLES[role]]
        selector.noneEnabled, selector.addEnabled, selector.removeEnabled = none_enabled, add_enabled, False
        selector.renameEnabled = add_enabled
        selector.setMRMLScene(slicer.mrmlScene)
        selector.connect("currentNodeChanged(vtkMRMLNode*)", self.updateParameterNodeFromGUI)
        form.addRow(label, selector)
        return selector

    def _spin_box(self, form, label, suffix, maximum, tooltip, minimum=0.0):
        import ctk

        box = ctk.ctkDoubleSpinBox()
        box.decimals, box.minimum, box.maximum, box.suffix = 3, minimum, maximum, suffix
        box.toolTip = tooltip
        box.connect("valueChanged(double)", self.updateParameterNodeFromGUI)
        form.addRow(label, box)
        return box

    def _build_panel(self):
        import ctk
        import qt

        ui = type("Panel", (), {})()
        sections = {}
        for key, title in (("inputs", "Inputs"), ("geometry", "C-arm geometry"), ("register", "Registration"),
                           ("outputs", "Outputs")):
            button = ctk.ctkCollapsibleButton()
            button.text = title
            self.layout.addWidget(button)
            sections[key] = qt.QFormLayout(button)
        form = sections["inputs"]
        ui.loadSample = qt.QPushButton("Load the sample case")
        ui.loadSample.toolTip = "CT, CT centroids, simulated X-ray and its clicks shipped with CarmReg"
        form.addRow(ui.loadSample)
        ui.ct = self._node_selector(form, "CT", "CT volume:")
        ui.ctPoints = self._node_selector(form, "CTPoints", "CT centroids:")
        ui.xray = self._node_selector(form, "Xray", "X-ray:")
        ui.xrayPoints = self._node_selector(form, "XrayPoints", "X-ray clicks (optional):")
        ui.orientation = qt.QComboBox()
        for name in slicer_nodes().ORIENTATIONS:
            ui.orientation.addItem(f"shown {name.replace('-', ' ')}", name)
        ui.orientation.toolTip = ("How the X-ray volume is turned before registering (its clicks with it; the "
                                  "outputs come back onto the volume as stored). Leave it as stored unless CarmReg "
                                  "refuses the image as mirrored or rotated and names the turn")
        ui.orientation.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        form.addRow("X-ray orientation:", ui.orientation)
        form = sections["geometry"]
        ui.sdd = self._spin_box(form, "Source to detector:", " mm", 3000.0, "0 = from the DICOM file or 1000 mm")
        ui.spacing = self._spin_box(form, "Detector pixel spacing:", " mm", 10.0, "0 = from the file / volume")
        ui.sod = self._spin_box(form, "Source to isocentre:", " mm", 3000.0, "0 = from the DICOM file or 0.6 SDD")
        ui.distortion = self._spin_box(form, "Pincushion at 100 mm:", " mm", 10.0, "An image intensifier's "
                                       "distortion from the C-arm's calibration: how far an image point 100 mm from "
                                       "the centre lies outward of a pinhole camera's. 0 = none (flat panel)", -10.0)
        ui.grid = self._node_selector(form, "GridXray", "Bead-grid X-ray (optional):")
        ui.grid.toolTip = ("An X-ray of a square bead grid at this intensifier's input, same field size and "
                           "orientation: Measure sets the Pincushion from it")
        ui.measure = qt.QPushButton("Measure the pincushion on the bead-grid X-ray")
        form.addRow(ui.measure)
        form = sections["register"]
        ui.metric = qt.QComboBox()
        ui.metric.addItems(list(slicer_nodes().METRICS))
        ui.metric.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        form.addRow("Similarity metric:", ui.metric)
        ui.polarity = qt.QComboBox()
        for key, words in xray_settings().POLARITY_CHOICES:
            ui.polarity.addItem(words, key)
        ui.polarity.toolTip = ("How the X-ray shows bone. CarmReg finds it from the image against the CT and says "
                               "how clearly; set it only to override")
        ui.polarity.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        form.addRow("X-ray polarity:", ui.polarity)
        ui.storage = qt.QComboBox()
        for key, words in xray_settings().STORAGE_CHOICES:
            ui.storage.addItem(words, key)
        ui.storage.toolTip = ("How a bone-dark X-ray stores its values (linear intensity: the detector's own; log "
                              "display: processed). CarmReg takes what the DICOM states, else finds it from the image; "
                              "set it only to override")
        ui.storage.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        form.addRow("X-ray storage:", ui.storage)
        ui.field = qt.QComboBox()
        for key, words in xray_settings().FIELD_CHOICES:
            ui.field.addItem(words, key)
        ui.field.toolTip = ("Where the beam reached the detector. CarmReg finds the exposed field (the collimator's "
                            "or intensifier's shadow left out); choose the whole image when it leaves out anatomy")
        ui.field.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        form.addRow("X-ray field:", ui.field)
        ui.checkLevels = qt.QCheckBox("Check which vertebra is which")
        ui.checkLevels.connect("toggled(bool)", self.updateParameterNodeFromGUI)
        form.addRow(ui.checkLevels)
        ui.estimatePincushion = qt.QCheckBox("Estimate an intensifier's pincushion from the image")
        ui.estimatePincushion.toolTip = ("On a round field with no Pincushion given, the image refinement estimates "
                                         "it; unchecked: a pinhole camera (a flat panel, an image already corrected)")
        ui.estimatePincushion.connect("toggled(bool)", self.updateParameterNodeFromGUI)
        form.addRow(ui.estimatePincushion)
        ui.apply = qt.QPushButton("Register")
        ui.cancel = qt.QPushButton("Cancel")
        ui.progress = qt.QProgressBar()
        form.addRow(ui.apply)
        form.addRow(ui.progress, ui.cancel)
        ui.summary = qt.QLabel("")
        ui.summary.wordWrap = True
        form.addRow(ui.summary)
        form = sections["outputs"]
        ui.carm = self._node_selector(form, "CarmTransform", "C-arm transform:", add_enabled=True)
        ui.drr = self._node_selector(form, "DRR", "DRR volume:", add_enabled=True)
        ui.overlay = self._node_selector(form, "Overlay", "Overlay volume:", add_enabled=True)
        ui.levels = self._node_selector(form, "ProjectedLevels", "Projected levels:", add_enabled=True)
        ui.export = qt.QPushButton("Save result files and Slicer scene...")
        form.addRow(ui.export)
        self.layout.addStretch(1)
        ui.loadSample.connect("clicked(bool)", self.onLoadSample)
        ui.apply.connect("clicked(bool)", self.onApplyButton)
        ui.cancel.connect("clicked(bool)", lambda checked=False: self.logic.cancel())
        ui.export.connect("clicked(bool)", self.onExport)
        ui.measure.connect("clicked(bool)", self.onMeasureDistortion)
        return ui

    # parameter node <-> GUI
    def setParameterNode(self, node):
        import vtk

        if self._parameterNode is not None and self._observer is not None:
            self._parameterNode.RemoveObserver(self._observer)
        self._parameterNode, self._observer = node, None
        if node is not None:
            slicer_nodes().set_default_parameters(node)
            self._observer = node.AddObserver(vtk.vtkCommand.ModifiedEvent, self.updateGUIFromParameterNode)
        self.updateGUIFromParameterNode()

    def _selectors(self):
        ui = self.ui
        return {"CT": ui.ct, "CTPoints": ui.ctPoints, "Xray": ui.xray, "XrayPoints": ui.xrayPoints,
                "CarmTransform": ui.carm, "DRR": ui.drr, "Overlay": ui.overlay, "ProjectedLevels": ui.levels,
                "GridXray": ui.grid}

    def updateGUIFromParameterNode(self, caller=None, event=None):
        node = self._parameterNode
        if node is None or self._updating:
            return
        self._updating = True
        try:
            for role, selector in self._selectors().items():
                selector.setCurrentNode(node.GetNodeReference(role))
            self.ui.sdd.value = float(node.GetParameter("SddMm") or 0)
            self.ui.spacing.value = float(node.GetParameter("PixelSpacingMm") or 0)
            self.ui.sod.value = float(node.GetParameter("SodMm") or 0)
            self.ui.distortion.value = float(node.GetParameter("DistortionMm") or 0)
            self.ui.metric.setCurrentText(node.GetParameter("Metric") or "gc")
            for combo, name, default in ((self.ui.polarity, "Polarity", "auto"), (self.ui.storage, "Storage", "auto"),
                                         (self.ui.field, "Field", "auto"),
                                         (self.ui.orientation, "XrayOrientation", "as-stored")):
                combo.setCurrentIndex(max(combo.findData(node.GetParameter(name) or default), 0))
            self.ui.checkLevels.checked = node.GetParameter("CheckLevels") != "false"
            self.ui.estimatePincushion.checked = node.GetParameter("EstimatePincushion") != "false"
            ready = all(node.GetNodeReference(r) for r in ("CT", "CTPoints", "Xray"))
            self.ui.apply.enabled = ready
            self.ui.apply.toolTip = "Register the CT to the X-ray" if ready else "Select CT, CT centroids and X-ray"
        finally:
            self._updating = False

    def updateParameterNodeFromGUI(self, *args):
        node = self._parameterNode
        if node is None or self._updating:
            return
        was_modified = node.StartModify()
        for role, selector in self._selectors().items():
            node.SetNodeReferenceID(role, selector.currentNodeID)
        node.SetParameter("SddMm", f"{self.ui.sdd.value:g}")
        node.SetParameter("PixelSpacingMm", f"{self.ui.spacing.value:g}")
        node.SetParameter("SodMm", f"{self.ui.sod.value:g}")
        node.SetParameter("DistortionMm", f"{self.ui.distortion.value:g}")
        node.SetParameter("Metric", self.ui.metric.currentText)
        for combo, name in ((self.ui.polarity, "Polarity"), (self.ui.storage, "Storage"), (self.ui.field, "Field"),
                            (self.ui.orientation, "XrayOrientation")):
            node.SetParameter(name, combo.itemData(combo.currentIndex))
        node.SetParameter("CheckLevels", "true" if self.ui.checkLevels.checked else "false")
        node.SetParameter("EstimatePincushion", "true" if self.ui.estimatePincushion.checked else "false")
        node.EndModify(was_modified)

    def enter(self):
        self.setParameterNode(self.logic.getParameterNode())

    def exit(self):
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.setParameterNode(self.logic.getParameterNode())

    def cleanup(self):
        import slicer

        self.setParameterNode(None)
        for tag in getattr(self, "_scene_observers", []):
            slicer.mrmlScene.RemoveObserver(tag)

    # actions
    def onLoadSample(self):
        import slicer

        with slicer.util.tryWithErrorDisplay("Failed to load the sample case.", waitCursor=True):
            self.logic.loadSampleCase(self._parameterNode)

    def onApplyButton(self):
        import slicer

        with slicer.util.tryWithErrorDisplay("Registration failed.", waitCursor=True):
            def progress(stage, fraction, message=""):
                self.ui.progress.value = int(100 * fraction)
                self.ui.progress.format = f"{stage}: %p%"
                slicer.app.processEvents()

            self.logic.progress = progress
            result = self.logic.process(self._parameterNode)
            self.ui.summary.text = slicer_nodes().result_summary(result)
            slicer.util.setSliceViewerLayers(background=self._parameterNode.GetNodeReference("Xray"),
                                             foreground=self._parameterNode.GetNodeReference("DRR"),
                                             foregroundOpacity=0.5, fit=True)

    def onMeasureDistortion(self):
        import slicer

        with slicer.util.tryWithErrorDisplay("Measuring the pincushion failed.", waitCursor=True):
            calibration = slicer_nodes().measure_distortion(self._parameterNode)
            slicer.util.infoDisplay(f"{calibration.summary()}: it is now the Pincushion at 100 mm.")

    def onExport(self):
        import qt
        import slicer

        folder = qt.QFileDialog.getExistingDirectory(self.parent, "Folder for the result files")
        if folder:
            with slicer.util.tryWithErrorDisplay("Saving the result failed.", waitCursor=True):
                paths = self.logic.saveResult(folder)
                slicer.util.infoDisplay(f"Wrote {len(paths)} files to {folder}; the Slicer scene is "
                                        f"{paths.get('slicer_scene')}")


class CarmRegLogic(ScriptedLoadableModuleLogic):
    """Registration on MRML nodes through ``carmreg.logic`` (no Qt): ``process(parameterNode)``; progress and
    cancel are attributes, as in SlicerElastix."""

    def __init__(self):
        ScriptedLoadableModuleLogic.__init__(self)
        self.progress = None
        self._pipeline = None
        self.last = None  # (result, ct, ct_landmarks, xray) of the last registration

    def cancel(self):
        if self._pipeline is not None:
            self._pipeline.cancel()

    def getParameterNode(self):
        node = ScriptedLoadableModuleLogic.getParameterNode(self)
        slicer_nodes().set_default_parameters(node)
        return node

    def loadSampleCase(self, parameterNode=None):
        """Load CarmReg's sample case as MRML nodes and select them; returns {role: node}."""
        import slicer

        ensure_python_dependencies()
        import_carmreg()
        from carmreg.logic.resources import sample_case

        paths = sample_case()
        nodes = {"CT": slicer.util.loadVolume(str(paths["ct"]), {"name": "CT"}),
                 "CTPoints": slicer.util.loadMarkups(str(paths["ct_landmarks"])),
                 "Xray": slicer.util.loadVolume(str(paths["xray"]), {"name": "X-ray", "singleFile": True}),
                 "XrayPoints": None}
        nodes["XrayPoints"] = self._clicks_on_volume(paths["xray_landmarks"], nodes["Xray"])
        parameterNode = parameterNode or self.getParameterNode()
        for role, node in nodes.items():
            parameterNode.SetNodeReferenceID(role, node.GetID())
        return nodes

    @staticmethod
    def _clicks_on_volume(path, xray_node):
        """X-ray clicks of a CarmReg .mrk.json placed on the X-ray volume (RAS of voxel (u, v, 0))."""
        import numpy as np
        import slicer

        from carmreg.logic.io.landmarks import read_landmarks_2d

        clicks = read_landmarks_2d(path)
        node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "X-ray clicks")
        matrix = slicer_nodes().ijk_to_ras(xray_node)
        for label, (u, v) in zip(clicks.labels, clicks.uv_px, strict=True):
            ras = (matrix @ np.array([u, v, 0.0, 1.0]))[:3]
            node.AddControlPoint(float(ras[0]), float(ras[1]), float(ras[2]), label or "")
        return node

    def process(self, parameterNode):
        """Register (installing missing Python packages first), show the result in the output nodes; returns
        CarmReg's RegistrationResult."""
        import slicer

        ensure_python_dependencies()
        import_carmreg()
        from carmreg.logic.registration import pipeline

        self._pipeline = pipeline.CarmRegLogic(progress=self.progress)
        try:
            self.last = slicer_nodes().register_nodes(parameterNode, self._pipeline)
        finally:
            self._pipeline = None
        slicer_nodes().show_result(slicer.mrmlScene, parameterNode, self.last[0], self.last[3])
        return self.last[0]

    def saveResult(self, folder):
        """CarmReg's result files and the Slicer scene (``slicer/CarmReg.mrml``) of the last registration."""
        if self.last is None:
            raise ValueError("CarmReg: there is no result to save yet; click Register first")
        from carmreg.logic.report.result_files import save_result

        result, ct, ct_landmarks, xray = self.last
        return save_result(result, folder, xray.pixels, None, ct=ct, ct_landmarks=ct_landmarks)


class CarmRegTest(ScriptedLoadableModuleTest):
    """Self-test (Slicer's SelfTests and ctest): the sample case loaded as MRML nodes, registered through the
    module's logic; every clicked level within 5 mm PDE, outputs in the scene."""

    def setUp(self):
        import slicer

        slicer.mrmlScene.Clear()

    def runTest(self):
        self.setUp()
        self.test_sample_case()

    def test_sample_case(self):
        self.delayDisplay("Loading the sample case")
        logic = CarmRegLogic()
        parameterNode = logic.getParameterNode()
        logic.loadSampleCase(parameterNode)
        result = logic.process(parameterNode)
        self.assertTrue(result.ok, result.warnings)
        pdes = [lv["pde_mm"] for lv in result.levels if lv.get("pde_mm") is not None]
        self.assertGreaterEqual(len(pdes), 3)
        self.assertLess(max(pdes), 5.0)
        for role in slicer_nodes().OUTPUT_NAMES:
            self.assertIsNotNone(parameterNode.GetNodeReference(role), role)
        self.assertEqual(parameterNode.GetNodeReference("ProjectedLevels").GetNumberOfControlPoints(),
                         len(result.levels))
        self.delayDisplay("Test passed")

