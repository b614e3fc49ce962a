"""NRRD ``.nrrd`` / ``.nhdr`` CT (pynrrd header, own bounded payload reader) and writing a CT as NRRD.

``space directions`` (one row per axis) and ``space origin`` (centre of the first voxel) in the named ``space``:
LPS as is, RAS and LAS converted to LPS; spaces without anatomical meaning are taken as LPS and flagged in
``meta``. The payload (raw or gzip) is read up to the size the header gives and no more.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError, describe
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.atomic import atomic_write
from carmreg.logic.io.limits import inflate_exactly, read_exactly, regular_file
from carmreg.logic.io.volume_checks import as_hu, check_memory, checked_volume, spatial_3d

NRRD_SPACE_TO_LPS = {
    "left-posterior-superior": (1.0, 1.0, 1.0), "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0), "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0), "las": (1.0, -1.0, 1.0),
}
"""Sign flips taking a point of each anatomical NRRD space to LPS."""


def load_nrrd(path: Path) -> Volume:
    import nrrd

    errors = (nrrd.NRRDError, OSError, EOFError, UnicodeError, ValueError, KeyError, IndexError, TypeError,
              OverflowError, zlib.error)
    try:
        with open(path, "rb") as handle:
            header = nrrd.read_header(handle)
            data_offset = handle.tell()
        sizes = [int(s) for s in np.atleast_1d(header.get("sizes", []))]
    except errors as exc:
        raise InputFileError(f"{path}: not a readable NRRD header ({describe(exc, 100)})") from None
    check_memory(sizes, 4 + _nrrd_itemsize(header), path)
    try:
        data = _nrrd_data(path, header, data_offset, sizes)
    except InputFileError:
        raise
    except errors as exc:
        raise InputFileError(f"{path}: the NRRD voxel data cannot be read; the file or its data file is "
                             f"probably truncated or missing ({describe(exc, 80)})") \
            from None
    data = as_hu(spatial_3d(data, path))
    affine, meta = _nrrd_affine(header, path)
    return checked_volume(data, affine, path, meta)


def _nrrd_data(path: Path, header: dict, data_offset: int, sizes: list[int]) -> np.ndarray:
    """The voxels (index order F), reading exactly the bytes ``sizes`` and ``type`` announce from the attached
    data or the one regular ``data file``: raw, gzip, bzip2 (inflated with a bound) or ASCII."""
    import bz2

    from nrrd.reader import _determine_datatype

    dtype = _determine_datatype(header)
    n_values = int(np.prod(sizes, dtype=np.int64))
    n_bytes = n_values * dtype.itemsize
    data_name = header.get("data file", header.get("datafile"))
    if data_name is not None:
        if str(data_name).upper().startswith("LIST") or len(str(data_name).split()) > 1:
            raise InputFileError(f"{path}: NRRD with one data file per slice ({data_name!r}) is not supported; "
                                 "save it as a single .nrrd")
        data_path = Path(data_name) if os.path.isabs(data_name) else path.parent / data_name
        regular_file(data_path, f"NRRD data file (named in {path.name})")
        data_offset = 0
    else:
        data_path = path
    encoding = str(header.get("encoding", "raw")).lower()
    line_skip = int(header.get("line skip", header.get("lineskip", 0)))
    byte_skip = int(header.get("byte skip", header.get("byteskip", 0)))
    if line_skip < 0 or byte_skip < -1:
        raise InputFileError(f"{path}: NRRD line skip {line_skip} / byte skip {byte_skip} are not valid")
    with open(data_path, "rb") as handle:
        handle.seek(data_offset)
        for _ in range(line_skip):
            handle.readline()
        if encoding in ("ascii", "text", "txt"):
            values = np.fromfile(handle, dtype, count=n_values, sep=" ")
            if values.size < n_values:
                raise InputFileError(f"{path}: the NRRD holds {values.size} ASCII values but its header needs "
                                     f"{n_values}; the file is truncated")
            return values.reshape(sizes, order="F")
        if encoding == "raw":
            handle.seek(-n_bytes, os.SEEK_END) if byte_skip == -1 else handle.seek(byte_skip, os.SEEK_CUR)
            raw = read_exactly(handle, n_bytes, path, "NRRD voxel data")
        elif encoding in ("gzip", "gz", "bzip2", "bz2"):
            skip = max(byte_skip, 0)
            inflater = bz2.BZ2Decompressor() if encoding.startswith("bz") else zlib.decompressobj(
                zlib.MAX_WBITS | 16)
            raw = inflate_exactly(handle, n_bytes + skip, path, "NRRD voxel data", decompressor=inflater)
            raw = raw[skip:] if skip else raw
        else:
            raise InputFileError(f"{path}: NRRD encoding {encoding!r} is not supported (raw, gzip, bzip2, ascii)")
    return np.frombuffer(raw, dtype=dtype, count=n_values).reshape(sizes, order="F")


def _nrrd_itemsize(header: dict) -> int:
    """Bytes per voxel from the NRRD 'type' name (an estimate for the memory check)."""
    name = str(header.get("type", "")).lower()
    if "char" in name or "8" in name:
        return 1
    if "short" in name or "16" in name:
        return 2
    if "long" in name or "64" in name or "double" in name:
        return 8
    return 4


def _nrrd_affine(header: dict, path: Path) -> tuple[np.ndarray, dict]:
    """ijk -> LPS from 'space', 'space directions' (rows = axes) and 'space origin' (or 'spacings')."""
    meta = {"format": "NRRD"}
    space = str(header.get("space", "")).lower()
    flips = NRRD_SPACE_TO_LPS.get(space)
    if flips is None:
        flips = (1.0, 1.0, 1.0)
        meta["warning_orientation"] = (f"NRRD space {space or 'not given'!r} has no anatomical meaning; "
                                       "taken as LPS, check left/right in the views")
    affine = np.eye(4)
    directions = header.get("space directions")
    if directions is not None:
        try:
            rows = np.array([d for d in np.asarray(directions, dtype=float) if np.all(np.isfinite(d))])
            origin = header.get("space origin")
            origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=float).ravel()
        except (TypeError, ValueError):
            rows, origin = np.zeros(0), np.zeros(0)
        if rows.shape != (3, 3) or origin.shape != (3,):
            raise InputFileError(f"{path}: NRRD 'space directions' / 'space origin' do not describe 3 "
                                 "spatial axes")
        affine[:3, :3] = rows.T
        affine[:3, 3] = origin
    else:
        try:
            spacings = np.asarray(header.get("spacings", [1.0, 1.0, 1.0]), dtype=float).ravel()
        except (TypeError, ValueError):
            spacings = np.zeros(0)
        if spacings.shape != (3,):
            raise InputFileError(f"{path}: NRRD 'spacings' does not give 3 spacings")
        affine[:3, :3] = np.diag(np.where(np.isfinite(spacings), spacings, 1.0))
        meta["warning_orientation"] = "NRRD has no 'space directions'; axes taken as LPS from the origin"
    return np.diag([*flips, 1.0]) @ affine, meta


def write_volume_nrrd(path: str | Path, volume: Volume, compress: bool = True) -> Path:
    """Write a Volume as NRRD in LPS (space left-posterior-superior), atomically; dtype kept (int16 stays)."""
    import nrrd

    affine = volume.ijk_to_lps
    header = {"space": "left-posterior-superior", "space directions": affine[:3, :3].T.copy(),
              "space origin": affine[:3, 3].copy(), "kinds": ["domain", "domain", "domain"],
              "encoding": "gzip" if compress else "raw", "endian": "little"}
    data = np.asarray(volume.hu)
    atomic_write(path, lambda tmp: nrrd.write(str(tmp), data, header, index_order="F", compression_level=1))
    return Path(path)
