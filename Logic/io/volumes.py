"""Reading and writing CT volumes: DICOM series, NIfTI, NRRD, MetaImage -> ``Volume`` (HU, LPS mm).

Every reader returns ``Volume(hu, ijk_to_lps)`` with ``hu[i, j, k]`` (i fastest in the file) and the 4x4
voxel-centre-index -> LPS mm affine (see ``Logic/volume.py``). HU stay int16 when the file's values are
integers that fit int16; otherwise they become float32.

Formats
-------
- DICOM series (a folder, or one slice file whose folder holds the series) or one enhanced multi-frame
  CT file: see the DICOM section below. CT only; slices sorted along the slice normal; spacing from
  ImagePositionPatient.
- NIfTI ``.nii`` / ``.nii.gz`` (nibabel): world is RAS; the sform is used when its code is set, else the
  qform, else nibabel's fallback (flagged in ``meta``). ``ijk_to_lps = diag(-1, -1, 1, 1) @ ijk_to_ras``.
  Scaling (scl_slope/scl_inter) is applied.
- NRRD ``.nrrd`` / ``.nhdr`` (pynrrd): ``space directions`` (one row per axis) and ``space origin`` (centre
  of the first voxel) in the named ``space``: left-posterior-superior / LPS as is, right-anterior-superior
  / RAS and left-anterior-superior / LAS converted to LPS; spaces without anatomical meaning
  (scanner-xyz, 3D-right-handed, none) are taken as LPS and flagged in ``meta``.
- MetaImage ``.mha`` / ``.mhd`` (own reader): ``TransformMatrix`` (row a = LPS direction of index axis a,
  as ITK writes it), ``Offset`` (centre of the first voxel), ``ElementSpacing``, ``ElementType``,
  ``ElementDataFile`` LOCAL or one external raw file, ``CompressedData`` (zlib), byte order.
  MetaImage worlds are LPS (ITK); ``AnatomicalOrientation`` is recorded in ``meta`` only.

Every reader estimates the memory first and refuses volumes above ``MAX_VOLUME_BYTES`` (8 GiB). Every
reader refuses what would give a silently wrong volume: fewer than 2 voxels along an axis, NaN or infinite
voxel values, a singular or non-finite affine; and turns every failure of the underlying library on a
damaged file into an ``InputFileError`` naming the file.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.atomic import atomic_write
from carmreg.logic.io.limits import check_dicom_size, file_kind, inflate_exactly, read_exactly, regular_file
from carmreg.logic.io.xray import (
    DICOM_PARSE_ERRORS,
    describe,
    dicom_int,
    dicom_numbers,
    drop_unreadable_elements,
    quiet_libraries,
)

MAX_VOLUME_BYTES = 8 * 1024**3
"""Largest volume (bytes in memory) a reader accepts."""
MAX_CT_EXTENT_MM = 2100.0
"""Longest CT axis accepted (a whole-body scan is about 2 m)."""
MAX_CT_SECTION_MM2 = 1000.0 * 1000.0
"""Largest product of the two shorter axes (a CT field of view is at most about 700 mm)."""
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
SUPPORTED = "a DICOM series folder, .nii/.nii.gz, .nrrd/.nhdr or .mha/.mhd"


def load_volume(path: str | Path, *, series_uid: str | None = None) -> Volume:
    """Read a CT from a DICOM series folder (or one of its files), NIfTI, NRRD or MetaImage.

    series_uid: which DICOM series to read when the folder holds more than one.
    Raises InputFileError with an actionable message for anything a user can fix.
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: CT not found; give {SUPPORTED}")
    if not path.is_dir():
        regular_file(path, "CT")
        if path.stat().st_size == 0:
            raise InputFileError(f"{path}: file is empty")
    with quiet_libraries() as notes:
        try:
            volume = _read_any(path, series_uid)
        except OSError as exc:  # permission denied, I/O error, symlink loop: one line, not a traceback
            raise InputFileError(f"{getattr(exc, 'filename', None) or path}: the CT cannot be read "
                                 f"({exc.strerror or exc}); check its permissions or copy it again") from None
    if notes:
        volume.meta["library_warnings"] = notes
    return volume


def _read_any(path: Path, series_uid: str | None) -> Volume:
    if path.is_dir():
        return load_dicom_series(path, series_uid=series_uid)
    name = path.name.lower()
    if name.endswith((".nii", ".nii.gz")):
        return _load_nifti(path)
    if name.endswith((".nrrd", ".nhdr")):
        return _load_nrrd(path)
    if name.endswith((".mha", ".mhd")):
        return _load_metaimage(path)
    if name.endswith((".dcm", ".dicom", ".ima")) or _has_dicom_marker(path):
        return load_dicom_file(path, series_uid=series_uid)
    raise InputFileError(f"{path}: unknown CT format; give {SUPPORTED}")


def _has_dicom_marker(path: Path) -> bool:
    with open(path, "rb") as handle:
        return handle.read(132)[128:132] == b"DICM"


# ----------------------------------------------------------------------------------------------- shared

