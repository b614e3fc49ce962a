"""MetaImage ``.mha`` / ``.mhd`` CT (own reader): ``TransformMatrix`` (row a = LPS direction of index axis a, as
ITK writes it), ``Offset`` (centre of the first voxel), ``ElementSpacing``, ``ElementType``, ``ElementDataFile``
LOCAL or one external raw file, ``CompressedData`` (zlib, inflated with a bound), byte order. Worlds are LPS
(ITK); ``AnatomicalOrientation`` is recorded in ``meta`` only.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError
from carmreg.logic.geometry.volume import Volume
from carmreg.logic.io.limits import inflate_exactly, read_exactly, regular_file
from carmreg.logic.io.volume_checks import as_hu, check_memory, checked_volume

METAIMAGE_TYPES = {
    "MET_CHAR": "i1", "MET_UCHAR": "u1", "MET_SHORT": "i2", "MET_USHORT": "u2", "MET_INT": "i4",
    "MET_UINT": "u4", "MET_LONG": "i4", "MET_ULONG": "u4", "MET_LONG_LONG": "i8", "MET_ULONG_LONG": "u8",
    "MET_FLOAT": "f4", "MET_DOUBLE": "f8",
}


def load_metaimage(path: Path) -> Volume:
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
    return checked_volume(data, _metaimage_affine(header, path), path, meta)


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
