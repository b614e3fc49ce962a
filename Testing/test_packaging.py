"""The wheel's contents, from pyproject.toml, against the source tree: every package and every resource file is
listed, so a new subpackage or data file is never left out of ``pip install .`` (``.ci/run`` then builds the
wheel, installs it into a fresh environment and runs ``carmreg demo`` outside the checkout)."""

from __future__ import annotations

import fnmatch
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]
NOT_SHIPPED = {"Screenshots"}  # Resources/ folders for the README only
SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def _package_folders() -> dict[str, Path]:
    """{import name: folder} of every folder holding an __init__.py under the mapped top-level folders."""
    found = {}
    for root_name, folder in SETUPTOOLS["package-dir"].items():
        for init in (ROOT / folder).rglob("__init__.py"):
            relative = init.parent.relative_to(ROOT / folder)
            if "__pycache__" in relative.parts:
                continue
            name = ".".join([root_name, *relative.parts])
            found.setdefault(name, init.parent)
    return found


def test_every_package_folder_is_listed_in_pyproject_and_nothing_else():
    found = _package_folders()
    listed = set(SETUPTOOLS["packages"])
    assert sorted(set(found) - listed) == [], "add these packages to [tool.setuptools] packages"
    assert sorted(listed - set(found)) == [], "these listed packages have no folder with an __init__.py"
    assert {"carmreg", "carmreg.panels", "carmreg.views", "carmreg.logic.io", "carmreg.logic.report"} <= listed


def test_every_resource_file_is_shipped_as_package_data():
    patterns = SETUPTOOLS["package-data"]["carmreg.resources"]
    resources = ROOT / SETUPTOOLS["package-dir"]["carmreg.resources"]
    files = [p.relative_to(resources).as_posix() for p in resources.rglob("*") if p.is_file()
             and "__pycache__" not in p.parts and p.name != "__init__.py" and p.suffix != ".pyc"
             and p.relative_to(resources).parts[0] not in NOT_SHIPPED]
    missing = [f for f in files if not any(fnmatch.fnmatch(f, pattern) for pattern in patterns)]
    assert missing == [], f"add to [tool.setuptools.package-data]: {missing}"
    for needed in ("SampleCase/ct.nrrd", "SampleCase/xray.dcm", "Presets/ii_9inch.json", "Icons/carmreg.svg",
                   "Icons/CarmReg.png", "requirements.txt"):
        assert needed in files, needed