def check_memory(shape, bytes_per_voxel: int, path: Path | str) -> None:
    """Refuse a volume whose array would need more than MAX_VOLUME_BYTES (or with a negative size)."""
    if any(int(n) < 0 for n in shape):
        raise InputFileError(f"{path}: the header gives a negative image size {list(shape)}; the file is "
                             "damaged")
    n_bytes = float(np.prod([float(n) for n in shape])) * int(bytes_per_voxel)
    if n_bytes > MAX_VOLUME_BYTES:
        raise InputFileError(f"{path}: the volume {'x'.join(str(int(n)) for n in shape)} needs "
                             f"{n_bytes / 1024**3:.1f} GiB, more than the "
                             f"{MAX_VOLUME_BYTES / 1024**3:.0f} GiB limit; crop it to the spine or resample "
                             "it to coarser voxels first")


def as_hu(data: np.ndarray) -> np.ndarray:
    """int16 when the values are integers that fit int16 (no copy for int16), else float32."""
    if data.dtype == np.int16:
        return data
    if np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.bool_):
        if data.size == 0 or (data.min() >= -32768 and data.max() <= 32767):
            return data.astype(np.int16)
        return data.astype(np.float32)
    if not np.issubdtype(data.dtype, np.floating):
        raise InputFileError(f"voxel type {data.dtype} is not a number type; give a scalar CT in HU")
    data = data.astype(np.float32, copy=False)
    return data


def _checked_volume(data: np.ndarray, affine: np.ndarray, path: Path, meta: dict) -> Volume:
    """A Volume from reader output, refusing what would silently go wrong later: a flat or empty grid,
    NaN or infinite voxels (the DRR would be NaN), a singular or non-finite affine (``Volume`` checks)."""
    if min(data.shape) < 2:
        raise InputFileError(f"{path}: the volume is {'x'.join(str(n) for n in data.shape)} voxels; a CT "
                             "for registration needs at least 2 voxels along every axis (is it one slice?)")
    if np.issubdtype(data.dtype, np.floating):
        lo, hi = float(np.min(data)), float(np.max(data))
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise InputFileError(f"{path}: {int(np.count_nonzero(~np.isfinite(data)))} voxel(s) are NaN or "
                                 "infinite; fill them (e.g. with -1000 HU, air) before loading the CT")
    volume = Volume(data, affine, str(path), meta)
    check_extent(volume.shape, volume.spacing_mm, path)
    return volume


def check_extent(shape, spacing_mm, path: Path | str) -> None:
    """Refuse a CT whose physical box is beyond any patient (spacing in um or cm written as mm): every
    resampled level (``resample_isotropic``) is sized by this box, so it is checked before any is made."""
    extent_mm = np.asarray(shape, float) * np.asarray(spacing_mm, float)
    box = sorted(extent_mm)
    if box[-1] > MAX_CT_EXTENT_MM or box[0] * box[1] > MAX_CT_SECTION_MM2:
        spacing = ", ".join(f"{s:.4g}" for s in spacing_mm)
        raise InputFileError(f"{path}: the CT spans {' x '.join(f'{e:.0f}' for e in extent_mm)} mm "
                             f"({'x'.join(str(int(n)) for n in shape)} voxels of {spacing} mm), larger than a "
                             f"patient (at most {MAX_CT_EXTENT_MM:.0f} mm long, "
                             f"{MAX_CT_SECTION_MM2 ** 0.5:.0f} mm across): the voxel spacing in the header is "
                             "probably not in mm (um or cm?); fix it and save the CT again")


def _spatial_3d(data: np.ndarray, path: Path) -> np.ndarray:
    """Drop trailing singleton axes (e.g. NIfTI t=1); refuse anything that is not one 3D scalar volume."""
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise InputFileError(f"{path}: expected one 3D scalar volume, the file holds an array of shape "
                             f"{data.shape}; give a single CT volume (not a time series or vector image)")
    return data


# ----------------------------------------------------------------------------------------------- NIfTI

def _load_nifti(path: Path) -> Volume:
    import nibabel as nib

    try:
        image = nib.load(str(path))
        shape = image.shape
        itemsize = np.dtype(image.get_data_dtype()).itemsize
    except _nifti_errors() as exc:
        raise InputFileError(f"{path}: not a readable NIfTI file ({describe(exc, 100)})") from None
    check_memory(shape, 4 + itemsize, path)
    try:
        affine_ras, which = _nifti_affine(image)
    except _nifti_errors() as exc:
        raise InputFileError(f"{path}: the NIfTI orientation (sform/qform) cannot be read "
                             f"({describe(exc, 80)}); the header is damaged") from None
    try:
        data = _nifti_data(image, path)
    except _nifti_errors() as exc:
        raise InputFileError(f"{path}: the NIfTI voxel data cannot be read; the file is probably truncated "
                             f"({describe(exc, 80)}); copy it again") from None
    data = as_hu(_spatial_3d(np.asarray(data), path))
    meta = {"format": "NIfTI", "affine_from": which}
    if which == "fallback":
        meta["warning_orientation"] = ("NIfTI header has neither sform nor qform; orientation assumed, "
                                       "check left/right in the views")
    return _checked_volume(data, LPS_FROM_RAS @ affine_ras, path, meta)


def _nifti_errors() -> tuple:
    """What nibabel raises on a damaged or truncated file."""
    from nibabel.filebasedimages import ImageFileError
    from nibabel.spatialimages import HeaderDataError

    return (ImageFileError, HeaderDataError, OSError, EOFError, ValueError, TypeError, OverflowError,
            zlib.error, np.linalg.LinAlgError)


