"""A CarmReg session: what the user loaded, set and clicked, as one readable JSON file (no Qt).

A session records the inputs and the user's work, never derived data:

- ``ct_path``, ``xray_path``: the data files (stored relative to the session file when they sit below its
  folder, absolute otherwise; both forms are kept and the first that exists wins on reading);
- ``geometry_overrides``: C-arm values the user set by hand or from a device preset, by field name
  (``sdd_mm``, ``pixel_spacing_mm`` (column, row), ``principal_point_px`` (u, v), ``sod_mm``, ``distortion_mm``
  (an intensifier's pincushion, ``CarmIntrinsics.distortion_mm``)) plus the
  ``preset`` key (a file stem in ``Resources/Presets``) and ``preset_fields`` (which fields the preset set);
  fields absent here come from the X-ray file or the defaults;
- ``ct_points``: CT centroids, ``[{"label": "T12", "position_lps_mm": [x, y, z]}]`` (LPS mm);
- ``xray_points``: X-ray centroids, ``[{"label": "T12" | null, "uv_px": [column, row]}]`` (detector px,
  pixel centres at integers, on the image as stored whatever its orientation);
- ``xray_orientation``: how the window turns the X-ray before showing, clicking and registering it
  (``image.turn.ORIENTATIONS``; "as-stored" unless the user turned a display stored mirrored or rotated). A
  session with a turn is written as version 2 (an older CarmReg refuses it rather than show a result computed on
  the turned image over the stored one); without, as version 1;
- ``last_result``: a summary of the last registration (pose, P, the geometry it used (isocentre, SOD),
  magnification, mPDE per stage, every level's projected ``uv_px``, fitted or not, PDE and click, the level
  check, ``ok`` and warnings, ``stale`` when the inputs changed after it, the output folder; pixels on the X-ray
  as registered, i.e. turned by ``xray_orientation``): the window shows it
  again on reopening (without the DRR, which is recomputed by registering again);
- ``session_file``: in an autosave only, the session file the work belongs to (so a recovered session keeps
  its name).

File format (``*.carmreg.json``)::

    {"format": "carmreg-session", "version": 1, "saved_utc": "...",
     "data": {"ct": {"path": "ct.nrrd", "absolute": "/.../ct.nrrd"}, "xray": {...}},
     "geometry_overrides": {...}, "landmarks": {"ct": [...], "xray": [...]},
     "parameters": {...}, "last_result": {...} | null}

Writes are atomic (``io.atomic``). The GUI also keeps an *autosave* copy after every edit in a state
folder (``$CARMREG_STATE_DIR`` or ``~/.local/state/carmreg``), one file per running process
(``autosave-<pid>.carmreg.json``), removed on a clean exit. An autosave left by a process that is no longer
running means a crash or a kill: ``find_recoverable`` lists those so the user can be offered recovery.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, LandmarkError, quote
from carmreg.logic.io.atomic import atomic_write_json, to_jsonable
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, level_index
from carmreg.logic.io.limits import regular_file

FORMAT_NAME = "carmreg-session"
FORMAT_VERSION = 2
SESSION_SUFFIX = ".carmreg.json"
GEOMETRY_FIELDS = ("sdd_mm", "pixel_spacing_mm", "principal_point_px", "sod_mm", "distortion_mm")


@dataclass
class Session:
    """Everything needed to reopen the user's work (see module docstring for frames and units)."""

    ct_path: str | None = None
    xray_path: str | None = None
    geometry_overrides: dict = field(default_factory=dict)
    ct_points: list[dict] = field(default_factory=list)
    xray_points: list[dict] = field(default_factory=list)
    xray_orientation: str = "as-stored"
    parameters: dict = field(default_factory=dict)
    last_result: dict | None = None
    session_file: str | None = None         # autosave only: the session file this work was saved as

    # ------------------------------------------------------------------------------------ landmarks
    def ct_landmarks(self) -> Landmarks3D:
        """CT points as Landmarks3D (raises LandmarkError if a point has no level name)."""
        unnamed = [i + 1 for i, p in enumerate(self.ct_points) if not p.get("label")]
        if unnamed:
            raise LandmarkError(f"CT point(s) {unnamed} have no level name: name every CT centroid "
                                "(e.g. T12) before registering or exporting")
        return Landmarks3D([p["label"] for p in self.ct_points],
                           np.array([p["position_lps_mm"] for p in self.ct_points], float).reshape(-1, 3),
                           source="session")

    def xray_landmarks(self) -> Landmarks2D:
        return Landmarks2D([p.get("label") for p in self.xray_points],
                           np.array([p["uv_px"] for p in self.xray_points], float).reshape(-1, 2),
                           source="session")

    def set_ct_landmarks(self, landmarks: Landmarks3D) -> None:
        self.ct_points = [{"label": lb, "position_lps_mm": [float(x) for x in p]}
                          for lb, p in zip(landmarks.labels, landmarks.points_lps_mm, strict=True)]

    def set_xray_landmarks(self, landmarks: Landmarks2D) -> None:
        self.xray_points = [{"label": lb, "uv_px": [float(x) for x in p]}
                            for lb, p in zip(landmarks.labels, landmarks.uv_px, strict=True)]

    # ---------------------------------------------------------------------------------- JSON mapping
    def to_json(self, session_path: str | Path | None = None) -> dict:
        """The JSON document; data paths are made relative to ``session_path``'s folder when below it."""
        base = Path(session_path).resolve().parent if session_path else None
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION if self.xray_orientation != "as-stored" else 1,
            "saved_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "data": {"ct": _path_entry(self.ct_path, base), "xray": _path_entry(self.xray_path, base)},
            "geometry_overrides": to_jsonable(self.geometry_overrides),
            "landmarks": {"ct": to_jsonable(_sorted_points(self.ct_points)),
                          "xray": to_jsonable(_sorted_points(self.xray_points))},
            **({"xray_orientation": self.xray_orientation} if self.xray_orientation != "as-stored" else {}),
            "parameters": to_jsonable(self.parameters),
            "last_result": to_jsonable(self.last_result),
            **({"session_file": str(self.session_file)} if self.session_file else {}),
        }

    @classmethod
    def from_json(cls, doc, session_path: str | Path | None = None) -> Session:
        """Inverse of ``to_json``; raises InputFileError naming the first bad field."""
        where = str(session_path) if session_path else "session"
        if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
            raise InputFileError(f"{where}: not a CarmReg session file (expected \"format\": "
                                 f"\"{FORMAT_NAME}\")")
        version = doc.get("version", 0)
        if not isinstance(version, int) or isinstance(version, bool) or version < 0:
            raise InputFileError(f"{where}: session \"version\" {quote(version, 40)} is not a whole number; the "
                                 "file is damaged")
        if version > FORMAT_VERSION:
            raise InputFileError(f"{where}: session version {version} is newer than this "
                                 f"CarmReg understands ({FORMAT_VERSION}); update CarmReg")
        base = Path(session_path).resolve().parent if session_path else None
        data = _mapping(doc, "data", where)
        landmarks = _mapping(doc, "landmarks", where)
        last_result = doc.get("last_result")
        if last_result is not None and not isinstance(last_result, dict):
            raise InputFileError(f"{where}: \"last_result\" {quote(last_result, 40)} is not an object")
        session = cls(ct_path=_resolve_entry(data.get("ct"), base, where, "data.ct"),
                      xray_path=_resolve_entry(data.get("xray"), base, where, "data.xray"),
                      geometry_overrides=_check_overrides(_mapping(doc, "geometry_overrides", where), where),
                      ct_points=_check_ct_points(_list(landmarks, "ct", where), where),
                      xray_points=_check_xray_points(_list(landmarks, "xray", where), where),
                      xray_orientation=_orientation(doc.get("xray_orientation", "as-stored"), where),
                      parameters=_mapping(doc, "parameters", where),
                      last_result=last_result, session_file=_session_file(doc.get("session_file"), where))
        return session


