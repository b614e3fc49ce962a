"""Where the product's own files live (the ``carmreg.resources`` package: Resources/ in the source tree, inside
the wheel when installed) and the per-user cache."""

from __future__ import annotations

import os
from importlib import resources as _importlib_resources
from pathlib import Path

from carmreg.logic.errors import InputFileError

RESOURCES_DIR = Path(str(_importlib_resources.files("carmreg.resources")))  # a real folder: never zipped
SAMPLE_CASE_DIR = RESOURCES_DIR / "SampleCase"
PRESETS_DIR = RESOURCES_DIR / "Presets"
ICON_PATH = RESOURCES_DIR / "Icons" / "carmreg.svg"


def sample_case() -> dict[str, Path]:
    """Paths of the embedded sample case; InputFileError when the installation lacks it."""
    names = {"ct": "ct.nrrd", "vertebrae": "vertebrae.nrrd", "ct_landmarks": "ct_centroids.mrk.json",
             "xray": "xray.dcm", "xray_png": "xray.png", "xray_landmarks": "xray_centroids.mrk.json",
             "ground_truth": "ground_truth.json"}
    paths = {key: SAMPLE_CASE_DIR / name for key, name in names.items()}
    missing = [str(p) for key, p in paths.items() if key in ("ct", "ct_landmarks", "xray", "xray_landmarks")
               and not p.is_file()]
    if missing:
        raise InputFileError(f"the embedded sample case is incomplete (missing {', '.join(missing)}); "
                             "reinstall CarmReg or run scripts/make_sample_case.py")
    return paths


def cache_dir() -> Path:
    """Per-user cache for DRR databases: $CARMREG_CACHE, else $XDG_CACHE_HOME/carmreg, else ~/.cache/carmreg."""
    if os.environ.get("CARMREG_CACHE"):
        return Path(os.environ["CARMREG_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "carmreg"