def _nifti_data(image, path: Path) -> np.ndarray:
    """Scaled voxel values; integer stored values with integer slope/intercept stay integers (no float64)
    as long as the scaled values fit int32."""
    proxy = image.dataobj
    slope, inter = float(getattr(proxy, "slope", 1.0)), float(getattr(proxy, "inter", 0.0))
    if not (np.isfinite(slope) and np.isfinite(inter)):
        raise InputFileError(f"{path}: NIfTI scaling scl_slope = {slope}, scl_inter = {inter} is not finite; "
                             "the header is damaged")
    if (np.issubdtype(image.get_data_dtype(), np.integer) and hasattr(proxy, "get_unscaled")
            and slope == round(slope) and inter == round(inter)):
        stored = np.asarray(proxy.get_unscaled())
        if slope == 1.0 and inter == 0.0:
            return stored
        extreme = max(abs(int(stored.min())), abs(int(stored.max()))) if stored.size else 0
        if abs(slope) * extreme + abs(inter) < 2**31:
            return stored.astype(np.int32) * np.int32(slope) + np.int32(inter)
    return np.asarray(np.asanyarray(proxy), dtype=np.float32)


def _nifti_affine(image) -> tuple[np.ndarray, str]:
    """ijk -> RAS affine: sform if coded, else qform if coded, else nibabel's fallback."""
    sform, s_code = image.get_sform(coded=True)
    if sform is not None and int(s_code) > 0:
        return np.asarray(sform, float), "sform"
    qform, q_code = image.get_qform(coded=True)
    if qform is not None and int(q_code) > 0:
        return np.asarray(qform, float), "qform"
    return np.asarray(image.affine, float), "fallback"


# ----------------------------------------------------------------------------------------------- NRRD

NRRD_SPACE_TO_LPS = {
    "left-posterior-superior": (1.0, 1.0, 1.0), "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0), "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0), "las": (1.0, -1.0, 1.0),
}
"""Sign flips taking a point of each anatomical NRRD space to LPS."""


def _load_nrrd(path: Path) -> Volume:
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
    data = as_hu(_spatial_3d(data, path))
    affine, meta = _nrrd_affine(header, path)
    return _checked_volume(data, affine, path, meta)


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


# ----------------------------------------------------------------------------------------------- MetaImage

METAIMAGE_TYPES = {
    "MET_CHAR": "i1", "MET_UCHAR": "u1", "MET_SHORT": "i2", "MET_USHORT": "u2", "MET_INT": "i4",
    "MET_UINT": "u4", "MET_LONG": "i4", "MET_ULONG": "u4", "MET_LONG_LONG": "i8", "MET_ULONG_LONG": "u8",
    "MET_FLOAT": "f4", "MET_DOUBLE": "f8",
}


def _load_metaimage(path: Path) -> Volume:
    """Read .mha (header + LOCAL data) or .mhd (+ one external raw file); see the module docstring."""
    header, data_offset = _read_metaimage_header(path)
    shape = _ints(header, "DimSize", path)
    if len(shape) != 3 and not (len(shape) == 4 and shape[3] == 1):
        raise InputFileError(f"{path}: MetaImage has {len(shape)} dimensions; expected a 3D volume")
    shape = shape[:3]
    if header.get("ElementNumberOfChannels", "1").strip() != "1":
        raise InputFileError(f"{path}: MetaImage has ElementNumberOfChannels = "
                             f"{header['ElementNumberOfChannels']!r}; give a scalar CT (one value per voxel)")
    dtype = _metaimage_dtype(header, path)
    check_memory(shape, 4 + dtype.itemsize, path)
    n_voxels = int(np.prod(shape))
    raw = _metaimage_bytes(path, header, data_offset, n_voxels * dtype.itemsize)
    data = np.frombuffer(raw, dtype=dtype, count=n_voxels).reshape(shape, order="F")
    meta = {"format": "MetaImage"}
    if "AnatomicalOrientation" in header:
        meta["anatomical_orientation"] = header["AnatomicalOrientation"]
    data = as_hu(data.astype(dtype.newbyteorder("=")))
    return _checked_volume(data, _metaimage_affine(header, path), path, meta)


def _read_metaimage_header(path: Path) -> tuple[dict, int]:
    """Parse 'Key = Value' lines up to and including ElementDataFile; return (header, byte offset after)."""
    header, offset = {}, 0
    with open(path, "rb") as handle:
        for _ in range(200):
            line = handle.readline()
            if not line:
                break
            offset += len(line)
            key, sep, value = line.decode("latin-1").partition("=")
            if not sep:
                continue
            header[_canonical_key(key.strip())] = value.strip()
            if _canonical_key(key.strip()) == "ElementDataFile":
                return header, offset
    raise InputFileError(f"{path}: not a MetaImage header (no 'ElementDataFile = ...' line)")


_KEYS = ("ObjectType", "NDims", "DimSize", "ElementSpacing", "ElementSize", "ElementType", "ElementDataFile",
         "Offset", "Origin", "Position", "TransformMatrix", "Rotation", "Orientation", "CompressedData",
         "CompressedDataSize", "BinaryDataByteOrderMSB", "ElementByteOrderMSB", "HeaderSize",
         "ElementNumberOfChannels", "AnatomicalOrientation")


