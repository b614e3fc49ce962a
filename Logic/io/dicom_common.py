"""DICOM helpers every reader shares (CT series, X-ray, landmarks): library noise collected instead of printed,
the errors pydicom raises on damaged files, unreadable elements dropped, numbers read with a check, and the
DS formatting of a decimal.
"""

from __future__ import annotations

import functools
import logging
import struct
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from carmreg.logic.errors import InputFileError

QUIET_LOGGERS = ("pydicom", "nibabel", "nibabel.global", "PIL")


@contextmanager
def quiet_libraries(limit: int = 5) -> Iterator[list[str]]:
    """Collect instead of print what pydicom, Pillow and nibabel warn or log while reading a damaged or
    non-standard file (the command line keeps one line per error on stderr). Yields a list that holds, on
    exit, the first ``limit`` distinct warning messages (for ``meta``); library log records are dropped."""
    notes: list[str] = []
    loggers = [logging.getLogger(name) for name in QUIET_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield notes
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)
        for message in dict.fromkeys(" ".join(str(w.message).split())[:160] for w in caught):
            if len(notes) < limit:
                notes.append(message)




@functools.cache
def dicom_parse_errors() -> tuple:
    """What pydicom raises on a damaged file (while reading, or when an element is first decoded). A function, so
    that importing the readers does not import pydicom (0.15-0.2 s of every ``carmreg register`` whose X-ray and CT
    are not DICOM)."""
    from pydicom.errors import BytesLengthException, InvalidDicomError

    return (InvalidDicomError, BytesLengthException, struct.error, NotImplementedError, EOFError, OSError,
            ValueError, KeyError, TypeError, IndexError, OverflowError, UnicodeError, AttributeError)


def drop_unreadable_elements(ds) -> list[str]:
    """Decode every element now (pydicom decodes lazily) and delete, recursively, those that cannot be
    decoded (a damaged or non-standard vendor element); returns their '(gggg,eeee) Keyword' names.

    An X-ray stays usable without, say, a broken private tag; a needed value that was dropped is then simply
    absent (the loader asks for it, naming what was ignored). Pixel data are not decoded.
    """
    from pydicom.datadict import keyword_for_tag

    dropped = []
    for tag in list(ds.keys()):
        try:
            element = ds[tag]
            if element.VR == "SQ":
                for item in element.value:
                    dropped += drop_unreadable_elements(item)
            else:
                _ = element.value
        except dicom_parse_errors():
            keyword = keyword_for_tag(tag)
            dropped.append(f"({tag.group:04X},{tag.element:04X}){' ' + keyword if keyword else ''}")
            del ds[tag]
    return dropped


def dicom_numbers(value, count: int | None, keyword: str, path: Path) -> np.ndarray | None:
    """A DICOM numeric value (DS/IS/US/FD, single or multi-valued) as float64, or None when absent.

    count: how many numbers are required (None: any number >= 1). A present but malformed value (text that
    is not a number, wrong multiplicity, NaN) raises InputFileError naming the tag.
    """
    if value is None or (isinstance(value, (str, bytes)) and not value.strip()):
        return None
    items = [value] if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__") else list(value)
    try:
        numbers = np.array([float(x) for x in items], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputFileError(f"{path}: DICOM {keyword} = {str(value)[:40]!r} is not a number; the header is "
                             "damaged or non-standard (give the value manually, or export the file again)") \
            from None
    if (count is not None and numbers.size != count) or numbers.size == 0 or not np.all(np.isfinite(numbers)):
        want = f"{count} number(s)" if count is not None else "finite numbers"
        raise InputFileError(f"{path}: DICOM {keyword} = {str(value)[:40]!r} is not {want}; the header is "
                             "damaged or non-standard (give the value manually, or export the file again)")
    return numbers


def dicom_int(ds, keyword: str, default: int, path: Path) -> int:
    """An integer attribute (IS/US) with a default when absent or empty."""
    numbers = dicom_numbers(ds.get(keyword), 1, keyword, path)
    if numbers is None:
        return default
    if numbers[0] != round(numbers[0]) or abs(numbers[0]) > 2**31:
        raise InputFileError(f"{path}: DICOM {keyword} = {numbers[0]:g} is not a valid integer; the header "
                             "is damaged")
    return int(numbers[0])

def ds_decimal(x: float) -> str:
    """A DICOM decimal string (at most 16 characters) holding ``x`` as precisely as fits."""
    for digits in range(12, 3, -1):
        text = f"{float(x):.{digits}g}"
        if len(text) <= 16:
            return text
    raise ValueError(f"cannot write {x} as a DICOM decimal string")

def has_dicom_marker(path: Path) -> bool:
    """The 'DICM' marker at byte 128 (a DICOM file with its preamble)."""
    with open(path, "rb") as handle:
        return handle.read(132)[128:132] == b"DICM"
