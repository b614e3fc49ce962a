"""Bounds on what a file may cost before it is read: regular files only, and no more bytes than the header says.

- ``regular_file``: the path must be a regular file (after following symlinks). A named pipe, a device
  (``/dev/zero``), a socket or a symlink loop would otherwise block or never end a read.
- ``read_exactly`` / ``inflate_exactly``: read the ``n_bytes`` the header announces, never more; a compressed
  payload is inflated in chunks and refused as soon as it would give more than ``n_bytes`` (a decompression
  bomb costs at most one chunk beyond the announced size) or ends before (truncated).
"""

from __future__ import annotations

import os
import stat
import zlib
from pathlib import Path
from typing import BinaryIO

from carmreg.logic.errors import InputFileError

CHUNK_BYTES = 1 << 20
"""Compressed bytes read per step while inflating."""

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def file_kind(path: str | Path) -> str | None:
    """None for a regular file (symlinks followed), else what it is: 'missing', 'a named pipe', ..."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "missing"
    except OSError as exc:  # ELOOP (symlink loop), ENAMETOOLONG, EACCES, ...
        return f"unreadable ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def regular_file(path: str | Path, what: str) -> Path:
    """``path`` if it is a regular file, else InputFileError '<path>: <what> is a named pipe, not a file; ...'."""
    path = Path(path)
    kind = file_kind(path)
    if kind == "missing":
        raise InputFileError(f"{path}: {what} not found")
    if kind is not None:
        raise InputFileError(f"{path}: {what} is {kind}, not a regular file; give the file itself")
    return path


def _bytes_left(handle: BinaryIO) -> int | None:
    """Bytes between the position and the end of a regular file; None for anything else (checked as read)."""
    try:
        info = os.fstat(handle.fileno())
        return info.st_size - handle.tell() if stat.S_ISREG(info.st_mode) else None
    except (OSError, AttributeError, ValueError):
        return None


def read_exactly(handle: BinaryIO, n_bytes: int, path: Path, what: str) -> bytearray:
    """The next ``n_bytes`` of ``handle`` (a writable buffer); InputFileError when the file ends before. A regular
    file too short for them is refused before the buffer is allocated (a header may announce gigabytes)."""
    left = _bytes_left(handle)
    if left is not None and left < n_bytes:
        raise InputFileError(f"{path}: holds {left} bytes of {what} but its header needs {n_bytes}; the file is "
                             "truncated, copy it again")
    data = bytearray(n_bytes)
    view, got = memoryview(data), 0
    while got < n_bytes:
        n = handle.readinto(view[got:])
        if not n:
            raise InputFileError(f"{path}: holds {got} bytes of {what} but its header needs {n_bytes}; the "
                                 "file is truncated, copy it again")
        got += n
    return data


def inflate_exactly(handle: BinaryIO, n_bytes: int, path: Path, what: str, wbits: int = zlib.MAX_WBITS | 32,
                    decompressor=None) -> bytearray:
    """Inflate the compressed stream at ``handle`` to exactly the ``n_bytes`` the header announces.

    zlib/gzip by default (``wbits``), or any ``decompressor`` with ``decompress(data, max_length)``
    semantics of ``zlib.Decompress``. Refuses a stream that would inflate to more (a decompression bomb:
    at most ``n_bytes`` + 1 bytes are ever produced) or to less (truncated), or that is corrupt.
    """
    inflater = decompressor or zlib.decompressobj(wbits)
    out = bytearray()
    pending = b""
    try:
        while not inflater.eof and len(out) <= n_bytes:
            if hasattr(inflater, "needs_input"):  # bz2: keeps unconsumed input itself
                pending = handle.read(CHUNK_BYTES) if inflater.needs_input else b""
                if inflater.needs_input and not pending:
                    break
            elif not pending:
                pending = handle.read(CHUNK_BYTES)
                if not pending:
                    break
            out += inflater.decompress(pending, n_bytes + 1 - len(out))
            pending = getattr(inflater, "unconsumed_tail", b"")
    except (zlib.error, OSError, EOFError) as exc:
        raise InputFileError(f"{path}: the compressed {what} are corrupt ({exc}); the file is probably "
                             "truncated, copy it again") from None
    if len(out) > n_bytes:
        raise InputFileError(f"{path}: the compressed {what} inflate to more than the {n_bytes} bytes its "
                             "header announces; the file is damaged or hostile (refused before inflating it "
                             "further)")
    if len(out) < n_bytes:
        raise InputFileError(f"{path}: the compressed {what} inflate to {len(out)} bytes but its header needs "
                             f"{n_bytes}; the file is truncated, copy it again")
    return out


DICOM_HEADER_SLACK_BYTES = 64 * 1024**2
"""Room for a DICOM file's header and private elements (thumbnails, vendor blobs) beside its pixels."""


def check_dicom_size(path: Path, rows: int, cols: int, frames: int = 1, bytes_per_pixel: int = 2) -> None:
    """Refuse a DICOM file far larger than the pixels its header describes (pydicom would read it whole):
    more than the uncompressed pixels plus ``DICOM_HEADER_SLACK_BYTES``."""
    size = os.stat(path).st_size
    pixel_bytes = max(int(rows), 0) * max(int(cols), 0) * max(int(frames), 1) * max(int(bytes_per_pixel), 1)
    if size > pixel_bytes + DICOM_HEADER_SLACK_BYTES:
        raise InputFileError(f"{path}: the file holds {size / 1024**2:.0f} MB, far more than its {cols} x {rows} px "
                             f"x {frames} frame(s) image needs ({pixel_bytes / 1024**2:.1f} MB); the file is "
                             "damaged or hostile, export it again")