def _canonical_key(key: str) -> str:
    """MetaIO keys are matched case-insensitively."""
    for known in _KEYS:
        if key.lower() == known.lower():
            return known
    return key


def _floats(header: dict, keys, default, path: Path) -> np.ndarray:
    for key in keys:
        if key in header:
            try:
                return np.array([float(x) for x in header[key].split()])
            except ValueError:
                raise InputFileError(f"{path}: MetaImage field {key} = {header[key]!r} is not numbers") \
                    from None
    return np.asarray(default, dtype=float)


def _ints(header: dict, key: str, path: Path) -> list[int]:
    if key not in header:
        raise InputFileError(f"{path}: MetaImage header has no {key}")
    try:
        values = [int(x) for x in header[key].split()]
    except ValueError:
        raise InputFileError(f"{path}: MetaImage field {key} = {header[key]!r} is not integers") from None
    if not values or min(values) < 0:
        raise InputFileError(f"{path}: MetaImage field {key} = {header[key]!r} is not a list of sizes")
    return values


def _metaimage_dtype(header: dict, path: Path) -> np.dtype:
    name = header.get("ElementType", "")
    if name not in METAIMAGE_TYPES:
        raise InputFileError(f"{path}: MetaImage ElementType {name!r} is not supported "
                             f"(supported: {', '.join(METAIMAGE_TYPES)})")
    msb = (header.get("BinaryDataByteOrderMSB", header.get("ElementByteOrderMSB", "False")).lower()
           == "true")
    return np.dtype(METAIMAGE_TYPES[name]).newbyteorder(">" if msb else "<")


def _metaimage_bytes(path: Path, header: dict, data_offset: int, n_bytes: int) -> bytearray:
    """The voxel bytes: LOCAL (after the header) or one external regular file, zlib-inflated if needed;
    exactly the ``n_bytes`` DimSize x ElementType announce are read or inflated, never more."""
    name = header["ElementDataFile"]
    if name.upper() == "LOCAL":
        data_path, offset = path, data_offset
    else:
        if name.upper() == "LIST" or "%" in name or len(name.split()) > 1:
            raise InputFileError(f"{path}: MetaImage with one data file per slice ({name!r}) is not "
                                 "supported; save it as a single .mha or NIfTI")
        data_path = Path(name) if os.path.isabs(name) else path.parent / name
        if not data_path.exists():
            raise InputFileError(f"{path}: MetaImage data file {data_path} not found; keep it beside the "
                                 "header")
        regular_file(data_path, f"MetaImage data file (named in {path.name})")
        offset = _ints(header, "HeaderSize", path)[0] if header.get("HeaderSize", "").strip() not in ("", "-1") \
            else 0
    compressed = header.get("CompressedData", "False").lower() == "true"
    with open(data_path, "rb") as handle:
        if header.get("HeaderSize", "").strip() == "-1" and not compressed:  # the data are the file's last bytes
            if os.fstat(handle.fileno()).st_size < n_bytes:
                raise InputFileError(f"{path}: MetaImage data file {data_path.name} is shorter than the {n_bytes} "
                                     "bytes its header needs; the file is truncated, copy it again")
            handle.seek(-n_bytes, os.SEEK_END)
        else:
            handle.seek(offset)
        if compressed:
            return inflate_exactly(handle, n_bytes, path, "MetaImage voxel data")
        return read_exactly(handle, n_bytes, path, "MetaImage voxel data")


def _metaimage_affine(header: dict, path: Path) -> np.ndarray:
    spacing = _floats(header, ("ElementSpacing", "ElementSize"), [1.0, 1.0, 1.0], path)[:3]
    origin = _floats(header, ("Offset", "Origin", "Position"), [0.0, 0.0, 0.0], path)[:3]
    matrix = _floats(header, ("TransformMatrix", "Rotation", "Orientation"), np.eye(3).ravel(), path)
    if matrix.size == 16:
        matrix = matrix.reshape(4, 4)[:3, :3].ravel()
    if matrix.size != 9 or spacing.size != 3 or origin.size != 3:
        raise InputFileError(f"{path}: MetaImage geometry fields do not describe a 3D volume")
    affine = np.eye(4)
    affine[:3, :3] = matrix.reshape(3, 3).T * spacing[None, :]  # row a of TransformMatrix = axis a
    affine[:3, 3] = origin
    return affine


# ----------------------------------------------------------------------------------------------- DICOM
# A CT series: every file under the folder (recursively; hidden files and DICOMDIR skipped) that reads as
# DICOM. Objects without an image plane (reports, dose summaries) and localizers (ImageType LOCALIZER) are
# left out. The remaining images must form one series (SeriesInstanceUID), of modality CT.
#
# Geometry of a slice: row direction r = IOP[0:3] (increasing column index i), column direction
# c = IOP[3:6] (increasing row index j), normal n = r x c, PixelSpacing = [row spacing dr, column spacing dc].
# Slices are sorted by d = IPP . n; the voxel (i, j, k) is at IPP_0 + i dc r + j dr c + k s with the slice
# step s = (IPP_last - IPP_0) / (n - 1) (a gantry tilt stays as a shear). Every IPP must lie on that line
# and the gaps must be equal, otherwise a slice is missing and the series is refused. HU = stored value x
# RescaleSlope + RescaleIntercept, per slice.