def _orientation(value, where: str) -> str:
    """The session's X-ray orientation, one of ``image.turn.ORIENTATIONS``."""
    from carmreg.logic.image.turn import ORIENTATIONS

    if value not in ORIENTATIONS:
        raise InputFileError(f"{where}: \"xray_orientation\" {quote(value, 40)} is not one of: "
                             f"{', '.join(ORIENTATIONS)}")
    return value


def _mapping(doc: dict, key: str, where: str) -> dict:
    value = doc.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputFileError(f"{where}: \"{key}\" {quote(value, 40)} is not an object; the file is damaged")
    return dict(value)


def _list(doc: dict, key: str, where: str) -> list:
    value = doc.get(key)
    if value is None:
        return []
    if not isinstance(value, list):
        raise InputFileError(f"{where}: \"landmarks.{key}\" {quote(value, 40)} is not a list of points")
    return value


def _is_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and bool(np.isfinite(x))


def _check_overrides(overrides: dict, where: str) -> dict:
    """Geometry overrides by field: numbers where numbers are meant (an error quotes the bad value)."""
    unknown = set(overrides) - set(GEOMETRY_FIELDS) - {"preset", "preset_fields"}
    if unknown:
        raise InputFileError(f"{where}: unknown geometry field(s) {sorted(unknown)}; expected "
                             f"{', '.join(GEOMETRY_FIELDS)}")
    for key, count in (("sdd_mm", 1), ("sod_mm", 1), ("pixel_spacing_mm", 2), ("principal_point_px", 2),
                       ("distortion_mm", 1)):
        value = overrides.get(key)
        if value is None:
            continue
        ok = _is_number(value) and (value > 0 or key == "distortion_mm") if count == 1 else (
            (isinstance(value, list) and len(value) == 2 and all(_is_number(x) for x in value))
            or (key == "pixel_spacing_mm" and _is_number(value)))
        if not ok:
            want = ("a number of mm" if key == "distortion_mm" else "a positive number of mm") if count == 1 \
                else "two numbers"
            raise InputFileError(f"{where}: geometry override {key} = {quote(value, 40)} is not {want}; fix or "
                                 "remove it")
    if "preset" in overrides and not isinstance(overrides["preset"], str | type(None)):
        raise InputFileError(f"{where}: geometry preset {quote(overrides['preset'], 40)} is not a name")
    fields = overrides.get("preset_fields")
    if fields is not None and not (isinstance(fields, list) and all(isinstance(x, str) for x in fields)):
        raise InputFileError(f"{where}: geometry preset_fields {quote(fields, 40)} is not a list of names")
    return overrides


