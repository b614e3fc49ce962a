"""An X-ray, its detector and its clicks turned by one of the shape-keeping orientations (``ORIENTATIONS``).

Used two ways: the orientation checks register the image turned (``click_orientation``), and the user who knows a
display was stored mirrored or rotated has it turned back before registering (``--orient-xray``, ``turned_xray``):
a refused display (``outcome.refused_display``) names the orientation in which the image matches the CT, and that
name turns it so.

Turning is a relabelling of pixels: pixel (u, v) = (column, row) of the stored image, 0-based centres, lands at
``orient_uv((u, v))``; the detector keeps its source, plane, pixel size and radial distortion, so its size, pixel
spacing (swapped by a quarter turn) and principal point turn with the pixels. A turn of the display is a turn of
the camera about its principal ray (a mirror, its reflection): the turned image on the turned detector is what the
C-arm would have recorded with its camera so turned (``Testing/Logic/registration/test_click_orientation.py``). So
an acquisition displayed turned, turned back, is the acquisition on its own detector again.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from carmreg.logic.errors import CarmRegError
from carmreg.logic.geometry.camera import CarmIntrinsics
from carmreg.logic.io.landmarks import Landmarks2D
from carmreg.logic.io.xray_image import XrayImage

ORIENTATIONS = {"as-stored": lambda a: a, "mirrored-left-right": lambda a: a[:, ::-1],
                "flipped-up-down": lambda a: a[::-1], "turned-180": lambda a: a[::-1, ::-1],
                "turned-90": lambda a: np.rot90(a, 1), "turned-270": lambda a: np.rot90(a, -1),
                "turned-90-and-mirrored": lambda a: np.rot90(a, 1)[:, ::-1],
                "turned-270-and-mirrored": lambda a: np.rot90(a, -1)[:, ::-1]}
"""The eight orientations an image keeps its pixel grid in (the turns of a square and their mirrors; np.rot90 turns
counter-clockwise). The last two transpose the image: ``turned-270-and-mirrored`` about its main diagonal,
``turned-90-and-mirrored`` about the other. The image checks compare every one that keeps a detector's shape with
the CT (``appearance.orientation_scores``: all eight on a square detector)."""

QUARTER_TURNED = ("turned-90", "turned-270", "turned-90-and-mirrored", "turned-270-and-mirrored")
"""The orientations that swap the image's columns and rows (and so its size and pixel spacing)."""