SECONDARY_CAPTURE_PREFIX = "1.2.840.10008.5.1.4.1.1.7"
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


def load_dicom_series(folder: str | Path, *, series_uid: str | None = None) -> Volume:
    """Read one CT series from a folder (see the DICOM notes above)."""
    folder = Path(folder)
    headers, skipped = _dicom_headers(folder)
    series = _choose_series(headers, folder, series_uid)
    _check_ct(series, folder)
    ordered, affine, spacing_note = _slice_geometry(series, folder)
    first = ordered[0][1]
    check_memory((*_columns_rows(first, ordered[0][0]), len(ordered)), 2 + 4, folder)
    hu = _read_slices(ordered, lambda path: _slice_pixels(path))
    meta = {"format": "DICOM", "series_uid": str(first.get("SeriesInstanceUID", "")),
            "series_description": str(first.get("SeriesDescription", "")), "n_slices": len(ordered),
            "skipped_files": skipped, "slice_spacing": spacing_note}
    return _checked_volume(hu, affine, folder, meta)


def load_dicom_file(path: str | Path, *, series_uid: str | None = None) -> Volume:
    """One DICOM file: read the series it belongs to from its folder."""
    import pydicom

    path = Path(path)
    ds = _read_header(path, pydicom)
    if ds is None:
        raise InputFileError(f"{path}: not a readable DICOM file")
    if dicom_int(ds, "NumberOfFrames", 1, path) > 1:
        return load_enhanced_ct(path)
    return load_dicom_series(path.parent, series_uid=series_uid or str(ds.get("SeriesInstanceUID", "")))


def _read_header(path: Path, pydicom):
    """Header without pixels (every element decoded), or None when the file is not DICOM.

    A file that says it is DICOM (the 'DICM' marker) but cannot be parsed raises InputFileError rather than
    being skipped, so a damaged slice is named instead of silently dropped from the series.
    """
    from pydicom.errors import InvalidDicomError

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except InvalidDicomError:
        ds = None
    except DICOM_PARSE_ERRORS as exc:
        if _has_dicom_marker(path):
            raise InputFileError(f"{path}: damaged DICOM file ({describe(exc, 80)}); "
                                 "copy it again or remove it from the folder") from None
        return None
    if ds is None:
        ds = _read_header_without_preamble(path, pydicom)
        if ds is None:
            return None
    _drop_unneeded_damage(ds, path)
    return ds


SLICE_KEYWORDS = {"ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "Rows", "Columns",
                  "RescaleSlope", "RescaleIntercept", "SeriesInstanceUID", "Modality", "SOPClassUID",
                  "ImageType", "NumberOfFrames", "PerFrameFunctionalGroupsSequence",
                  "SharedFunctionalGroupsSequence", "BitsAllocated", "BitsStored", "PixelRepresentation",
                  "SamplesPerPixel"}
"""Header elements the CT reader uses: one of them unreadable makes the slice unusable."""


def _drop_unneeded_damage(ds, path: Path) -> None:
    """Drop elements pydicom cannot decode (e.g. a broken vendor private tag); refuse the slice when one of
    them is needed to place or scale it, so a damaged slice is named instead of misread or skipped."""
    needed = [name for name in drop_unreadable_elements(ds) if name.split(" ")[-1] in SLICE_KEYWORDS]
    if needed:
        raise InputFileError(f"{path}: the DICOM header is damaged: {', '.join(needed)} cannot be read; copy "
                             "or export the series again")


def _read_header_without_preamble(path: Path, pydicom):
    """A DICOM file without the 128-byte preamble (only tried for DICOM-like suffixes), or None."""
    if path.suffix.lower() not in ("", ".dcm", ".dicom", ".ima"):
        return None
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True, force=True)
        return ds if "SOPClassUID" in ds else None
    except Exception:  # noqa: BLE001 - forced parsing of a non-DICOM file fails in many ways
        return None


def _dicom_headers(folder: Path) -> tuple[list, int]:
    """[(path, header)] of the image slices under ``folder``; and how many files were left out."""
    import pydicom

    headers, skipped = [], 0
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith(".") or name.upper() == "DICOMDIR":
                continue
            path = Path(root) / name
            if file_kind(path) is not None:  # a pipe, a device, a broken or looping symlink: never opened
                skipped += 1
                continue
            ds = _read_header(path, pydicom)
            if ds is None or "ImagePositionPatient" not in ds or _is_localizer(ds):
                skipped += 1
                continue
            headers.append((path, ds))
    if not headers:
        raise InputFileError(f"{folder}: no DICOM image slices found in this folder; give the folder of a CT "
                             "series, or a NIfTI/NRRD/MetaImage file")
    return headers, skipped


def _is_localizer(ds) -> bool:
    image_type = [str(t).upper() for t in (ds.get("ImageType") or [])]
    return "LOCALIZER" in image_type


