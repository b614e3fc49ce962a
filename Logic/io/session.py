"""A CarmReg session: what the user loaded, set and clicked, as one readable JSON file (no Qt).

A session records the inputs and the user's work, never derived data:

- ``ct_path``, ``xray_path``: the data files (stored relative to the session file when they sit below its
  folder, absolute otherwise; both forms are kept and the first that exists wins on reading);
- ``geometry_overrides``: C-arm values the user set by hand or from a device preset, by field name
  (``sdd_mm``, ``pixel_spacing_mm`` (column, row), ``principal_point_px`` (u, v), ``sod_mm``) plus the
  ``preset`` key (a file stem in ``Resources/Presets``) and ``preset_fields`` (which fields the preset set);
  fields absent here come from the X-ray file or the defaults;
- ``ct_points``: CT centroids, ``[{"label": "T12", "position_lps_mm": [x, y, z]}]`` (LPS mm);
- ``xray_points``: X-ray centroids, ``[{"label": "T12" | null, "uv_px": [column, row]}]`` (detector px,
  pixel centres at integers);
- ``last_result``: a summary of the last registration (pose, P, the geometry it used (isocentre, SOD),
  magnification, mPDE per stage, every level's projected ``uv_px``, fitted or not, PDE and click, the level
  check, ``ok`` and warnings, ``stale`` when the inputs changed after it, the output folder): the window shows it
  again on reopening (without the DRR, which is recomputed by registering again);
- ``session_file``: in an autosave only, the session file the work belongs to (so a recovered session keeps
  its name).

File format (``*.carmreg.json``)::

    {"format": "carmreg-session", "version": 1, "saved_utc": "...",
     "data": {"ct": {"path": "ct.nrrd", "absolute": "/.../ct.nrrd"}, "xray": {...}},
     "geometry_overrides": {...}, "landmarks": {"ct": [...], "xray": [...]},
     "parameters": {...}, "last_result": {...} | null}

Writes are atomic (``Logic.atomic``). The GUI also keeps an *autosave* copy after every edit in a state
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

from carmreg.logic.errors import InputFileError, LandmarkError
from carmreg.logic.io.atomic import atomic_write_json, to_jsonable
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, level_index

FORMAT_NAME = "carmreg-session"
FORMAT_VERSION = 1
SESSION_SUFFIX = ".carmreg.json"
GEOMETRY_FIELDS = ("sdd_mm", "pixel_spacing_mm", "principal_point_px", "sod_mm")


@dataclass
class Session:
    """Everything needed to reopen the user's work (see module docstring for frames and units)."""

    ct_path: str | None = None
    xray_path: str | None = None
    geometry_overrides: dict = field(default_factory=dict)
    ct_points: list[dict] = field(default_factory=list)
    xray_points: list[dict] = field(default_factory=list)
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
            "version": FORMAT_VERSION,
            "saved_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "data": {"ct": _path_entry(self.ct_path, base), "xray": _path_entry(self.xray_path, base)},
            "geometry_overrides": to_jsonable(self.geometry_overrides),
            "landmarks": {"ct": to_jsonable(_sorted_points(self.ct_points)),
                          "xray": to_jsonable(_sorted_points(self.xray_points))},
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
        if int(doc.get("version", 0)) > FORMAT_VERSION:
            raise InputFileError(f"{where}: session version {doc.get('version')} is newer than this "
                                 f"CarmReg understands ({FORMAT_VERSION}); update CarmReg")
        base = Path(session_path).resolve().parent if session_path else None
        data = doc.get("data") or {}
        landmarks = doc.get("landmarks") or {}
        session = cls(ct_path=_resolve_entry(data.get("ct"), base),
                      xray_path=_resolve_entry(data.get("xray"), base),
                      geometry_overrides=dict(doc.get("geometry_overrides") or {}),
                      ct_points=_check_ct_points(landmarks.get("ct") or [], where),
                      xray_points=_check_xray_points(landmarks.get("xray") or [], where),
                      parameters=dict(doc.get("parameters") or {}),
                      last_result=doc.get("last_result"), session_file=doc.get("session_file") or None)
        unknown = set(session.geometry_overrides) - set(GEOMETRY_FIELDS) - {"preset", "preset_fields"}
        if unknown:
            raise InputFileError(f"{where}: unknown geometry field(s) {sorted(unknown)}; expected "
                                 f"{', '.join(GEOMETRY_FIELDS)}")
        return session


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
            "level_check": to_jsonable(getattr(result, "level_check", None)),
            "out_dir": str(out_dir) if out_dir else None}


# ------------------------------------------------------------------------------------------ file I/O

def save_session(path: str | Path, session: Session) -> Path:
    """Write the session as indented JSON, atomically."""
    return atomic_write_json(path, session.to_json(path))


def load_session(path: str | Path) -> Session:
    """Read a session file; raises InputFileError with the file name on any problem."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: session file not found")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(f"{path}: not a readable session file ({exc.__class__.__name__}); "
                             "open another file or start a new session") from None
    return Session.from_json(doc, path)


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


def _resolve_entry(entry, base: Path | None) -> str | None:
    if not entry:
        return None
    if isinstance(entry, str):
        entry = {"path": entry}
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


def _check_ct_points(points, where: str) -> list[dict]:
    out = []
    for i, p in enumerate(points):
        try:
            pos = [float(x) for x in p["position_lps_mm"]]
            if len(pos) != 3 or not np.all(np.isfinite(pos)):
                raise ValueError
        except (KeyError, TypeError, ValueError):
            raise InputFileError(f"{where}: CT landmark {i + 1} needs \"position_lps_mm\": [x, y, z]") \
                from None
        out.append({"label": p.get("label") or None, "position_lps_mm": pos})
    return out


def _check_xray_points(points, where: str) -> list[dict]:
    out = []
    for i, p in enumerate(points):
        try:
            uv = [float(x) for x in p["uv_px"]]
            if len(uv) != 2 or not np.all(np.isfinite(uv)):
                raise ValueError
        except (KeyError, TypeError, ValueError):
            raise InputFileError(f"{where}: X-ray landmark {i + 1} needs \"uv_px\": [column, row]") from None
        out.append({"label": p.get("label") or None, "uv_px": uv})
    return out
