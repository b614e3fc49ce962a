"""Vertebral landmarks: level names, Slicer Markups JSON (.mrk.json) and plain JSON, pairing by label.

3D points are LPS mm (``points_lps_mm``). 2D points are detector pixels ``uv_px`` = (column, row), 0-based,
pixel centres at integer coordinates.

2D points in .mrk.json
----------------------
Slicer shows an X-ray loaded as a volume with origin 0 and identity directions in LPS and spacing = pixel
spacing, so a pixel (u, v) sits at LPS ``(u * du, v * dv, 0)`` mm. CarmReg writes 2D points that way
(``coordinateSystem: "LPS"``) *and* stores the exact pixel coordinates in each control point under the
namespaced key ``"carmreg": {"uv_px": [u, v]}``, plus ``"carmreg": {"pixel_spacing_mm": [du, dv]}`` on the
markup. On reading, ``uv_px`` wins; without it, ``position[:2] / pixel_spacing`` is used (spacing 1 if
unknown), so points placed in Slicer on such a volume load correctly.

Plain JSON for 2D: ``{"T12": [column, row], ...}`` (named) or ``[[column, row], ...]`` (unnamed clicks).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, LandmarkError, describe, quote
from carmreg.logic.io.atomic import atomic_write_json
from carmreg.logic.io.limits import regular_file

LEVEL_NAMES = ([f"C{i}" for i in range(1, 8)] + [f"T{i}" for i in range(1, 14)]
               + [f"L{i}" for i in range(1, 7)] + ["S1"])
"""Vertebral levels from head to sacrum (T13 and L6 for transitional anatomy)."""
MRK_SCHEMA = "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#"


def normalize_level_name(label: str) -> str:
    """'t12', 'T 12', 'T12 ' -> 'T12'. Raises LandmarkError for anything that is not a vertebral level."""
    m = re.fullmatch(r"\s*([CTLS])\s*-?\s*(\d{1,2})\s*", str(label), flags=re.IGNORECASE)
    name = f"{m.group(1).upper()}{int(m.group(2))}" if m else None
    if name not in LEVEL_NAMES:
        raise LandmarkError(f"landmark label {quote(label)} is not a vertebral level: name points C1-C7, T1-T13, "
                            "L1-L6 or S1 (e.g. 'T12', 'L1')")
    return name


def level_index(name: str) -> int:
    """Position along the spine, head to sacrum (C1 = 0)."""
    return LEVEL_NAMES.index(normalize_level_name(name))


TRANSITIONAL_LEVELS = ("T13", "L6")
"""Rare extra levels: accepted as names, skipped when stepping from a usual level."""


def next_level(name: str | None, step: int = 1) -> str:
    """The level after ``name`` going caudally (T11 -> T12 -> L1); 'T12' when nothing is placed yet.

    Stepping from a usual level skips the transitional T13 and L6; stepping from them uses the full list.
    """
    if name is None:
        return "T12"
    name = normalize_level_name(name)
    names = LEVEL_NAMES if name in TRANSITIONAL_LEVELS else [n for n in LEVEL_NAMES
                                                            if n not in TRANSITIONAL_LEVELS]
    i = min(max(names.index(name) + step, 0), len(names) - 1)
    return names[i]


@dataclass
class Landmarks3D:
    """Named points in the CT: labels[i] at points_lps_mm[i] (LPS mm)."""

    labels: list[str]
    points_lps_mm: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        self.points_lps_mm = np.asarray(self.points_lps_mm, dtype=np.float64).reshape(-1, 3)
        self.labels = _normalized(self.labels, self.source, unnamed_ok=False)
        _check_points(self.labels, self.points_lps_mm, self.source)

    def as_dict(self) -> dict[str, np.ndarray]:
        return dict(zip(self.labels, self.points_lps_mm, strict=True))

    def sorted(self) -> Landmarks3D:
        order = np.argsort([level_index(lb) for lb in self.labels], kind="stable")
        return Landmarks3D([self.labels[i] for i in order], self.points_lps_mm[order], self.source)


@dataclass
class Landmarks2D:
    """Points on the X-ray: uv_px[i] = (column, row); labels[i] may be None (an unnamed click)."""

    labels: list[str | None]
    uv_px: np.ndarray
    source: str = ""
    pixel_spacing_mm: tuple[float, float] | None = field(default=None)

    def __post_init__(self) -> None:
        self.uv_px = np.asarray(self.uv_px, dtype=np.float64).reshape(-1, 2)
        self.labels = _normalized(self.labels, self.source, unnamed_ok=True)
        _check_points([lb for lb in self.labels if lb], self.uv_px, self.source)

    @property
    def named(self) -> bool:
        return all(lb is not None for lb in self.labels)

    def as_dict(self) -> dict[str, np.ndarray]:
        return {lb: p for lb, p in zip(self.labels, self.uv_px, strict=True) if lb is not None}


def _normalized(labels: list, source: str, unnamed_ok: bool) -> list:
    """Level names normalised ('t 12' -> 'T12'); None/'' kept as None when ``unnamed_ok``; errors name the
    file."""
    out = []
    for label in labels:
        if unnamed_ok and (label is None or label == ""):
            out.append(None)
            continue
        try:
            out.append(normalize_level_name(label))
        except LandmarkError as exc:
            raise LandmarkError(f"{source}: {exc}" if source else str(exc)) from None
    return out


def _check_points(labels: list[str], points: np.ndarray, source: str) -> None:
    where = f"{source}: " if source else ""
    if not np.all(np.isfinite(points)):
        raise LandmarkError(f"{where}a landmark position is not a finite number (NaN or infinity); "
                            "place or remove that point")
    dup = sorted(lb for lb, n in Counter(labels).items() if n > 1)
    if dup:
        raise LandmarkError(f"{where}level {', '.join(dup)} is labelled more than once; each vertebra "
                            "needs exactly one centroid")


LEVEL_SPACING_MM = (8.0, 60.0)
"""Plausible distance between the centroids of adjacent vertebrae (cervical ~15 mm, lumbar ~35-40 mm)."""


def _level_gap(upper: str, lower: str) -> int:
    """Number of vertebrae from ``upper`` down to ``lower``; the transitional T13 and L6 count only when one
    of the two is itself transitional (T12 -> L1 is one level)."""
    usual = [n for n in LEVEL_NAMES if n not in TRANSITIONAL_LEVELS]
    names = LEVEL_NAMES if {upper, lower} & set(TRANSITIONAL_LEVELS) else usual
    return names.index(lower) - names.index(upper)


def _first_reversal(t: np.ndarray) -> int | None:
    """Index k of the first step t[k] -> t[k+1] that does not advance (t must increase), or None."""
    bad = np.flatnonzero(np.diff(np.asarray(t, dtype=float)) <= 0)
    return int(bad[0]) if bad.size else None


def spine_order_warnings(ct: Landmarks3D, xray: Landmarks2D | None = None) -> list[str]:
    """Plausibility of the labels (warnings, not errors), since adjacent vertebrae never swap places:

    - CT centroids sorted head to sacrum must descend: LPS z (superior) strictly decreases;
    - and lie 8-60 mm apart per level (catches points in cm or voxels, and misnamed levels);
    - X-ray points sorted head to sacrum must advance monotonically along the line from the first to the
      last (any image orientation), i.e. ``(uv_k - uv_first) . (uv_last - uv_first)`` strictly increases.
    """
    notes = []
    ct = ct.sorted()
    labels, z = ct.labels, ct.points_lps_mm[:, 2]
    k = _first_reversal(-z) if len(labels) >= 2 else None
    if k is not None:
        notes.append(f"CT levels are not in spine order: {labels[k + 1]} (z {z[k + 1]:.1f} mm) is not below "
                     f"{labels[k]} (z {z[k]:.1f} mm; LPS +z is superior); two labels are probably swapped or "
                     "misnamed, check them")
    if len(labels) >= 2:
        gaps = np.array([_level_gap(a, b) for a, b in zip(labels, labels[1:], strict=False)])
        per_level = np.linalg.norm(np.diff(ct.points_lps_mm, axis=0), axis=1) / gaps
        lo, hi = LEVEL_SPACING_MM
        odd = [f"{a}-{b} {d:.1f} mm" for a, b, d in zip(labels, labels[1:], per_level, strict=False)
               if not lo <= d <= hi]
        if odd:
            notes.append(f"CT centroid spacing per level is implausible ({', '.join(odd)}; expected {lo:.0f}-"
                         f"{hi:.0f} mm): are the points in mm and LPS, and named after the right vertebrae?")
    named = sorted(xray.as_dict().items(), key=lambda kv: level_index(kv[0])) if xray is not None else []
    if len(named) >= 3:
        uv = np.array([p for _, p in named])
        k = _first_reversal((uv - uv[0]) @ (uv[-1] - uv[0]))
        if k is not None:
            notes.append(f"X-ray levels are not in spine order: {named[k + 1][0]} does not follow "
                         f"{named[k][0]} along the spine from {named[0][0]} to {named[-1][0]}; two labels "
                         "are probably swapped or misnamed, check them")
    return notes


@dataclass
class Pairs:
    """CT and X-ray landmarks matched by label, ordered head to sacrum."""

    labels: list[str]
    points_lps_mm: np.ndarray
    uv_px: np.ndarray
    notes: list[str]          # levels on one side only, spine-order doubts: for the user, not errors


def pair_by_label(ct: Landmarks3D, xray: Landmarks2D, minimum: int = 3) -> Pairs:
    """Pair CT and X-ray points by level name (never by index); one-sided labels and spine-order doubts go
    to ``Pairs.notes``; LandmarkError with fewer than ``minimum`` common levels."""
    ct_map, xr_map = ct.as_dict(), xray.as_dict()
    common = sorted(set(ct_map) & set(xr_map), key=level_index)
    notes = []
    only_xray = sorted(set(xr_map) - set(ct_map), key=level_index)
    if only_xray:
        notes.append(f"X-ray levels {', '.join(only_xray)} have no CT centroid and are not used")
    notes += spine_order_warnings(ct, xray)
    if len(common) < minimum:
        ct_from, xray_from = (f" ({lm.source})" if lm.source else "" for lm in (ct, xray))
        raise LandmarkError(f"only {len(common)} level(s) ({', '.join(common) or 'none'}) are labelled on "
                            f"both the CT{ct_from} and the X-ray{xray_from}; label at least {minimum} of the "
                            "same vertebrae on both")
    return Pairs(common, np.array([ct_map[lb] for lb in common]), np.array([xr_map[lb] for lb in common]),
                 notes)


# ----------------------------------------------------------------------------------------------- reading

PLAIN_3D = "plain JSON landmarks must map level names to [x, y, z] LPS mm"
PLAIN_2D = "plain JSON X-ray landmarks must be {\"T12\": [column, row]} or [[column, row], ...] px"
MAX_LANDMARK_FILE_BYTES = 16 * 1024**2
"""Largest landmark file read (a few hundred points take a few kB)."""


def _load_json(path: Path):
    if path.is_dir():
        raise InputFileError(f"{path}: is a folder; give the landmark file (.mrk.json or .json) itself")
    regular_file(path, "landmark file")
    if path.stat().st_size > MAX_LANDMARK_FILE_BYTES:
        raise InputFileError(f"{path}: the landmark file is {path.stat().st_size / 1024**2:.0f} MB, far more than "
                             "any list of vertebral centroids; give the right file")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(f"{path}: not a valid JSON landmark file ({describe(exc, 80)})") from None
    except RecursionError:
        raise InputFileError(f"{path}: the JSON is nested too deeply to be a landmark file") from None
    except OSError as exc:
        raise InputFileError(f"{path}: the landmark file cannot be read ({exc.strerror or exc})") from None


def _numbers(value, n: int, path: Path, what: str, expected: str = "") -> np.ndarray:
    """Exactly ``n`` JSON numbers (booleans and strings are not numbers), as floats; else InputFileError
    quoting the value. Never reshapes: ``[u, v, 0]`` is not a 2-D point."""
    if not (isinstance(value, list | tuple) and len(value) == n
            and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)):
        raise InputFileError(f"{path}: {what} {quote(value)} is not {n} numbers" + (f"; {expected}" if expected
                                                                                    else ""))
    return np.array(value, dtype=float)


def _require_level_keys(doc: dict, path: Path, value: str) -> None:
    """A plain JSON object none of whose keys is a level name is some other JSON file, not landmarks."""
    def is_level(key) -> bool:
        try:
            normalize_level_name(key)
            return True
        except LandmarkError:
            return False

    if doc and not any(is_level(key) for key in doc):
        first_key, first_value = next(iter(doc.items()))
        if isinstance(first_value, list) and len(first_value) in (2, 3):  # points under names that are not levels
            try:
                normalize_level_name(first_key)
            except LandmarkError as exc:
                raise InputFileError(f"{path}: {exc}") from None
        keys = ", ".join(quote(k, 30) for k in list(doc)[:4])
        raise InputFileError(f"{path}: not a landmark file: expected a Slicer .mrk.json, or JSON mapping "
                             f"level names to {value} such as {{\"T12\": [...]}}; its keys are {keys}")


def _control_points(doc, path: Path) -> tuple[list, dict]:
    try:
        markup = doc["markups"][0]
        points = markup["controlPoints"]
        if not isinstance(points, list):
            raise TypeError
    except (KeyError, IndexError, TypeError):
        raise InputFileError(f"{path}: not a Slicer markups file (expected markups[0].controlPoints)") \
            from None
    if not all(isinstance(p, dict) for p in points):
        raise InputFileError(f"{path}: not a Slicer markups file (controlPoints must be objects)")
    system = str(markup.get("coordinateSystem", "LPS")).upper()
    if system not in ("LPS", "RAS"):
        raise InputFileError(f"{path}: unknown coordinateSystem {system!r} (expected LPS or RAS)")
    return [p for p in points if p.get("positionStatus", "defined") == "defined"], markup


def _position(point: dict, path: Path) -> np.ndarray:
    try:
        pos = _numbers(point["position"], 3, path, "position")
    except (KeyError, InputFileError):
        raise InputFileError(f"{path}: control point {quote(point.get('label', '?'), 30)} has no 3-number "
                             f"position (it has {quote(point.get('position'), 40)})") from None
    return pos


def read_landmarks_3d(path: str | Path) -> Landmarks3D:
    """Read CT centroids from a Slicer .mrk.json (LPS or RAS) or plain JSON ``{"T12": [x, y, z]}`` (LPS)."""
    path = Path(path)
    doc = _load_json(path)
    if isinstance(doc, dict) and "markups" not in doc:
        _require_level_keys(doc, path, "[x, y, z] LPS mm")
        return Landmarks3D(list(doc), [_numbers(v, 3, path, f"the position of {quote(k, 30)}", PLAIN_3D)
                                       for k, v in doc.items()], str(path))
    points, markup = _control_points(doc, path)
    flip = np.array([-1.0, -1.0, 1.0]) if markup.get("coordinateSystem", "LPS").upper() == "RAS" else 1.0
    labels = [p.get("label", "") for p in points]
    points_lps_mm = np.array([_position(p, path) * flip for p in points], dtype=float).reshape(-1, 3)
    return Landmarks3D(labels, points_lps_mm, str(path))


def read_landmarks_2d(path: str | Path, pixel_spacing_mm: tuple[float, float] | None = None) -> Landmarks2D:
    """Read X-ray points: .mrk.json (see module docstring), ``{"T12": [u, v]}`` or ``[[u, v], ...]``."""
    path = Path(path)
    doc = _load_json(path)
    if isinstance(doc, list):
        uv = [_numbers(v, 2, path, f"unnamed click {i + 1}", PLAIN_2D) for i, v in enumerate(doc)]
        return Landmarks2D([None] * len(doc), np.array(uv).reshape(-1, 2), str(path))
    if isinstance(doc, dict) and "markups" not in doc:
        _require_level_keys(doc, path, "[column, row] px")
        uv = [_numbers(v, 2, path, f"the click {quote(k, 30)}", PLAIN_2D) for k, v in doc.items()]
        return Landmarks2D(list(doc), np.array(uv).reshape(-1, 2), str(path))
    points, markup = _control_points(doc, path)
    spacing = _markup_spacing(markup, pixel_spacing_mm, path)
    ras = str(markup.get("coordinateSystem", "LPS")).upper() == "RAS"
    uv, labels = [], []
    for p in points:
        extra = p.get("carmreg")
        if isinstance(extra, dict) and "uv_px" in extra:
            uv.append(_numbers(extra["uv_px"], 2, path,
                               f"control point {quote(p.get('label', '?'), 30)}: carmreg.uv_px"))
        else:
            pos = _position(p, path) * (np.array([-1.0, -1.0, 1.0]) if ras else 1.0)
            uv.append(pos[:2] / np.asarray(spacing))
        labels.append(p.get("label") or None)
    return Landmarks2D(labels, np.array(uv).reshape(-1, 2), str(path), spacing)


def _markup_spacing(markup: dict, fallback, path: Path) -> tuple[float, float]:
    """(du, dv) mm per pixel: the file's ``carmreg.pixel_spacing_mm``, else ``fallback``, else (1, 1)."""
    extra = markup.get("carmreg")
    spacing = (extra.get("pixel_spacing_mm") if isinstance(extra, dict) else None) or fallback
    if spacing is None:
        return 1.0, 1.0
    if isinstance(spacing, list):
        du, dv = _numbers(spacing, 2, path, "carmreg.pixel_spacing_mm (column, row) mm")
    else:
        try:
            du, dv = (float(x) for x in np.asarray(spacing, dtype=float).reshape(2))
        except (TypeError, ValueError):
            raise InputFileError(f"{path}: carmreg.pixel_spacing_mm {quote(spacing, 40)} is not two numbers "
                                 "(column, row) mm") from None
    if not (np.isfinite(du) and np.isfinite(dv) and du > 0 and dv > 0):
        raise InputFileError(f"{path}: pixel spacing ({du}, {dv}) mm for the X-ray points is not positive")
    return du, dv