def _choose_series(headers: list, folder: Path, series_uid: str | None) -> list:
    groups: dict[str, list] = {}
    for path, ds in headers:
        groups.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((path, ds))
    if series_uid:
        if series_uid not in groups:
            raise InputFileError(f"{folder}: no series with SeriesInstanceUID {series_uid}; it holds "
                                 f"{_describe_series(groups)}")
        return groups[series_uid]
    if len(groups) > 1:
        raise InputFileError(f"{folder}: holds {len(groups)} image series ({_describe_series(groups)}); put "
                             "the CT series alone in a folder or choose it with --series-uid")
    return next(iter(groups.values()))


def _describe_series(groups: dict) -> str:
    parts = []
    for uid, items in groups.items():
        ds = items[0][1]
        parts.append(f"{uid or '(no UID)'}: {ds.get('Modality', '?')} '{ds.get('SeriesDescription', '')}', "
                     f"{len(items)} images")
    return "; ".join(parts)


def _check_ct(series: list, folder: Path) -> None:
    ds = series[0][1]
    modality = str(ds.get("Modality", "")).upper()
    sop_class = str(ds.get("SOPClassUID", ""))
    what = f"{folder}: series '{ds.get('SeriesDescription', '')}'"
    if sop_class.startswith(SECONDARY_CAPTURE_PREFIX):
        raise InputFileError(f"{what} is a secondary capture (screenshots), not a CT reconstruction; give "
                             "the original CT series")
    if modality != "CT":
        raise InputFileError(f"{what} has modality {modality or 'unknown'}, not CT; CarmReg needs a CT in "
                             "Hounsfield units (give the CT series of the patient)")


def _required(ds, keyword: str, path: Path, count: int):
    try:
        value = dicom_numbers(ds.get(keyword), count, keyword, path)
    except InputFileError:
        value = None
    if value is None:
        raise InputFileError(f"{path}: DICOM slice lacks a valid {keyword}; the series cannot be placed in "
                             "space (export it again from the scanner or PACS)")
    return value


def _columns_rows(ds, path: Path) -> tuple[int, int]:
    cols, rows = dicom_int(ds, "Columns", 0, path), dicom_int(ds, "Rows", 0, path)
    if cols < 1 or rows < 1:
        raise InputFileError(f"{path}: DICOM slice has no valid Rows/Columns ({rows} x {cols}); the file is "
                             "damaged")
    return cols, rows


def _slice_geometry(series: list, folder: Path) -> tuple[list, np.ndarray, str]:
    """Sort slices along the normal; check orientation, size and even spacing; build ijk_to_lps."""
    if len(series) < 2:
        raise InputFileError(f"{folder}: the CT series has only {len(series)} slice; give the whole series")
    first_path, first = series[0]
    iop = _required(first, "ImageOrientationPatient", first_path, 6)
    spacing_rc = _required(first, "PixelSpacing", first_path, 2)
    row_dir, col_dir = iop[:3], iop[3:]
    if (abs(np.linalg.norm(row_dir) - 1) > 1e-2 or abs(np.linalg.norm(col_dir) - 1) > 1e-2
            or abs(row_dir @ col_dir) > 1e-2):
        raise InputFileError(f"{first_path}: ImageOrientationPatient {iop.tolist()} is not two orthogonal "
                             "unit vectors; the slice cannot be placed in space (export the series again)")
    if np.any(spacing_rc <= 0):
        raise InputFileError(f"{first_path}: PixelSpacing {spacing_rc.tolist()} mm is not positive; the "
                             "header is damaged")
    normal = np.cross(row_dir, col_dir)
    for path, ds in series:
        _check_same_plane(ds, path, iop, spacing_rc, first)
    positions = np.array([_required(ds, "ImagePositionPatient", path, 3) for path, ds in series])
    depth = positions @ normal
    order = np.argsort(depth, kind="stable")
    ordered, positions, depth = [series[i] for i in order], positions[order], depth[order]
    step, note = _even_step(positions, depth, folder)
    affine = np.eye(4)
    affine[:3, 0] = row_dir * spacing_rc[1]
    affine[:3, 1] = col_dir * spacing_rc[0]
    affine[:3, 2] = step
    affine[:3, 3] = positions[0]
    return ordered, affine, note


def _check_same_plane(ds, path: Path, iop: np.ndarray, spacing_rc: np.ndarray, first) -> None:
    if np.max(np.abs(_required(ds, "ImageOrientationPatient", path, 6) - iop)) > 1e-3:
        raise InputFileError(f"{path}: slice orientation differs from the rest of the series; the folder "
                             "mixes reconstructions, give one series")
    if np.max(np.abs(_required(ds, "PixelSpacing", path, 2) - spacing_rc)) > 1e-4:
        raise InputFileError(f"{path}: pixel spacing differs from the rest of the series; give one series")
    if _columns_rows(ds, path) != _columns_rows(first, path):
        raise InputFileError(f"{path}: slice size differs from the rest of the series; give one series")


