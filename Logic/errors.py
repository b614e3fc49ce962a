"""One family of user-facing errors.

A ``CarmRegError`` is a problem with the user's input or request that the user can fix: its message says
what was wrong, where (file, field) and what to do. Front doors print it as one line (CLI, exit code 2) or
show it in a dialog (GUI). Anything else is an internal error and keeps its traceback.
"""

import json


class CarmRegError(Exception):
    """Base class of every error a user can act on."""


class InputFileError(CarmRegError):
    """A file is missing, unreadable, truncated or of the wrong kind."""


class GeometryError(CarmRegError):
    """The C-arm geometry is missing or physically impossible."""


class LandmarkError(CarmRegError):
    """Landmarks are missing, duplicated, unpaired, outside the image or degenerate."""


class RegistrationError(CarmRegError):
    """The registration cannot run on these inputs or its own checks failed."""


class CancelledError(CarmRegError):
    """The user cancelled a long computation."""


def quote(value, limit: int = 60) -> str:
    """The user's value for an error message: ``'text'`` for a string, JSON for anything else (``[true, 0]``),
    cut to ``limit`` characters with the full length named (a 10 MB label stays one short line)."""
    if isinstance(value, str):
        text = repr(value if len(value) <= limit else value[:limit])
    else:
        try:
            text = json.dumps(value, allow_nan=True)
        except (TypeError, ValueError, RecursionError):
            text = repr(value)
    if len(text) > limit + 2:
        text = text[:limit] + "..."
    if isinstance(value, str | list | dict) and len(value) > limit:
        text += f" ({len(value)} {'characters' if isinstance(value, str) else 'items'})"
    return text



def describe(exc: BaseException, limit: int = 100) -> str:
    """'Kind: message' of a library exception on one line (whitespace collapsed) and at most ``limit``
    characters of message, cut at a word with "..." when longer, for embedding in a one-line CarmRegError."""
    text = " ".join(str(exc).split())
    if len(text) > limit:
        text = (text[:limit].rsplit(" ", 1)[0] or text[:limit]) + " ..."
    return f"{exc.__class__.__name__}: {text}"