def _session_file(value, where: str) -> str | None:
    """The autosave's ``session_file`` (a path string) or None; anything else is a damaged file."""
    if value in (None, ""):
        return None
    if not isinstance(value, str):
        raise InputFileError(f"{where}: \"session_file\" {quote(value, 40)} is not a path")
    return value


def summarize_result(result, out_dir: str | Path | None = None) -> dict:
    """A small JSON summary of a RegistrationResult for the session record (pose, P, mPDE, per level)."""
    stages = [{"name": s.name, "mpde_mm": to_jsonable(s.mpde_mm), "seconds": to_jsonable(s.seconds)}
              for s in getattr(result, "stages", [])]
    keys = ("label", "uv_px", "fitted", "pde_mm", "in_image", "clicked_uv_px", "name_margin")
    levels = [{k: to_jsonable(v) for k, v in lv.items() if k in keys} for lv in getattr(result, "levels", [])]
    pose = result.pose.as_dict() if hasattr(result.pose, "as_dict") else to_jsonable(result.pose)
    geometry = getattr(result, "geometry", None)
    return {"ok": bool(getattr(result, "ok", False)), "pose": pose,
            "projection_matrix": to_jsonable(np.asarray(result.projection_matrix)),
            "magnification": to_jsonable(getattr(result, "magnification", None)),
            "isocenter_lps_mm": to_jsonable(list(geometry.isocenter_lps_mm)) if geometry is not None else None,
            "sod_mm": to_jsonable(geometry.sod_mm) if geometry is not None else None,
            "stages": stages, "levels": levels, "warnings": list(getattr(result, "warnings", [])),
            "failed_checks": list(getattr(result, "failed_checks", [])),
            "level_check": to_jsonable(getattr(result, "level_check", None)),
            "out_dir": str(out_dir) if out_dir else None}


# ------------------------------------------------------------------------------------------ file I/O

def save_session(path: str | Path, session: Session) -> Path:
    """Write the session as indented JSON, atomically."""
    return atomic_write_json(path, session.to_json(path))


MAX_SESSION_BYTES = 64 * 1024**2


def load_session(path: str | Path) -> Session:
    """Read a session file; raises InputFileError with the file name on any problem (never another error)."""
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: session file not found")
    regular_file(path, "session file")
    if path.stat().st_size > MAX_SESSION_BYTES:
        raise InputFileError(f"{path}: {path.stat().st_size / 1024**2:.0f} MB is far too large for a session file")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputFileError(f"{path}: not a readable session file ({exc.__class__.__name__}); "
                             "open another file or start a new session") from None
    try:
        return Session.from_json(doc, path)
    except (TypeError, ValueError, AttributeError, KeyError, RecursionError, OverflowError) as exc:
        raise InputFileError(f"{path}: not a valid session file ({exc.__class__.__name__}: "
                             f"{quote(str(exc), 80)}); open another file or start a new session") from None


# ------------------------------------------------------------------------------------------ autosave