def _even_step(positions: np.ndarray, depth: np.ndarray, folder: Path) -> tuple[np.ndarray, str]:
    """The slice step vector; refuse duplicated positions, missing slices and uneven spacing."""
    gaps = np.diff(depth)
    if np.any(gaps < 1e-3):
        k = int(np.argmin(gaps))
        raise InputFileError(f"{folder}: two slices lie at the same position ({depth[k]:.3f} mm along the "
                             "slice normal); the folder holds several acquisitions of one series, export a "
                             "single reconstruction")
    spacing = float(np.median(gaps))
    tolerance = max(0.01, 0.05 * spacing)
    bad = np.flatnonzero(np.abs(gaps - spacing) > tolerance)
    if bad.size:
        k = int(bad[0])
        raise InputFileError(f"{folder}: slice spacing is uneven: {gaps[k]:.3f} mm between the slices at "
                             f"{depth[k]:.3f} and {depth[k + 1]:.3f} mm where the series spacing is "
                             f"{spacing:.3f} mm; a slice is probably missing (copy the whole series) or the "
                             "series mixes spacings (resample it to even spacing)")
    step = (positions[-1] - positions[0]) / (len(positions) - 1)
    residual = positions - (positions[0] + np.arange(len(positions))[:, None] * step)
    if np.max(np.linalg.norm(residual, axis=1)) > tolerance:
        raise InputFileError(f"{folder}: slice positions do not lie on one line; the series cannot be "
                             "stacked into a volume")
    return step, f"{spacing:.4f} mm from ImagePositionPatient"


