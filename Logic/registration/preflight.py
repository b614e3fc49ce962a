"""What a registration needs before any stage runs, in words: one rule set for the command line, the window and
the Slicer module.

``preflight`` says what is missing as a list of sentences (empty = ready) and which level identification the
clicks ask for (``click_mode``): ``named`` (every X-ray click named), ``partly_named``, ``unnamed`` or
``image_only`` (no clicks). The window shows the sentences and enables Register; ``CarmRegLogic.prepare`` (the
command line's and the Slicer module's way in) raises the first one with ``Readiness.raise_first``: one line, exit
code 2. The rules:

- a CT, an X-ray and its geometry (source-to-detector distance, pixel spacing);
- at least 3 named CT centroids;
- named clicks: at least ``MIN_CLICKS`` levels named on both the CT and the X-ray (``pair_by_label``);
- unnamed or partly named clicks: at least ``MIN_CLICKS`` of them, and a labelling of consecutive CT levels that
  can carry them (``check_labelling_possible``); no clicks at all is valid (levels from the image alone);
- named clicks in spine order down the image, not head-down (``head_down``), and clicks (named or not) along the
  course the CT's levels take in an AP view, not across it (``across``): CarmReg registers an AP view shown head up.

``check_landmarks`` then refuses points outside the CT or the image and coincident points (it needs the loaded
CT and X-ray, so it runs in ``prepare``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.errors import GeometryError, InputFileError, LandmarkError
from carmreg.logic.geometry.camera import in_detector
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.image.turn import turn_advice
from carmreg.logic.io.landmarks import (
    Landmarks2D,
    Landmarks3D,
    Pairs,
    level_index,
    pair_by_label,
    spine_order_warnings,
)
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.labellings import (
    check_labelling_possible,
    ct_level_names,
    identifiable_clicks,
    principal_axis,
)

MIN_CLICKS = 3
"""X-ray clicks needed (named or not); zero clicks = the levels from the image alone."""
MIN_CT_CENTROIDS = 3


@dataclass
class Readiness:
    """``problems``: what is missing, one sentence each (empty = ready); ``mode``: see ``click_mode``;
    ``common_levels``: the levels named on both the CT and the X-ray, head to sacrum."""

    mode: str
    problems: list[str] = field(default_factory=list)
    common_levels: list[str] = field(default_factory=list)
    kinds: list[type] = field(default_factory=list)   # the CarmRegError class of each problem

    def add(self, kind: type, problem: str) -> None:
        self.kinds.append(kind)
        self.problems.append(problem)

    def raise_first(self) -> None:
        """Raise the first problem as its CarmRegError (the command line's one line, exit code 2)."""
        if self.problems:
            raise self.kinds[0](self.problems[0])


def click_mode(clicks: Landmarks2D) -> str:
    """``image_only`` (no clicks), ``named`` (every click named), ``unnamed`` (none named) or ``partly_named``."""
    n = len(clicks.labels)
    unnamed = sum(lb is None for lb in clicks.labels)
    if n == 0:
        return "image_only"
    if unnamed == 0:
        return "named"
    return "unnamed" if unnamed == n else "partly_named"


def preflight(ct_landmarks: Landmarks3D, clicks: Landmarks2D, *, ct_loaded: bool = True, xray_loaded: bool = True,
              geometry_known: bool = True, xray_size_px: tuple[int, int] | None = None) -> Readiness:
    """What stops a registration of these inputs now, in words (module docstring). ``xray_size_px``: the X-ray's
    (columns, rows) when known; clicks off it are not judged for their course (``check_landmarks`` names them)."""
    mode = click_mode(clicks)
    ct_names = ct_level_names(ct_landmarks)
    readiness = Readiness(mode, common_levels=[lb for lb in ct_names if lb in set(clicks.labels)])
    if not ct_loaded:
        readiness.add(InputFileError, "no CT loaded: load the preoperative CT")
    if not xray_loaded:
        readiness.add(InputFileError, "no X-ray loaded: load the intraoperative X-ray")
    elif not geometry_known:
        readiness.add(GeometryError, "the X-ray geometry is incomplete: give the source-to-detector distance and "
                                     "the pixel spacing (or choose a device preset)")
    if len(ct_names) < MIN_CT_CENTROIDS:
        readiness.add(LandmarkError, f"only {len(ct_names)} CT centroid(s) in {ct_landmarks.source or 'the CT'}: "
                                     f"label at least {MIN_CT_CENTROIDS} vertebrae in the CT")
        return readiness
    problem = (_clicks_problem(ct_landmarks, clicks, mode) or _head_down_problem(clicks)
               or _across_problem(ct_landmarks, clicks, mode, xray_size_px))
    if problem:
        readiness.add(LandmarkError, problem)
    return readiness


def _clicks_problem(ct_landmarks: Landmarks3D, clicks: Landmarks2D, mode: str) -> str | None:
    n = len(clicks.labels)
    try:
        if mode == "named":
            pair_by_label(ct_landmarks, clicks, MIN_CLICKS)
        elif mode != "image_only" and n < MIN_CLICKS:
            return (f"only {n} X-ray click(s): click the centres of at least {MIN_CLICKS} adjacent vertebrae (named "
                    "or not), or none to identify the levels from the image alone")
        elif mode != "image_only":
            check_labelling_possible(clicks, ct_level_names(ct_landmarks))
    except LandmarkError as exc:
        extra = ("; or leave the X-ray clicks unnamed for CarmReg to identify them"
                 if mode == "named" and n >= MIN_CLICKS else "")
        return str(exc) + extra
    return None


HEAD_DOWN_COS = -0.5
"""``head_down``: the cosine of the angle between the named clicks' head-to-sacrum direction and the image's down
(+row) beyond which they run head-down: 120 degrees. A geometric bound, not a tuned one: the landmark fit turns
the image in its plane at most 15 degrees from head up (``rx_deg``, ``fine.FineParameters.bounds``), and a run of
adjacent vertebrae is never bent a further 105 degrees; a display turned 180 degrees or flipped up-down puts them
near 180 degrees, a quarter turn near 90 (not caught here: ``across`` catches it)."""


def _head_to_sacrum(clicks: Landmarks2D) -> tuple[str, str, np.ndarray] | None:
    """(the most cranial named click's level, the most caudal's, the unit direction d = uv_caudal - uv_cranial in
    pixels (column, row)); None with fewer than two named clicks or when those two coincide."""
    named = sorted(((lb, uv) for lb, uv in zip(clicks.labels, clicks.uv_px, strict=True) if lb is not None),
                   key=lambda item: level_index(item[0]))
    if len(named) < 2:
        return None
    (cranial, a), (caudal, b) = named[0], named[-1]
    d = np.asarray(b, float) - np.asarray(a, float)
    length = float(np.linalg.norm(d))
    return None if length == 0.0 else (cranial, caudal, d / length)


def head_down(clicks: Landmarks2D) -> tuple[str, str] | None:
    """(the most cranial named click's level, the most caudal's) when their direction d (``_head_to_sacrum``) points
    up the image, ``d_row < HEAD_DOWN_COS``: the image shows the head at the bottom (a display turned 180 degrees or
    flipped up-down) or the names are reversed; None otherwise or with fewer than two named clicks."""
    found = _head_to_sacrum(clicks)
    if found is None or found[2][1] >= HEAD_DOWN_COS:
        return None
    return found[0], found[1]


def _head_down_problem(clicks: Landmarks2D) -> str | None:
    """``head_down`` in words, with the turn that shows the image head up (``image.turn.turn_advice``)."""
    found = head_down(clicks)
    if found is None:
        return None
    cranial, caudal = found
    return (f"the named X-ray clicks run head-down ({cranial} lies below {caudal} on the image): CarmReg registers "
            "an AP view shown head up, so the display is turned 180 degrees or flipped up-down, or the names are "
            "reversed; check the names" + turn_advice("turned-180")
            + " (\"flipped up down\", flipped-up-down, if the image then shows the patient mirrored)")


QUARTER_TURN_DEG = 45.0
"""``across``: the angle between the clicks' axis and the course of every run of CT levels they could be, as an AP
view shown head up draws it, beyond which the clicks run across the image: nearer a quarter turn than head up. A
geometric bound, not a tuned one: the landmark fit turns the image at most 15 degrees in its plane and the C-arm at
most 15 degrees out of it (``fine.FineParameters.bounds``), which moves the drawn course of a few adjacent levels by
at most about 30 degrees; a display turned a quarter moves it by 90 degrees less that."""
ELONGATED = 2.0
"""``across`` judges clicks only when they lie along a line: their spread along their axis at least this many times
the spread across it (singular values of the centred clicks), else their axis says nothing."""


@dataclass(frozen=True)
class Across:
    """Clicks that run across the image (``across``): ``angle_deg``, the smallest angle between their axis and the
    drawn course of a run of CT levels they could be, that run's end levels ``levels`` (head first), and ``turn``,
    the ``image.turn`` name that shows named clicks head up (None for unnamed clicks: either quarter turn may)."""

    angle_deg: float
    levels: tuple[str, str]
    turn: str | None


def _drawn_course(points_lps_mm: np.ndarray) -> np.ndarray:
    """The axis of CT points as an AP view shown head up draws them: (column, row) ~ (L, -S) (``geometry.camera``:
    columns toward the patient's left, rows toward the feet), perspective and the C-arm's small turns left out."""
    return principal_axis(np.stack([points_lps_mm[:, 0], -points_lps_mm[:, 2]], axis=1))[0]


def _line_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between the lines along unit vectors ``a`` and ``b``, degrees in [0, 90]."""
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))


def _candidate_runs(ct_landmarks: Landmarks3D, clicks: Landmarks2D, mode: str) -> list[list[str]]:
    """The CT levels the clicks could be, head first, one list per labelling: the names given (named clicks), else
    every run of as many adjacent CT levels as there are clicks (unnamed or partly named)."""
    if mode == "named":
        known = set(ct_landmarks.labels)
        return [sorted((lb for lb in clicks.labels if lb in known), key=level_index)]
    names, n = ct_level_names(ct_landmarks), len(clicks.labels)
    return [names[s:s + n] for s in range(len(names) - n + 1)]


def across(ct_landmarks: Landmarks3D, clicks: Landmarks2D, mode: str | None = None) -> Across | None:
    """Whether the clicks run across the image: the angle between their axis (pixels) and the drawn course
    (``_drawn_course``) of every run of CT levels they could be (``_candidate_runs``), mirrored left-right or not,
    exceeds ``QUARTER_TURN_DEG``. None when they do not, when they do not lie along a line (``ELONGATED``) or when no
    run has two CT levels. With two named clicks or more, ``turn`` shows them head up: ``turned-90`` when the head
    lies right of the sacrum on the image (np.rot90 turns counter-clockwise), else ``turned-270``."""
    uv = np.asarray(clicks.uv_px, float).reshape(-1, 2)
    if len(uv) < 2:
        return None
    axis, elongation = principal_axis(uv)
    if elongation < ELONGATED:
        return None
    points = dict(zip(ct_landmarks.labels, np.asarray(ct_landmarks.points_lps_mm, float), strict=True))
    best = None
    for run in _candidate_runs(ct_landmarks, clicks, mode or click_mode(clicks)):
        if len(run) < 2:
            continue
        course = _drawn_course(np.array([points[lb] for lb in run]))
        angle = min(_line_angle_deg(axis, course), _line_angle_deg(axis, course * (-1.0, 1.0)))
        if best is None or angle < best[0]:
            best = (angle, (run[0], run[-1]))
    if best is None or best[0] <= QUARTER_TURN_DEG:
        return None
    named = _head_to_sacrum(clicks)
    turn = None if named is None else ("turned-90" if named[2][0] < 0 else "turned-270")
    return Across(best[0], best[1], turn)


def _across_problem(ct_landmarks: Landmarks3D, clicks: Landmarks2D, mode: str,
                    xray_size_px: tuple[int, int] | None) -> str | None:
    """``across`` in words, with the quarter turn that shows the image head up (both when the clicks are unnamed);
    None for clicks off an image of ``xray_size_px`` (a click in the wrong place, not a turned display)."""
    if mode == "image_only" or (xray_size_px is not None and not all(
            in_detector(uv, xray_size_px) for uv in np.asarray(clicks.uv_px, float).reshape(-1, 2))):
        return None
    found = across(ct_landmarks, clicks, mode)
    if found is None:
        return None
    first, last = found.levels
    said = (f"the X-ray clicks run across the image ({found.angle_deg:.0f} degrees from the course {first}-{last} "
            "takes in the CT): CarmReg registers an AP view shown head up, so the display is turned a quarter")
    if found.turn is not None:
        return said + "; check the clicks" + turn_advice(found.turn)
    return (said + ": have it turned so that the head is at the top: X-ray orientation \"shown turned 90\" (a quarter "
            "counter-clockwise) or \"shown turned 270\" (clockwise) (the window's step 1, the Slicer module's Inputs) "
            "or, on the command line, --orient-xray turned-90 or turned-270")


def given_pairs(ct_landmarks: Landmarks3D, clicks: Landmarks2D) -> tuple[Pairs | None, list[str]]:
    """The clicks paired with the CT by name when every click is named, else None; and the plausibility notes
    (levels on one side only, spine order). Call after ``preflight``."""
    if click_mode(clicks) == "named":
        pairs = pair_by_label(ct_landmarks, clicks, MIN_CLICKS)
        return pairs, list(pairs.notes)
    return None, spine_order_warnings(ct_landmarks)


def check_landmarks(ct: Volume, ct_landmarks: Landmarks3D, xray: XrayImage, clicks: Landmarks2D) -> None:
    """Refuse points outside the CT or the image, and degenerate (coincident) point sets."""
    outside = [lb for lb, inside in zip(ct_landmarks.labels, ct.contains_lps(ct_landmarks.points_lps_mm),
                                        strict=True) if not inside]
    if outside:
        raise LandmarkError(f"CT landmark(s) {', '.join(outside)} in {ct_landmarks.source or 'the CT landmarks'} "
                            f"lie outside the CT volume {ct.source}: check the landmark file's coordinate system "
                            "(LPS vs RAS) and that it belongs to this CT")
    cols, rows = xray.size_px
    used = identifiable_clicks(clicks, ct_level_names(ct_landmarks))
    uv_all = np.asarray(clicks.uv_px, float).reshape(-1, 2)[used]
    off = [clicks.labels[i] or f"unnamed click {i + 1}" for i, uv in zip(used, uv_all, strict=True)
           if not in_detector(uv, (cols, rows))]
    if off:
        raise LandmarkError(f"X-ray landmark(s) {', '.join(off)} lie outside the {cols}x{rows} image "
                            f"{xray.source}: check they are (column, row) pixels of this X-ray")
    for name, pts in (("CT", ct_landmarks.points_lps_mm), ("X-ray", uv_all)):
        if len(pts) < 2:
            continue
        d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
        if d.min() < 1.0:
            raise LandmarkError(f"two {name} landmarks are less than 1 {'mm' if name == 'CT' else 'px'} apart: "
                                "each level needs its own centroid")
