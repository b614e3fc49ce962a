"""Named landmark points being edited in the GUI, with every edit undoable (QUndoStack).

Two stores exist: CT centroids (``dim == 3``, positions LPS mm) and X-ray centroids (``dim == 2``, positions
(u, v) detector px). One level name per vertebra: placing a level that is already there moves it. Edits go
through undo commands pushed on a shared QUndoStack, so Ctrl+Z undoes placing, moving (one command per drag),
renaming and deleting alike. ``changed`` fires after every change (views redraw, the window autosaves).

Unnamed points: with ``naming`` off (X-ray only: "Name the levels" unticked) a click places a point with label
None; the logic then identifies its level. Unnamed points are shown as ``?1``, ``?2``, ... numbered along the
spine, top of the image first (X-ray: row v increasing; CT: LPS z decreasing, i.e. head first).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from qtpy import QtCore, QtGui

from carmreg.logic.errors import LandmarkError
from carmreg.logic.io.landmarks import (
    LEVEL_NAMES,
    Landmarks2D,
    Landmarks3D,
    level_index,
    next_level,
    normalize_level_name,
)


@dataclass
class Point:
    id: int
    label: str | None
    position: np.ndarray  # (3,) LPS mm or (2,) (u, v) px


class PointStore(QtCore.QObject):
    """The points of one image (CT or X-ray) and the level proposed for the next click."""

    changed = QtCore.Signal()
    selection_changed = QtCore.Signal(object)   # point id or None
    pending_level_changed = QtCore.Signal(str)
    naming_changed = QtCore.Signal(bool)

    def __init__(self, name: str, dim: int, undo_stack: QtGui.QUndoStack, parent=None):
        super().__init__(parent)
        self.name, self.dim, self.undo_stack = name, dim, undo_stack
        self._points: dict[int, Point] = {}
        self._next_id = 1
        self.selected: int | None = None
        self.pending_level = "T12"
        self.naming = True  # False: a click places an unnamed point (label None)

    # ------------------------------------------------------------------------------------- queries
    def points(self) -> list[Point]:
        """Named points head to sacrum, then the unnamed ones along the spine (``?1``, ``?2``, ...)."""
        def key(p: Point):
            return (0, level_index(p.label), 0.0, p.id) if p.label else (1, 0, self._spine_key(p), p.id)
        return sorted(self._points.values(), key=key)

    def unnamed_numbers(self) -> dict[int, int]:
        """{point id: k} of the unnamed points, k = 1, 2, ... along the spine, top of the image first."""
        unnamed = [p for p in self.points() if not p.label]
        return {p.id: k for k, p in enumerate(unnamed, start=1)}

    def display_name(self, point_id: int) -> str:
        """The level name, or ``?k`` for the k-th unnamed point (see ``unnamed_numbers``)."""
        point = self._points[point_id]
        return point.label or f"?{self.unnamed_numbers().get(point_id, 0)}"

    def unnamed_count(self) -> int:
        return sum(1 for p in self._points.values() if not p.label)

    def get(self, point_id: int) -> Point | None:
        return self._points.get(point_id)

    def find(self, label: str) -> Point | None:
        label = normalize_level_name(label)
        return next((p for p in self._points.values() if p.label == label), None)

    def labels(self) -> list[str]:
        return [p.label for p in self.points() if p.label]

    def __len__(self) -> int:
        return len(self._points)

    def next_free_level(self, after: str | None) -> str:
        """First level caudal of ``after`` (T11 -> T12 -> L1) not yet placed; wraps to the head if needed."""
        used = set(self.labels())
        name = next_level(after) if after else "T12"
        start = LEVEL_NAMES.index(name)
        for i in list(range(start, len(LEVEL_NAMES))) + list(range(0, start)):
            if LEVEL_NAMES[i] not in used:
                return LEVEL_NAMES[i]
        return name

    def set_naming(self, on: bool) -> None:
        """Name the levels on click (on) or place unnamed points (off)."""
        if bool(on) != self.naming:
            self.naming = bool(on)
            self.naming_changed.emit(self.naming)

    def set_pending_level(self, label: str) -> None:
        label = normalize_level_name(label)
        if label != self.pending_level:
            self.pending_level = label
            self.pending_level_changed.emit(label)

    # ------------------------------------------------------------------------------------- edits (undoable)
    def place(self, position) -> int:
        """Place the pending level at ``position``; if that level exists, move it there. Returns its id.

        With ``naming`` off: always a new unnamed point; the pending level stays as it is."""
        if not self.naming:
            point_id = self.add(None, position)
            self.select(point_id)
            return point_id
        label = self.pending_level
        existing = self.find(label)
        if existing is not None:
            self.move(existing.id, position, existing.position.copy())
            point_id = existing.id
        else:
            point_id = self._next_id
            self.undo_stack.push(_AddPoint(self, Point(point_id, label, self._vec(position))))
        self.select(point_id)
        self.set_pending_level(self.next_free_level(label))
        return point_id

    def add(self, label: str | None, position) -> int:
        """Add a point with an explicit level (undoable)."""
        label = normalize_level_name(label) if label else None
        if label and self.find(label) is not None:
            raise LandmarkError(f"{label} is already placed on the {self.name}; move or rename that point")
        point_id = self._next_id
        self.undo_stack.push(_AddPoint(self, Point(point_id, label, self._vec(position))))
        return point_id

    def move(self, point_id: int, new_position, old_position=None) -> None:
        """Move a point (undoable). During a drag call ``move_live`` and then this once with the start."""
        point = self._points[point_id]
        old = point.position.copy() if old_position is None else self._vec(old_position)
        new = self._vec(new_position)
        if np.allclose(old, new) and np.allclose(point.position, new):
            return
        self.undo_stack.push(_MovePoint(self, point_id, old, new))

    def move_live(self, point_id: int, position) -> None:
        """Move without an undo entry (while dragging)."""
        self._points[point_id].position = self._vec(position)
        self.changed.emit()

    def rename(self, point_id: int, label: str | None) -> None:
        """Give a point another level name (undoable); refuses a name another point already has."""
        label = normalize_level_name(label) if label else None
        point = self._points[point_id]
        if label == point.label:
            return
        other = self.find(label) if label else None
        if other is not None:
            raise LandmarkError(f"{label} is already placed on the {self.name}; delete or rename that point "
                                "first")
        self.undo_stack.push(_RenamePoint(self, point_id, point.label, label))

    def rename_many(self, labels: dict[int, str | None], text: str = "Rename points") -> None:
        """Rename several points in one undo step ({point id: new label or None}); the names after the change
        must be unique (swaps are allowed). Ids that no longer exist are ignored."""
        new = {pid: (normalize_level_name(lb) if lb else None) for pid, lb in labels.items() if pid in self._points}
        new = {pid: lb for pid, lb in new.items() if lb != self._points[pid].label}
        if not new:
            return
        after = [new.get(p.id, p.label) for p in self._points.values()]
        dup = sorted({lb for lb in after if lb and after.count(lb) > 1}, key=level_index)
        if dup:
            raise LandmarkError(f"{', '.join(dup)} would be placed twice on the {self.name}; delete or rename the "
                                "other point first")
        self.undo_stack.push(_RenameMany(self, {pid: self._points[pid].label for pid in new}, new, text))

    def remove(self, point_id: int) -> None:
        if point_id in self._points:
            self.undo_stack.push(_RemovePoint(self, self._points[point_id]))

    def remove_selected(self) -> bool:
        if self.selected is None or self.selected not in self._points:
            return False
        self.remove(self.selected)
        return True

    def replace_all(self, labels: list, positions, text: str = "Import landmarks", undoable: bool = True) -> None:
        """Replace every point (one undo step when ``undoable``; loading a session is not undoable)."""
        new = [Point(0, normalize_level_name(lb) if lb else None, self._vec(p))
               for lb, p in zip(labels, np.asarray(positions, float).reshape(-1, self.dim), strict=True)]
        if undoable:
            self.undo_stack.push(_ReplaceAll(self, new, text))
        else:
            self._set_all(new)

    def map_positions(self, to_new) -> None:
        """Every point moved by ``to_new`` (an (n, dim) array of positions to the (n, dim) new ones), ids, names and
        the selection kept. Not an undo step of its own: the caller's (the X-ray turned) undoes it by mapping back,
        so the steps before it still find their points."""
        points = self._snapshot()
        if points:
            moved = np.asarray(to_new(np.array([p.position for p in points], float)), float).reshape(-1, self.dim)
            for point, position in zip(points, moved, strict=True):
                point.position = self._vec(position)
            self._restore(points)

    # ------------------------------------------------------------------------------------- selection
    def select(self, point_id: int | None) -> None:
        if point_id != self.selected:
            self.selected = point_id
            self.selection_changed.emit(point_id)

    # ------------------------------------------------------------------------------------- conversion
    def to_landmarks(self):
        """Landmarks3D (named points only, CT) or Landmarks2D (X-ray) in level order."""
        pts = self.points()
        if self.dim == 3:
            named = [p for p in pts if p.label]
            return Landmarks3D([p.label for p in named], np.array([p.position for p in named]).reshape(-1, 3),
                               source=f"{self.name} points in the window")
        return Landmarks2D([p.label for p in pts], np.array([p.position for p in pts]).reshape(-1, 2),
                           source=f"{self.name} points in the window")

    def to_records(self) -> list[dict]:
        key = "position_lps_mm" if self.dim == 3 else "uv_px"
        return [{"label": p.label, key: [float(x) for x in p.position]} for p in self.points()]

    # ------------------------------------------------------------------------------------- internals
    def _spine_key(self, point: Point) -> float:
        """Position along the spine, head first: X-ray row v (top of the image first); CT -z (LPS +z is
        superior); the id breaks ties."""
        return float(point.position[1]) if self.dim == 2 else -float(point.position[2])

    def _vec(self, position) -> np.ndarray:
        v = np.asarray(position, dtype=np.float64).reshape(-1)
        if v.shape != (self.dim,) or not np.all(np.isfinite(v)):
            raise LandmarkError(f"a {self.name} point needs {self.dim} finite coordinates")
        return v.copy()

    def _insert(self, point: Point) -> None:
        self._points[point.id] = Point(point.id, point.label, point.position.copy())
        self._next_id = max(self._next_id, point.id + 1)
        self.changed.emit()

    def _delete(self, point_id: int) -> None:
        self._points.pop(point_id, None)
        if self.selected == point_id:
            self.select(None)
        self.changed.emit()

    def _set_position(self, point_id: int, position: np.ndarray) -> None:
        self._points[point_id].position = position.copy()
        self.changed.emit()

    def _set_label(self, point_id: int, label: str | None) -> None:
        self._points[point_id].label = label
        self.changed.emit()

    def _set_labels(self, labels: dict[int, str | None]) -> None:
        for pid, label in labels.items():
            if pid in self._points:
                self._points[pid].label = label
        self._refresh_pending()
        self.changed.emit()

    def _set_all(self, points: list[Point]) -> None:
        self._points = {}
        for point in points:
            point.id = self._next_id
            self._next_id += 1
            self._points[point.id] = Point(point.id, point.label, point.position.copy())
        self.select(None)
        self._refresh_pending()
        self.changed.emit()

    def _snapshot(self) -> list[Point]:
        return [Point(p.id, p.label, p.position.copy()) for p in self._points.values()]

    def _restore(self, points: list[Point]) -> None:
        self._points = {p.id: Point(p.id, p.label, p.position.copy()) for p in points}
        if self.selected not in self._points:
            self.select(None)
        self._refresh_pending()
        self.changed.emit()

    def _refresh_pending(self) -> None:
        """After bulk changes: propose the level after the last one placed if the current one is taken."""
        labels = self.labels()
        if not labels:
            return
        if self.pending_level in labels or len(labels) == len(self._points):
            self.set_pending_level(self.next_free_level(labels[-1]))


# ------------------------------------------------------------------------------------------ commands

def _fmt(label: str | None) -> str:
    return label or "unnamed point"


class _AddPoint(QtGui.QUndoCommand):
    def __init__(self, store: PointStore, point: Point):
        super().__init__(f"Place {_fmt(point.label)} on {store.name}")
        self.store, self.point = store, point

    def redo(self):
        self.store._insert(self.point)
        if self.point.label and self.store.pending_level == self.point.label:
            self.store.set_pending_level(self.store.next_free_level(self.point.label))

    def undo(self):
        self.store._delete(self.point.id)
        if self.point.label:  # the picker goes back to the level undone: the next click places it again
            self.store.set_pending_level(self.point.label)


class _RemovePoint(QtGui.QUndoCommand):
    def __init__(self, store: PointStore, point: Point):
        super().__init__(f"Delete {_fmt(point.label)} from {store.name}")
        self.store, self.point = store, Point(point.id, point.label, point.position.copy())

    def redo(self):
        self.store._delete(self.point.id)

    def undo(self):
        self.store._insert(self.point)


class _MovePoint(QtGui.QUndoCommand):
    def __init__(self, store: PointStore, point_id: int, old: np.ndarray, new: np.ndarray):
        super().__init__(f"Move {_fmt(store.get(point_id).label)} on {store.name}")
        self.store, self.point_id, self.old, self.new = store, point_id, old, new

    def redo(self):
        self.store._set_position(self.point_id, self.new)

    def undo(self):
        self.store._set_position(self.point_id, self.old)


class _RenamePoint(QtGui.QUndoCommand):
    def __init__(self, store: PointStore, point_id: int, old: str | None, new: str | None):
        super().__init__(f"Rename {_fmt(old)} to {_fmt(new)} on {store.name}")
        self.store, self.point_id, self.old, self.new = store, point_id, old, new

    def redo(self):
        self.store._set_label(self.point_id, self.new)

    def undo(self):
        self.store._set_label(self.point_id, self.old)


class _RenameMany(QtGui.QUndoCommand):
    def __init__(self, store: PointStore, old: dict, new: dict, text: str):
        super().__init__(f"{text} ({store.name})")
        self.store, self.old, self.new = store, dict(old), dict(new)

    def redo(self):
        self.store._set_labels(self.new)

    def undo(self):
        self.store._set_labels(self.old)


class _ReplaceAll(QtGui.QUndoCommand):
    def __init__(self, store: PointStore, points: list[Point], text: str):
        super().__init__(f"{text} ({store.name})")
        self.store, self.before = store, store._snapshot()
        self.after = []
        for point in points:
            self.after.append(Point(store._next_id, point.label, point.position))
            store._next_id += 1

    def redo(self):
        self.store._restore(self.after)

    def undo(self):
        self.store._restore(self.before)