def _read_slices(ordered: list, stored_pixels) -> np.ndarray:
    """Stack the slices as hu[i = column, j = row, k = slice], applying RescaleSlope/Intercept.

    ordered: [(key, header)] in slice order; stored_pixels(key) -> (rows, columns) stored values.
    """
    first = ordered[0][1]
    rescale = [_rescale(ds, key) for key, ds in ordered]
    integer = all(s == 1.0 and b == round(b) for s, b in rescale)
    cols, rows = _columns_rows(first, ordered[0][0])
    hu = np.empty((cols, rows, len(ordered)), np.int16 if integer else np.float32, order="F")
    for k, ((key, ds), (slope, intercept)) in enumerate(zip(ordered, rescale, strict=True)):
        if isinstance(key, Path):
            samples = dicom_int(ds, "SamplesPerPixel", 1, key)
            check_dicom_size(key, rows, cols, 1, samples * max(1, dicom_int(ds, "BitsAllocated", 16, key) // 8))
        stored = stored_pixels(key)
        if stored.shape != (rows, cols):
            raise InputFileError(f"{key}: pixel data of shape {stored.shape} does not match Rows x Columns "
                                 f"{rows} x {cols}; the slice is damaged")
        if integer:
            values = stored.astype(np.int32) + int(intercept)
            if values.min() < -32768 or values.max() > 32767:
                hu = hu.astype(np.float32)
                integer = False
            hu[:, :, k] = values.T
        else:
            hu[:, :, k] = (stored.astype(np.float32) * np.float32(slope) + np.float32(intercept)).T
    return hu


def _rescale(ds, key) -> tuple[float, float]:
    """(RescaleSlope, RescaleIntercept), default (1, 0) when absent; a zero slope is refused."""
    slope = dicom_numbers(ds.get("RescaleSlope"), 1, "RescaleSlope", Path(str(key)))
    intercept = dicom_numbers(ds.get("RescaleIntercept"), 1, "RescaleIntercept", Path(str(key)))
    if slope is not None and slope[0] == 0:
        raise InputFileError(f"{key}: RescaleSlope is 0, so every voxel would have the same HU; the header "
                             "is damaged (export the series again)")
    return 1.0 if slope is None else float(slope[0]), 0.0 if intercept is None else float(intercept[0])


def _slice_pixels(path: Path) -> np.ndarray:
    import pydicom

    try:
        ds = pydicom.dcmread(path)
        pixels = ds.pixel_array
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds for bad or undecodable data
        raise InputFileError(f"{path}: cannot decode this slice's pixel data ({describe(exc, 100)}); the "
                             "file may be truncated or compressed in a format without a decoder (decompress "
                             "it, e.g. gdcmconv --raw)") from None
    if pixels.ndim != 2:
        raise InputFileError(f"{path}: slice pixel data has shape {pixels.shape}; expected one grey image")
    return pixels


def load_enhanced_ct(path: str | Path) -> Volume:
    """A single-file multi-frame (enhanced) CT: per-frame ImagePositionPatient, shared or per-frame
    orientation, pixel spacing and rescale from the functional groups; then as a series."""
    import pydicom

    path = Path(path)
    header = _read_header(path, pydicom)
    if header is None:
        raise InputFileError(f"{path}: not a readable DICOM file")
    _check_ct([(path, header)], path)
    frames = _frame_headers(header, path)
    ordered, affine, spacing_note = _slice_geometry(frames, path)
    check_memory((*_columns_rows(header, path), len(ordered)), 2 + 4, path)
    stack = _decoded_frames(path, len(frames))
    hu = _read_slices(ordered, lambda frame: stack[frame])
    meta = {"format": "DICOM enhanced", "series_uid": str(header.get("SeriesInstanceUID", "")),
            "series_description": str(header.get("SeriesDescription", "")), "n_slices": len(ordered),
            "slice_spacing": spacing_note}
    return _checked_volume(hu, affine, path, meta)


_FRAME_FIELDS = (("ImagePositionPatient", "PlanePositionSequence"),
                 ("ImageOrientationPatient", "PlaneOrientationSequence"),
                 ("PixelSpacing", "PixelMeasuresSequence"),
                 ("RescaleSlope", "PixelValueTransformationSequence"),
                 ("RescaleIntercept", "PixelValueTransformationSequence"))


def _frame_headers(ds, path: Path) -> list:
    """[(frame index, pseudo-header with the classic per-slice tags)] from the functional groups."""
    from pydicom.dataset import Dataset

    per_frame = ds.get("PerFrameFunctionalGroupsSequence") or []
    shared = (ds.get("SharedFunctionalGroupsSequence") or [Dataset()])[0]
    if len(per_frame) != dicom_int(ds, "NumberOfFrames", 1, path):
        raise InputFileError(f"{path}: multi-frame DICOM without one functional group per frame; export the "
                             "CT as a classic series or convert it to NIfTI (e.g. with dcm2niix)")
    frames = []
    for index, group in enumerate(per_frame):
        header = Dataset()
        header.Rows, header.Columns = ds.Rows, ds.Columns
        for keyword, sequence in _FRAME_FIELDS:
            for source in (group, shared, ds):
                item = source.get(sequence)
                holder = item[0] if item else (source if source is ds else None)
                if holder is not None and keyword in holder:
                    setattr(header, keyword, holder[keyword].value)
                    break
        frames.append((index, header))
    return frames


def _decoded_frames(path: Path, n_frames: int) -> np.ndarray:
    import pydicom

    try:
        stack = pydicom.dcmread(path).pixel_array
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds for bad or undecodable data
        raise InputFileError(f"{path}: cannot decode the pixel data ({describe(exc, 100)}); the file may be "
                             "truncated or compressed without a decoder") from None
    if stack.ndim != 3 or stack.shape[0] != n_frames:
        raise InputFileError(f"{path}: pixel data of shape {stack.shape} does not hold {n_frames} grey "
                             "frames")
    return stack


def write_dicom_series(folder: str | Path, volume: Volume, *, patient_name: str = "CarmReg^Sample",
                       series_description: str = "CarmReg CT") -> list[Path]:
    """Write a Volume as a CT DICOM series (one file per k slice, explicit VR little endian), atomically
    per file. HU are stored as int16 (rounded and clipped if the volume is float) with slope 1,
    intercept 0. The i and j axes of ``ijk_to_lps`` must be orthogonal (any k step, e.g. a tilt, is fine).
    Refuses a folder that already holds .dcm files (two series would mix)."""
    folder = Path(folder)
    if folder.is_dir() and any(folder.glob("*.dcm")):
        raise InputFileError(f"{folder}: already holds DICOM files; choose an empty folder")
    template = _ct_template(volume, patient_name, series_description)
    hu = np.asarray(volume.hu)
    if hu.dtype != np.int16:
        hu = np.clip(np.rint(hu), -32768, 32767).astype(np.int16)
    affine = volume.ijk_to_lps
    normal = np.cross(affine[:3, 0], affine[:3, 1])
    normal /= np.linalg.norm(normal)
    paths = []
    for k in range(hu.shape[2]):
        position = affine[:3, 3] + k * affine[:3, 2]
        paths.append(_write_ct_slice(folder / f"slice_{k:04d}.dcm", template, hu[:, :, k].T, k, position,
                                     float(position @ normal)))
    return paths


def _ct_template(volume: Volume, patient_name: str, series_description: str):
    """Dataset with everything shared by the slices of one written series."""
    import datetime

    from pydicom.dataset import Dataset
    from pydicom.uid import generate_uid

    from carmreg.logic.io.xray import ds_decimal

    affine = volume.ijk_to_lps
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    row_dir, col_dir = affine[:3, 0] / spacing[0], affine[:3, 1] / spacing[1]
    if abs(row_dir @ col_dir) > 1e-6:
        raise ValueError("write_dicom_series: the i and j axes of ijk_to_lps are not orthogonal")
    normal = np.cross(row_dir, col_dir)
    now = datetime.datetime.now()
    ds = Dataset()
    ds.SOPClassUID, ds.Modality = CT_IMAGE_STORAGE, "CT"
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = (generate_uid() for _ in range(3))
    ds.PatientName, ds.PatientID, ds.SeriesDescription = patient_name, "CARMREG", series_description
    ds.StudyDate = ds.SeriesDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = now.strftime("%H%M%S")
    ds.SeriesNumber, ds.ImageType = 1, ["DERIVED", "SECONDARY", "AXIAL"]
    ds.ImageOrientationPatient = [ds_decimal(x) for x in (*row_dir, *col_dir)]
    ds.PixelSpacing = [ds_decimal(spacing[1]), ds_decimal(spacing[0])]  # row spacing \ column spacing
    ds.SliceThickness = ds_decimal(abs(affine[:3, 2] @ normal))
    ds.Rows, ds.Columns = int(volume.shape[1]), int(volume.shape[0])
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", "1", "HU"
    return ds


def _write_ct_slice(path: Path, template, pixels_rc: np.ndarray, k: int, position: np.ndarray,
                    depth: float) -> Path:
    import copy

    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    from carmreg.logic.io.xray import ds_decimal

    ds = copy.deepcopy(template)
    ds.SOPInstanceUID = generate_uid()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = ds.SOPClassUID, ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [ds_decimal(x) for x in position]
    ds.SliceLocation = ds_decimal(depth)
    ds.PixelData = np.ascontiguousarray(pixels_rc, dtype="<i2").tobytes()
    atomic_write(path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))
    return path
