"""C-arm device presets: JSON rows of data in ``Resources/Presets`` (no Qt, usable from the CLI too).

Each preset file holds ``name``, ``description`` and ``fields``; every field has ``value``, ``unit``, ``min``,
``max`` and a human ``label``. ``pixel_spacing_mm`` is (column, row) spacing *at the detector* for the
preset's ``size_px`` (columns, rows); an X-ray saved at another size (binned or resampled) covers the same
detector area, so its spacing is scaled by ``preset size / image size``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from carmreg.logic.errors import InputFileError
from carmreg.logic.resources import PRESETS_DIR


@dataclass(frozen=True)
class DevicePreset:
    """One C-arm model: field name -> {value, unit, min, max, label}."""

    key: str
    name: str
    description: str
    fields: dict

    def value(self, name: str):
        return self.fields.get(name, {}).get("value")

    def range(self, name: str) -> tuple[float | None, float | None]:
        entry = self.fields.get(name, {})
        return entry.get("min"), entry.get("max")

    def geometry_for(self, image_size_px: tuple[int, int] | None = None) -> dict:
        """Geometry values for an image of ``image_size_px`` (columns, rows): sdd_mm, pixel_spacing_mm,
        sod_mm. Pixel spacing is scaled from the preset's readout size to the image size."""
        du, dv = self.value("pixel_spacing_mm")
        if image_size_px is not None and self.value("size_px"):
            cols, rows = self.value("size_px")
            du, dv = du * cols / image_size_px[0], dv * rows / image_size_px[1]
        return {"sdd_mm": float(self.value("sdd_mm")), "pixel_spacing_mm": (float(du), float(dv)),
                "sod_mm": float(self.value("sod_mm"))}


def load_preset(path: str | Path) -> DevicePreset:
    """Read one preset file; raises InputFileError if it lacks a required field."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        fields = doc["fields"]
        for name in ("sdd_mm", "pixel_spacing_mm", "sod_mm"):
            entry = fields[name]
            if entry["value"] is None or "unit" not in entry:
                raise KeyError(name)
        return DevicePreset(path.stem, str(doc["name"]), str(doc.get("description", "")), fields)
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputFileError(f"{path}: not a valid C-arm preset (needs fields sdd_mm, pixel_spacing_mm, "
                             f"sod_mm with value and unit; problem: {exc})") from None


def list_presets(folder: str | Path | None = None) -> list[DevicePreset]:
    """All presets in ``folder`` (default: the product's Resources/Presets), sorted by name."""
    folder = Path(folder) if folder else PRESETS_DIR
    return sorted((load_preset(p) for p in folder.glob("*.json")), key=lambda p: p.name)