def orient_uv(uv_px: np.ndarray, name: str, size_px: tuple[int, int]) -> np.ndarray:
    """Where pixels (u, v) = (column, row) of the stored image, ``size_px`` = (columns, rows), land in its
    orientation ``ORIENTATIONS[name]`` (0-based pixel centres; np.rot90 turns counter-clockwise)."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    u, v = uv[:, 0], uv[:, 1]
    right, bottom = size_px[0] - 1.0 - u, size_px[1] - 1.0 - v
    turned = {"as-stored": (u, v), "mirrored-left-right": (right, v), "flipped-up-down": (u, bottom),
              "turned-180": (right, bottom), "turned-90": (v, right), "turned-270": (bottom, u),
              "turned-90-and-mirrored": (bottom, right), "turned-270-and-mirrored": (v, u)}[name]
    return np.stack(turned, axis=1)


TURNS = tuple(name for name in ORIENTATIONS if name != "as-stored")
"""The orientations a user may have the X-ray turned by (``--orient-xray``, the window's and the Slicer module's
X-ray orientation)."""

UNDONE_BY = {**{name: name for name in ORIENTATIONS}, "turned-90": "turned-270", "turned-270": "turned-90"}
"""The orientation that turns each orientation's image back to the image as stored (a quarter turn: the other one;
every other orientation, the transposes included, undoes itself)."""


def turned_size(size_px: tuple[int, int], name: str) -> tuple[int, int]:
    """(columns, rows) of an image of ``size_px`` (columns, rows) turned by ``name``: swapped by ``QUARTER_TURNED``."""
    return _turned_pair(size_px, name)


def stored_uv(uv_px: np.ndarray, name: str, stored_size_px: tuple[int, int]) -> np.ndarray:
    """Where pixels (u, v) of the image turned by ``name`` lie on the image as stored (``stored_size_px`` =
    (columns, rows) as stored): the inverse of ``orient_uv``, ``stored_uv(orient_uv(uv, name, s), name, s) == uv``."""
    return orient_uv(uv_px, UNDONE_BY[name], turned_size(stored_size_px, name))


def composed(first: str, then: str) -> str:
    """The orientation that turns an image as ``first`` and then ``then`` do, one after the other (the eight
    ``ORIENTATIONS`` are closed under it: a quarter turn and a mirror make a transpose)."""
    probe = np.arange(6).reshape(2, 3)
    want = ORIENTATIONS[then](ORIENTATIONS[first](probe))
    return next(name for name, turn in ORIENTATIONS.items()
                if turn(probe).shape == want.shape and np.array_equal(turn(probe), want))


def stored_image(image: np.ndarray, name: str) -> np.ndarray:
    """An image on the turned X-ray's grid (a DRR, an overlay: rows, columns[, channels]) put back on the grid of
    the X-ray as stored; the inverse of ``ORIENTATIONS[name]``."""
    return np.ascontiguousarray(ORIENTATIONS[UNDONE_BY[name]](image))


def _turned_pair(pair, name: str) -> tuple | None:
    """A (column, row) pair (size, pixel spacing) of the image turned by ``name``: swapped by ``QUARTER_TURNED``."""
    if pair is None:
        return None
    return tuple(reversed(pair)) if name in QUARTER_TURNED else tuple(pair)


def turned_intrinsics(intr: CarmIntrinsics, name: str) -> CarmIntrinsics:
    """The detector of the image turned by ``ORIENTATIONS[name]`` (module docstring); sources and distortion kept."""
    (u0, v0), = orient_uv(np.array([intr.principal_point_px], float), name, intr.size_px)
    return CarmIntrinsics(intr.sdd_mm, _turned_pair(intr.pixel_spacing_mm, name), _turned_pair(intr.size_px, name),
                          (float(u0), float(v0)), dict(intr.sources), intr.distortion_mm)


def turned_clicks(clicks: Landmarks2D, name: str, size_px: tuple[int, int]) -> Landmarks2D:
    """The clicks where orientation ``name`` of the image (``size_px`` = (columns, rows) as stored) shows them, their
    pixel spacing turned too; names stay with their clicks (they are anatomy)."""
    return Landmarks2D(list(clicks.labels), orient_uv(clicks.uv_px, name, size_px), clicks.source,
                       _turned_pair(clicks.pixel_spacing_mm, name))


def turn_advice(name: str | None) -> str:
    """How to have the file registered in orientation ``name`` (None: no turn CarmReg offers does), as the end of a
    sentence: the window's, the Slicer module's and the command line's way to the same turn."""
    if name is None:
        return ""
    if name == "as-stored":
        return (", or register the file as stored: X-ray orientation \"shown as stored\" (the window's step 1, the "
                "Slicer module's Inputs) or, on the command line, without --orient-xray")
    return (f", or have it turned: X-ray orientation \"shown {name.replace('-', ' ')}\" (the window's step 1, the "
            f"Slicer module's Inputs) or, on the command line, --orient-xray {name}")


def turned_xray(xray: XrayImage, name: str) -> XrayImage:
    """``xray`` turned by ``ORIENTATIONS[name]`` as the user asked (``--orient-xray``): its pixels and its detector
    (``turned_intrinsics``; none while the geometry is incomplete), recorded in ``sources["orientation"]`` (result.json
    ``inputs.geometry_sources``) and ``meta["turned"]`` (the name; result.json ``inputs.xray_turned``). "as-stored"
    returns ``xray`` itself; an unknown name is a CarmRegError naming the choices."""
    if name == "as-stored":
        return xray
    if name not in TURNS:
        raise CarmRegError(f"X-ray orientation '{name}' is not one of: {', '.join(TURNS)}")
    pixels = np.ascontiguousarray(ORIENTATIONS[name](xray.pixels))
    intrinsics = None if xray.intrinsics is None else turned_intrinsics(xray.intrinsics, name)
    sources = {**xray.sources, "orientation": f"turned {name.replace('-', ' ')} as the user asked, before registering"}
    return dataclasses.replace(xray, pixels=pixels, intrinsics=intrinsics, sources=sources,
                               meta={**xray.meta, "turned": name})
