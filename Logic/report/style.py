"""The one drawing style of a result, shared by the window, the report page and ``overlay.png`` (no Qt).

Colours are hex strings (``#rrggbb``). Each status of the level answer has two shades of one hue:

- ``fill``: the background of a banner with white text on it (the window's banner, the report page's banner,
  the banner of ``overlay.png``);
- ``ink``: text and markers on a dark background (the window's panels, names drawn on an X-ray).

``level_answer`` and ``answer_banner`` give the level answer in words and its colour, for every banner. An answer
whose names are withheld (``LevelCheck.withheld``: the X-ray refused) is told in the contradiction colour, and no
front door writes a level name on the X-ray then (``names_shown``).

A name the image did not confirm (status ambiguous or contradicted, ``UNCONFIRMED``) carries a "?" wherever it is
written - on every overlay, in the window's table, on the 3D Slicer scene's points - so that an image or a
screenshot without its banner never shows an unconfirmed name as a plain one.

Markers on an overlay (positions (u, v) = (column, row) detector px): a filled disc for a level the fit used,
named with its PDE (detector mm) to the click, in ``FITTED_COLOUR`` - or, unconfirmed, in the status's ink
(amber ambiguous, red contradicted) with a "?" after the name; a ring in ``CHECK_COLOUR`` for a CT-labelled level
not clicked (its name with a "?" when unconfirmed); a cross in ``CLICK_COLOUR`` for the surgeon's click.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from carmreg.logic.registration.level_check import LevelCheck


@dataclass(frozen=True)
class StatusColour:
    """Two shades of a level-answer colour (module docstring)."""

    fill: str
    ink: str


STATUS_COLOURS: dict[str | None, StatusColour] = {
    "confident": StatusColour("#2b8a3e", "#69db7c"),     # green: names confirmed by the image
    "proposed": StatusColour("#b08900", "#ffe066"),      # yellow: named from the image alone, not confirmed
    "ambiguous": StatusColour("#e8590c", "#ffa94d"),     # amber
    "contradicted": StatusColour("#c92a2a", "#ff8787"),  # red: the image contradicts the given names
    None: StatusColour("#495057", "#c8ccd0"),            # grey: not checked
}
STATUS_WORDS = {"confident": "LEVELS CONFIRMED BY THE IMAGE", "proposed": "LEVELS PROPOSED (NOT CONFIRMED)",
                "ambiguous": "LEVELS AMBIGUOUS", "contradicted": "LEVEL NAMES CONTRADICTED BY THE IMAGE",
                None: "LEVEL NAMES NOT CHECKED"}
WITHHELD_WORDS = "IMAGE REFUSED - NO LEVEL NAMED"
FITTED_COLOUR = "#40c057"
CHECK_COLOUR = "#ffd228"
CLICK_COLOUR = "#ff4d4d"
# the statuses whose names the image did not confirm (written with a "?"), and what the "?" says then
UNSURE_WORDS = {"ambiguous": "name not confirmed by the image", "contradicted": "name contradicted by the image"}
UNCONFIRMED = tuple(UNSURE_WORDS)


def names_shown(check: LevelCheck | None) -> bool:
    """Whether level names may be written on the X-ray: not when the answer withholds them."""
    return not (check and check.withheld)


def unconfirmed(check: LevelCheck | None) -> bool:
    """Whether the level names are not confirmed by the image (ambiguous, contradicted or withheld; module
    docstring). Names not checked (no level check) are the surgeon's own and stay plain."""
    return bool(check) and check.status in UNCONFIRMED


def unsure_name(label: str, check: LevelCheck | None) -> str:
    """A level's name where it must be written as text (a 3D Slicer point's name, the window's table): with a "?"
    when the image did not confirm it (``unconfirmed``)."""
    return f"{label}?" if unconfirmed(check) else label


def status_fill(status: str | None) -> str:
    """Banner background of a level-answer status (unknown statuses: the not-checked grey)."""
    return STATUS_COLOURS.get(status, STATUS_COLOURS[None]).fill


def status_ink(status: str | None) -> str:
    """Text/marker colour of a level-answer status on a dark background."""
    return STATUS_COLOURS.get(status, STATUS_COLOURS[None]).ink


def hex_rgb(colour: str) -> tuple[int, int, int]:
    """``#rrggbb`` -> (r, g, b) 0..255."""
    value = colour.lstrip("#")
    return int(value[0:2], 16), int(value[2:4], 16), int(value[4:6], 16)


@dataclass(frozen=True)
class LevelMarker:
    """How one projected level is drawn: its text, colour and whether it is a fitted (filled) marker."""

    text: str
    colour: str
    fitted: bool


def level_marker(level: dict, status: str | None, with_text: bool = True) -> LevelMarker:
    """The marker of one ``result.levels`` entry under the level answer's ``status``: ``T12  1.8 mm`` in green
    for a fitted level (PDE to the click, detector mm), ``T12?  1.8 mm`` in the status's ink when the image did
    not confirm the names (``UNCONFIRMED``), ``L2`` in yellow for a level not clicked (``L2?`` unconfirmed: drawn
    at the pose fitted to those names, it may sit on a neighbour); ``with_text`` False gives an empty text (names
    hidden)."""
    fitted = bool(level.get("fitted"))
    pde = level.get("pde_mm")
    unsure = status in UNCONFIRMED
    text = level["label"] + ("?" if unsure else "") + (f"  {pde:.1f} mm" if pde is not None else "")
    colour = (status_ink(status) if unsure else FITTED_COLOUR) if fitted else CHECK_COLOUR
    return LevelMarker(text if with_text else "", colour, fitted)


