"""The overlay as on screen, drawn without Qt (matplotlib): the report page's overlay and ``overlay.png``.

The same picture as the window's overlay view: the composite of ``composite`` (the X-ray bone bright in grey
over its display range, the DRR at the found pose added in amber, black outside the exposed field), every
CT-labelled level projected and named in the style of ``style.level_marker`` (filled green disc with its PDE for a
level the fit used, amber or red with a "?" when the image did not confirm the names (ambiguous, contradicted),
yellow ring for a level not clicked,
red cross for a click), and - in ``overlay.png`` - the level answer's banner (``style.answer_banner``) across the
top. Pixel positions are (u, v) = (column, row) px, 0-based pixel centres; images are indexed image[row, column].

``overlay_image`` renders at the X-ray's own size (one output pixel per detector pixel), so the PNG and the
3D Slicer overlay sit on the X-ray's pixel grid; text and markers are scaled as on the report page, where the
overlay is ``OVERLAY_INCHES`` wide (never smaller than there: a small X-ray gets relatively larger names).
"""

from __future__ import annotations

import textwrap

import numpy as np

from carmreg.logic.registration.level_check import LevelCheck
from carmreg.logic.report.composite import blend, normalise, xray_bone_bright
from carmreg.logic.report.style import CLICK_COLOUR, answer_banner, level_marker, names_shown

OVERLAY_INCHES = 4.8        # the longer side of the overlay on the report page
RENDER_DPI = 100.0
LABEL_POINTS = 7.5          # level names, at OVERLAY_INCHES
BANNER_MAX_ROWS = 0.15      # the banner's reason is left out when it would cover more of the image
MIN_SCALE = 1.0             # small X-rays: text and markers no smaller than on the page (about 10 px)


def screen_composite(xray_pixels: np.ndarray, drr_line_integral: np.ndarray | None, bone_dark: bool,
                     alpha: float = 0.5, mask: np.ndarray | None = None) -> np.ndarray:
    """(rows, cols, 3) uint8: the window's default overlay - the X-ray bone bright in grey, the DRR added in
    amber with weight ``alpha``, black outside the exposed field ``mask`` (default ``image.field.field_mask``)."""
    from carmreg.logic.image.field import field_mask

    if mask is None or np.shape(mask) != np.shape(xray_pixels):
        mask = field_mask(xray_pixels)
    xray01 = xray_bone_bright(xray_pixels, bone_dark, mask)
    drr01 = normalise(drr_line_integral, mask) if drr_line_integral is not None else np.zeros_like(xray01)
    return blend(xray01, drr01, alpha)


def draw_overlay(ax, rgb: np.ndarray, levels: list[dict], clicked: dict | None, status: str | None,
                 scale: float = 1.0, interpolation: str = "antialiased", names: bool = True) -> None:
    """The composite ``rgb`` (image[row, col]) with the projected levels, their names and PDE
    (``style.level_marker`` under the level answer's ``status``; ``names`` False: markers only,
    ``style.names_shown``), and the clicks ({name: (u, v) px}); ``scale`` multiplies text and marker sizes
    (1 = the report page's); ``interpolation``: matplotlib's, for an image drawn at another size than its own
    (the page's "antialiased": a Hanning filter where the image is shrunk; "lanczos" differed from it by 0.2 grey
    levels on average, a little sharper, and took 0.25 s more of every report)."""
    ax.imshow(rgb, interpolation=interpolation)
    rows, cols = rgb.shape[:2]
    for lv in levels:
        if lv.get("in_image", True):
            _draw_level(ax, lv, level_marker(lv, status, names), scale)
    for uv in (clicked or {}).values():
        ax.plot(float(uv[0]), float(uv[1]), "+", ms=9 * scale, mew=1.3 * scale, color=CLICK_COLOUR)
    ax.set_xlim(-0.5, cols - 0.5)
    ax.set_ylim(rows - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])


def _draw_level(ax, level: dict, marker, scale: float) -> None:
    """One projected level at its (u, v) px: disc or ring, and its name in a dark box (a box, not an outline:
    the name stays text in a PDF)."""
    u, v = level["uv_px"]
    if marker.fitted:
        ax.plot(u, v, "o", ms=5.5 * scale, color=marker.colour, mec="black", mew=0.6 * scale)
    else:
        ax.plot(u, v, "o", ms=7 * scale, mfc="none", mec=marker.colour, mew=1.4 * scale)
    if not marker.text:
        return
    ax.annotate(marker.text, (u, v), xytext=(9 * scale, -3 * scale), textcoords="offset points",
                color=marker.colour, fontsize=LABEL_POINTS * scale, fontweight="bold",
                bbox={"boxstyle": "round,pad=0.15", "fc": "black", "alpha": 0.55, "ec": "none"})


