"""One family of user-facing errors.

A ``CarmRegError`` is a problem with the user's input or request that the user can fix: its message says
what was wrong, where (file, field) and what to do. Front doors print it as one line (CLI, exit code 2) or
show it in a dialog (GUI). Anything else is an internal error and keeps its traceback.
"""


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
    """``repr(value)`` for an error message, cut to ``limit`` characters (a 10 MB label stays one short line)."""
    text = repr(value) if not isinstance(value, str) or len(value) <= limit else repr(value[:limit])
    if len(text) > limit + 2:
        text = text[:limit] + "..."
    if isinstance(value, str | bytes | list | dict) and len(value) > limit:
        text += f" ({len(value)} {'characters' if isinstance(value, str) else 'items'})"
    return text