def state_dir() -> Path:
    """Folder for autosave files: ``$CARMREG_STATE_DIR`` or ``~/.local/state/carmreg``."""
    env = os.environ.get("CARMREG_STATE_DIR")
    return Path(env) if env else Path.home() / ".local" / "state" / "carmreg"


def autosave_path(pid: int | None = None, folder: str | Path | None = None) -> Path:
    """This process's autosave file."""
    return Path(folder or state_dir()) / f"autosave-{os.getpid() if pid is None else pid}{SESSION_SUFFIX}"


def write_autosave(session: Session, pid: int | None = None, folder: str | Path | None = None) -> Path:
    """Atomically write the autosave copy (data paths kept absolute)."""
    path = autosave_path(pid, folder)
    return atomic_write_json(path, session.to_json(None))


def clear_autosave(pid: int | None = None, folder: str | Path | None = None) -> None:
    """Remove this process's autosave (call on a clean exit or after an explicit save + discard)."""
    autosave_path(pid, folder).unlink(missing_ok=True)


def find_recoverable(folder: str | Path | None = None) -> list[Path]:
    """Autosave files left by processes that are no longer running, newest first."""
    folder = Path(folder or state_dir())
    if not folder.is_dir():
        return []
    found = []
    for path in folder.glob(f"autosave-*{SESSION_SUFFIX}"):
        pid_text = path.name[len("autosave-"):-len(SESSION_SUFFIX)]
        if pid_text.isdigit() and int(pid_text) != os.getpid() and not _pid_alive(int(pid_text)):
            found.append(path)
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


def set_aside(path: str | Path) -> Path:
    """Rename an autosave that cannot be restored to ``<name>.unreadable-<time>`` (no longer offered, kept for
    the user); returns the new path (the old one when even the rename fails)."""
    path = Path(path)
    target = path.with_name(f"{path.name}.unreadable-{_dt.datetime.now():%Y%m%d-%H%M%S}")
    try:
        os.replace(path, target)
    except OSError:
        return path
    return target


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


# ------------------------------------------------------------------------------------------ helpers

def _path_entry(path: str | None, base: Path | None) -> dict | None:
    if not path:
        return None
    absolute = Path(path).expanduser().resolve()
    entry = {"path": str(absolute), "absolute": str(absolute)}
    if base is not None:
        try:
            entry["path"] = absolute.relative_to(base).as_posix()
        except ValueError:
            pass
    return entry


def _resolve_entry(entry, base: Path | None, where: str = "session", key: str = "data") -> str | None:
    if not entry:
        return None
    if isinstance(entry, str):
        entry = {"path": entry}
    if not isinstance(entry, dict) or not all(isinstance(entry.get(k), str | type(None))
                                              for k in ("path", "absolute")):
        raise InputFileError(f"{where}: \"{key}\" {quote(entry, 40)} is not a file path")
    candidates = []
    rel = entry.get("path")
    if rel:
        candidates.append(Path(rel) if Path(rel).is_absolute() or base is None else base / rel)
    if entry.get("absolute"):
        candidates.append(Path(entry["absolute"]))
    for candidate in candidates:
        if candidate.exists():
            return str(candidate)
    return str(candidates[0]) if candidates else None


def _sorted_points(points: list[dict]) -> list[dict]:
    def key(p):
        try:
            return (0, level_index(p.get("label") or ""))
        except LandmarkError:
            return (1, 0)
    return sorted(points, key=key)


def _label(p: dict, i: int, where: str, side: str) -> str | None:
    label = p.get("label")
    if label is not None and not isinstance(label, str):
        raise InputFileError(f"{where}: {side} landmark {i + 1} label {quote(label, 40)} is not a name")
    return label or None


def _point(p, key: str, n: int, i: int, where: str, side: str, want: str) -> list[float]:
    value = p.get(key) if isinstance(p, dict) else None
    if not (isinstance(value, list) and len(value) == n and all(_is_number(x) for x in value)):
        raise InputFileError(f"{where}: {side} landmark {i + 1} needs \"{key}\": {want} (it has "
                             f"{quote(value if isinstance(p, dict) else p, 40)})")
    return [float(x) for x in value]


def _check_ct_points(points, where: str) -> list[dict]:
    return [{"label": _label(p, i, where, "CT"),
             "position_lps_mm": _point(p, "position_lps_mm", 3, i, where, "CT", "[x, y, z]")}
            for i, p in enumerate(points)]


def _check_xray_points(points, where: str) -> list[dict]:
    return [{"label": _label(p, i, where, "X-ray"),
             "uv_px": _point(p, "uv_px", 2, i, where, "X-ray", "[column, row]")}
            for i, p in enumerate(points)]