# ----------------------------------------------------------------------------------------------- the answer

def level_answer(check: LevelCheck | None, ok: bool = True, detail: bool = True) -> tuple[str, str, str]:
    """(headline, reason, colour) of the level answer for the page and the window's banner; ``detail`` adds
    the margin and how to read it to the reason."""
    status = check.status if check else None
    if check and check.withheld:
        return WITHHELD_WORDS, check.message, status_fill("contradicted")
    headline = STATUS_WORDS.get(status, str(status).upper())
    names = ", ".join(check.names()) if check else ""
    if check and check.mode == "image_only":
        names = names or "none"
    if names:
        headline += f": {names}"
    reason = check.message if check else "the level check was not run (fully named clicks, level check off)"
    explained = margin_detail(check) if detail else ""
    if explained:
        reason += f" ({explained})"
    colour = status_fill(status if ok or status == "contradicted" else "contradicted")
    return headline, reason.strip(), colour


def margin_detail(check: LevelCheck | None) -> str:
    """The level answer's margin and how to read it ("" without a finite margin, or when no name is shown)."""
    margin = check.margin if check else None
    if margin is None or not math.isfinite(margin) or not names_shown(check):
        return ""
    from carmreg.logic.registration.level_confidence import ConfidenceRule

    return (f"margin {float(margin):+.3f}; the score is 1 - gradient correlation + landmark terms, lower is better; "
            f"confident needs {ConfidenceRule().margin:.2f} and the checks of the README's rule")


def answer_banner(level_check: LevelCheck | None, ok: bool, failed_checks: list[str]) -> tuple[str, str, str] | None:
    """(headline, reason, colour) to show above a result: the level answer (without the margin details, which
    the window lists beside), or "CHECKS FAILED" with the failed checks (``RegistrationResult.failed_checks``, not
    the advisories) when the result is not ok for another reason; None when there is nothing to say (level check
    off and every check passed)."""
    if not level_check and ok:
        return None
    headline, reason, colour = level_answer(level_check, ok, detail=False)
    if not ok and not (level_check and (level_check.contradicted or level_check.withheld)):
        headline, reason = "CHECKS FAILED - " + headline, "; ".join(failed_checks)
    return headline, reason, colour


STALE_WORDS = "RESULT OUT OF DATE - REGISTER AGAIN"


def stale_banner(why: str) -> tuple[str, str, str]:
    """(headline, reason, colour) over a result its inputs have moved on from: grey whatever its answer was (a
    green confirmation must never stay over clicks or an X-ray it did not check)."""
    return STALE_WORDS, f"{why}: the overlay, level names and pose shown describe the previous inputs", \
        status_fill(None)


MODE_TEXT = {"named": "names as clicked", "partly_named": "partly named clicks", "unnamed": "unnamed clicks",
             "image_only": "image alone (no clicks)"}
"""The mode in a few words, for the one-line banner (``level_banner``)."""
MODE_DESCRIPTION = {"named": "named clicks, checked against the names shifted up and down",
                    "partly_named": "partly named clicks, the others named from the image",
                    "unnamed": "unnamed clicks, named from the image",
                    "image_only": "no clicks: levels from the image alone"}
"""What the mode did, for the report page and the window's level box."""


def level_banner(check: LevelCheck | None) -> tuple[str, tuple[int, int, int]] | None:
    """One line for the surgeon: how the levels were named, the status and the margin to the runner-up, with
    the status's colour on a dark background (``status_ink``) as (r, g, b)."""
    if not check:
        return None
    if check.withheld:
        return f"Levels: {WITHHELD_WORDS}", hex_rgb(status_ink("contradicted"))
    text = f"Levels from {MODE_TEXT.get(check.mode, check.mode)}: {check.status.upper()}"
    margin, runner = check.margin, check.runner_up_labels
    if margin is not None and math.isfinite(margin):
        text += f" (margin {margin:+.3f}"
        text += f" over {'-'.join([runner[0], runner[-1]]) if len(runner) > 1 else runner[0]})" if runner else ")"
    return text, hex_rgb(status_ink(check.status))


def level_summary(check: LevelCheck) -> str:
    """The levels stage in two lines for the command line: which names, from what, how sure (margin = score of
    the best other labelling minus the chosen one's; the objective is 1 - gradient correlation + landmark
    terms)."""
    if check.withheld:
        return f"level identification: {check.message}"
    if check.mode == "image_only":
        what = f"levels in view (from the image alone): {', '.join(check.visible_labels) or 'none'}"
    elif check.mode == "named":
        what = f"clicked names {', '.join(check.assigned_labels)} checked against shifted names"
    else:
        what = f"clicks named {', '.join(check.assigned_labels)} ({check.mode.replace('_', ' ')})"
    margin, runner = check.margin, check.runner_up_labels
    sure = check.status.upper() + (f", margin {margin:+.3f}" if margin is not None else "")
    return (f"level identification: {what}\n  {sure}" + (f" over {', '.join(runner)}" if runner else "")
            + f": {check.message}")