# ----------------------------------------------------------------------------------------------- writing

def _markup(points: list[dict], extra: dict | None = None) -> dict:
    markup = {"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm", "locked": False,
              "labelFormat": "%N-%d", "controlPoints": points,
              "display": {"visibility": True, "textScale": 3.0, "glyphScale": 3.0}}
    if extra:
        markup["carmreg"] = extra
    return {"@schema": MRK_SCHEMA, "markups": [markup]}


def _control_point(index: int, label: str | None, position, extra: dict | None = None) -> dict:
    point = {"id": str(index + 1), "label": label or "", "description": "", "associatedNodeID": "",
             "position": [float(x) for x in position], "orientation": [-1.0, 0, 0, 0, -1.0, 0, 0, 0, 1.0],
             "selected": True, "locked": False, "visibility": True, "positionStatus": "defined"}
    if extra:
        point["carmreg"] = extra
    return point


def write_markups_lps(path: str | Path, labels: list, points_lps_mm: np.ndarray,
                      point_extras: list[dict] | None = None) -> Path:
    """Write named 3D points (LPS mm, ``labels[i]`` may be None) as a Slicer .mrk.json (atomic); a point's
    ``point_extras[i]`` goes under its namespaced ``"carmreg"`` key."""
    extras = point_extras or [None] * len(labels)
    points = [_control_point(i, lb, p, extra) for i, (lb, p, extra) in
              enumerate(zip(labels, np.asarray(points_lps_mm, float).reshape(-1, 3), extras, strict=True))]
    return atomic_write_json(path, _markup(points))


def write_landmarks_3d(path: str | Path, landmarks: Landmarks3D) -> Path:
    """Write CT centroids as a Slicer .mrk.json in LPS mm (atomic)."""
    return write_markups_lps(path, landmarks.labels, landmarks.points_lps_mm)


def write_landmarks_2d(path: str | Path, landmarks: Landmarks2D,
                       pixel_spacing_mm: tuple[float, float] | None = None) -> Path:
    """Write X-ray points as .mrk.json: LPS (u du, v dv, 0) plus exact ``carmreg.uv_px`` (atomic)."""
    spacing = np.asarray(pixel_spacing_mm or landmarks.pixel_spacing_mm or (1.0, 1.0), float)
    points = [_control_point(i, lb, [uv[0] * spacing[0], uv[1] * spacing[1], 0.0],
                             {"uv_px": [float(uv[0]), float(uv[1])]})
              for i, (lb, uv) in enumerate(zip(landmarks.labels, landmarks.uv_px, strict=True))]
    return atomic_write_json(path, _markup(points, {"pixel_spacing_mm": [float(s) for s in spacing]}))