def _draw_banner(ax, banner: tuple[str, str, str], scale: float, rows: int, cols: int,
                 clear_rows: float = float("inf")) -> None:
    """The level answer in white on its colour across the top of the image: the headline, and the reason
    below it when it fits in BANNER_MAX_ROWS of the image and above ``clear_rows`` (the first row of a level's
    marker or name: the reason never covers one); the font shrinks so the headline fits the width."""
    headline, reason, colour = banner
    char_px = 0.62 * RENDER_DPI / 72.0  # width of a character per point of font size, px
    points = min(LABEL_POINTS * scale, 0.96 * cols / (char_px * max(len(headline), 1)))
    lines = textwrap.wrap(reason, max(20, int(0.96 * cols / (char_px * points)))) if reason else []
    line_px = 1.35 * points * RENDER_DPI / 72.0
    room = min(BANNER_MAX_ROWS * rows, clear_rows)
    text = headline if (1 + len(lines)) * line_px > room else "\n".join([headline, *lines])
    ax.text(0.012, 0.988, text, transform=ax.transAxes, va="top", ha="left", color="white", fontsize=points,
            linespacing=1.35, bbox={"boxstyle": "square,pad=0.45", "fc": colour, "alpha": 0.92, "ec": "none"})


def render_overlay(rgb: np.ndarray, levels: list[dict], clicked: dict | None = None,
                   level_check: LevelCheck | None = None, ok: bool = True, failed_checks: list[str] | tuple = ()
                   ) -> np.ndarray:
    """(rows, cols, 3) uint8: the composite ``rgb`` with the levels, the clicks and the level answer's banner
    drawn on it at the image's own size (module docstring)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows, cols = rgb.shape[:2]
    scale = max(max(rows, cols) / (OVERLAY_INCHES * RENDER_DPI), MIN_SCALE)
    fig = Figure(figsize=((cols + 0.01) / RENDER_DPI, (rows + 0.01) / RENDER_DPI), dpi=RENDER_DPI)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_axis_off()
    # one output pixel per image pixel: "nearest" copies them (lanczos gave the same to 1 grey level, 4x slower)
    draw_overlay(ax, rgb, levels, clicked, level_check.status if level_check else None, scale, "nearest",
                 names_shown(level_check))
    banner = answer_banner(level_check, ok, list(failed_checks))
    if banner is not None:
        tops = [lv["uv_px"][1] for lv in levels if lv.get("in_image", True)]
        tops += [uv[1] for uv in (clicked or {}).values()]
        marker_px = 12.0 * scale * RENDER_DPI / 72.0  # a marker's and a name's half height, with room
        _draw_banner(ax, banner, scale, rows, cols, min(tops, default=float("inf")) - marker_px)
    canvas.draw()
    out = np.asarray(canvas.buffer_rgba())[:rows, :cols, :3]
    return np.ascontiguousarray(out)


def overlay_image(xray_pixels: np.ndarray, drr_line_integral: np.ndarray | None, levels: list[dict],
                  clicked: dict | None = None, mask: np.ndarray | None = None, level_check: LevelCheck | None = None,
                  bone_dark: bool | None = None, ok: bool = True, failed_checks: list[str] | tuple = ()):
    """The overlay as a PIL RGB image of the X-ray's size: ``screen_composite`` (``bone_dark`` None: the X-ray
    as stored, not flipped) drawn on by ``render_overlay``. ``mask``: the exposed field (default: found)."""
    from PIL import Image

    rgb = screen_composite(xray_pixels, drr_line_integral, bool(bone_dark), mask=mask)
    return Image.fromarray(render_overlay(rgb, levels, clicked, level_check, ok, failed_checks))


def result_bone_dark(result, bone_dark: bool | None = None) -> bool:
    """The X-ray's polarity: as given, else as the registration found it (``result.appearance``), else dark."""
    if bone_dark is not None:
        return bool(bone_dark)
    appearance = getattr(result, "appearance", None)
    return bool(getattr(appearance, "bone_dark", True))


def result_overlay_image(result, xray_pixels: np.ndarray, clicked: dict | None = None):
    """``overlay_image`` of a RegistrationResult: its DRR, levels, exposed field, polarity
    (``result_bone_dark``), level answer and checks."""
    return overlay_image(xray_pixels, result.drr_line_integral, result.levels, clicked,
                         mask=getattr(result, "field_mask", None), level_check=result.level_check,
                         bone_dark=result_bone_dark(result), ok=bool(result.ok),
                         failed_checks=list(getattr(result, "failed_checks", [])))
