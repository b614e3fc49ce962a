"""The one-page report of a registration: a PDF (or PNG) a surgeon can keep (matplotlib, no Qt).

What the page shows, top to bottom:

- the title, the time it was made and the line **"Research software - not for diagnosis"**;
- the **level answer** in words and colour (green confident, yellow proposed from the image alone, amber
  ambiguous, red contradicted, grey not checked) with its reason (``LevelCheck.message``) and the failed
  checks when ``ok`` is False;
- the **overlay as on screen**: the X-ray (bone bright, inside its exposed field) with the DRR at the found pose
  blended in amber (the window's default "blend" mode; the window passes its own composite), every CT-labelled
  level projected and named: filled green disc = a level the fit used, with its PDE (mm on the detector) to the
  click; yellow ring = a level not clicked; red cross = the click. When the image does not confirm the names
  (ambiguous, contradicted), every name carries a "?" and the clicked levels are drawn in the status's colour;
- the **named levels**, with the same "?" (projected ``uv_px`` = (column, row) px, 0-based pixel centres; PDE
  in detector mm);
- the **pose** (the six C-arm parameters about the nominal AP pose, mm and degrees), the **magnification** at
  the isocentre (SDD / SOD at the pose) and the **mPDE of the pose drawn** (mean PDE of the clicked levels at
  the final pose: the accuracy of what is on the page, not of an intermediate stage);
- the **inputs**: file names, the C-arm geometry values and where each came from (DICOM tag, manual, preset,
  default);
- the **versions** (CarmReg, Python, numpy, scipy, numba; cma in results from before CarmReg ran its own CMA-ES)
  and the CMA-ES seed.

Every text block has its place on the page: a long one (an unclear image's reason and warnings) is set in smaller
type, down to 6 pt, and beyond that cut with a pointer to result.json (``fit_text``), never printed over another.

``write_report_pdf`` writes one A4 page atomically; ``write_report_png`` the same page as a PNG (README).
Text in the PDF is real text (DejaVu embedded as Type 3 fonts with a ToUnicode map), so it can be searched and
read back; Type 42 (whole TrueType subsets) read back the same but took 0.9 s more to write.
"""

from __future__ import annotations

import datetime as _dt
import textwrap
from pathlib import Path

import numpy as np

from carmreg.logic.io.atomic import atomic_write, atomic_write_bytes
from carmreg.logic.registration.level_check import LevelCheck
from carmreg.logic.report.overlay import draw_overlay, result_bone_dark, screen_composite
from carmreg.logic.report.style import (
    MODE_DESCRIPTION,
    UNSURE_WORDS,
    level_answer,
    margin_detail,
    names_shown,
    unsure_name,
)

A4_INCHES = (8.27, 11.69)
LINE_SPACING = 1.2  # matplotlib's line spacing, x the font size
FIT_SIZES_PT = (7.2, 6.8, 6.4, 6.0)  # the sizes a text block may shrink to before it is cut
CUT = " ... (in full in result.json)"
NOT_FOR_DIAGNOSIS = "Research software - NOT FOR DIAGNOSIS. Check every level on the image yourself."


# ----------------------------------------------------------------------------------------------- numbers

def drawn_mpde_mm(levels: list[dict]) -> float | None:
    """mPDE of the pose drawn: mean PDE (detector mm) of the levels the fit used, at the final pose (their
    ``pde_mm`` are computed with the final projection matrix). None when no level was clicked."""
    values = [float(lv["pde_mm"]) for lv in levels if lv.get("fitted") and lv.get("pde_mm") is not None]
    return float(np.mean(values)) if values else None


# ----------------------------------------------------------------------------------------------- text blocks

def _levels_block(levels: list[dict], check: LevelCheck | None = None) -> str:
    """The levels projected into the image (head to sacrum), then the names of those outside it; none when the
    answer withholds the names (``style.names_shown``)."""
    if not names_shown(check):
        return _wrap("No level is named: " + check.withheld, 38)
    lines = ["level  clicked  PDE mm  (u, v) px"]
    for lv in levels:
        if not lv.get("in_image", True):
            continue
        pde = lv.get("pde_mm")
        u, v = lv["uv_px"]
        lines.append(f"{unsure_name(lv['label'], check):<6} {'yes' if lv.get('fitted') else 'no':<8} "
                     f"{'-' if pde is None else f'{pde:.2f}':>6}  ({u:.0f}, {v:.0f})")
    outside = [lv["label"] for lv in levels if not lv.get("in_image", True)]
    if outside:
        lines.append("")
        lines.append(_wrap("outside the image: " + ", ".join(outside), 38))
    return "\n".join(lines)


def _pose_block(doc: dict, drawn: float | None) -> str:
    pose = doc["pose"]
    units = {"tx_mm": "mm", "ty_mm": "mm", "tz_mm": "mm", "rx_deg": "deg", "ry_deg": "deg", "rz_deg": "deg"}
    lines = ["C-arm pose about the nominal AP view (CT LPS frame):"]
    names = list(pose)
    for i in (0, 3):
        lines.append("  " + "   ".join(f"{n.split('_')[0]} {pose[n]:+8.2f} {units.get(n, '')}"
                                       for n in names[i:i + 3]))
    lines.append(f"magnification at the isocentre {doc['magnification']:.3f}")
    lines.append("mPDE of the pose drawn " + (f"{drawn:.2f} mm" if drawn is not None else "- (no clicks)")
                 + " (mean detector distance, clicked levels)")
    stages = [s for s in doc["stages"] if s.get("mpde_mm") is not None]
    if stages:
        lines.append("per stage: " + ", ".join(f"{s['name']} {s['mpde_mm']:.2f}" for s in stages) + " mm")
    return "\n".join(lines)


def _inputs_block(doc: dict) -> str:
    inputs, geometry = doc.get("inputs") or {}, doc["geometry"]
    sources = geometry.get("sources") or {}
    lines = []
    for key, title in (("ct", "CT"), ("ct_landmarks", "CT centroids"), ("xray", "X-ray"),
                       ("xray_landmarks", "X-ray clicks")):
        value = inputs.get(key)
        if value:
            lines.append(f"{title}: {_short_path(str(value))}")
    spacing = geometry["pixel_spacing_mm"]
    values = {"sdd_mm": f"SDD {geometry['sdd_mm']:.1f} mm",
              "pixel_spacing_mm": f"pixel spacing {spacing[0]:.4g} x {spacing[1]:.4g} mm (column x row)",
              "principal_point_px": "principal point ({:.1f}, {:.1f}) px".format(*geometry["principal_point_px"]),
              "sod_mm": f"SOD {geometry['sod_mm']:.1f} mm"}
    if geometry.get("distortion_mm"):
        values["distortion_mm"] = f"pincushion {geometry['distortion_mm']:.2f} mm at 100 mm from the centre"
    for key, text in values.items():
        lines.append(f"{text}  <- {sources.get(key, 'default' if key == 'sod_mm' else 'not recorded')}")
    lines.append(f"detector {geometry['size_px'][0]} x {geometry['size_px'][1]} px; isocentre at the CT centre "
                 "(LPS {:.1f}, {:.1f}, {:.1f}) mm".format(*geometry["isocenter_lps_mm"]))
    return "\n".join(lines)


def _labellings_block(check: LevelCheck | None, appearance=None, turned: str = "as-stored") -> str:
    """How the levels were named: the X-ray's appearance as found (``turned``: the turn the user had the file turned
    by), the mode and every labelling registered with its score, best first."""
    seen_as = f"X-ray: {appearance.summary(turned)}. " if appearance is not None else ""
    if not check:
        return seen_as + "The level names were not checked against the image (level check off)."
    mode = MODE_DESCRIPTION.get(check.mode, str(check.mode))
    tried = sorted((h for h in check.hypotheses if h.get("refined", True) and h.get("labels")),
                   key=lambda h: float(h.get("score", np.inf)))
    best_of = {}
    for h in tried:  # best first: each labelling's best registration
        best_of.setdefault(tuple(h["labels"]), h)
    shown = list(best_of.values())[:8]
    parts = [f"{'-'.join([h['labels'][0], h['labels'][-1]]) if len(h['labels']) > 1 else h['labels'][0]} "
             f"{float(h['score']):.3f}" + ("*" if h.get("stopped_at_evaluations") else "") for h in shown]
    text = f"{seen_as}Mode: {mode}."
    if parts:
        text += " Labellings registered, score (lower is better): " + ", ".join(parts) + "."
        if any(h.get("stopped_at_evaluations") for h in shown):
            text += " *: stopped early, too far behind to matter."
        if check.withheld:
            text += " They were judged on the image as stored, which was refused: a record, not an answer."
    return text


def _failed_checks(failed: list[str], reason: str) -> str:
    """"CHECKS FAILED" with the failed checks the banner's reason does not already say (a contradiction's or a
    refusal's message is both the reason and a failed check: said twice, it ran out of the banner); advisories
    are not failed checks (they are listed under "Warnings")."""
    rest = [w for w in failed if w not in reason]
    return "CHECKS FAILED" + (": " + "; ".join(rest) if rest else "")


def _short_path(path: str, width: int = 78) -> str:
    return path if len(path) <= width else "..." + path[-(width - 3):]


def _versions_line(doc: dict) -> str:
    rep = doc.get("reproducibility") or {}
    parts = [f"CarmReg {rep.get('carmreg', '?')}"] + [f"{k} {rep[k]}" for k in ("python", "numpy", "scipy", "cma",
                                                                               "numba") if k in rep]
    return "Versions: " + ", ".join(parts) + f"; seed {rep.get('seed', '?')}"


def _wrap(text: str, width: int) -> str:
    return "\n".join(textwrap.fill(par, width) for par in text.split("\n"))


def _line_count(text: str) -> int:
    return text.count("\n") + 1 if text else 0


def fit_text(blocks: list[str], chars_at_7pt2: int, height_in: float, gap_in: float = 0.0) -> tuple[float, list[str]]:
    """(font size pt, the blocks wrapped) so that the blocks, one under the other with ``gap_in`` between, fill at
    most ``height_in`` inches: the largest size of ``FIT_SIZES_PT`` at which they fit, each wrapped to the width
    ``chars_at_7pt2`` characters of 7.2 pt fill (proportionally more when smaller; a block is ``lines x size x
    LINE_SPACING`` pt tall). At the smallest size the text is cut where the room ends, the last line kept ending
    with ``CUT``; a block with no room left is "". Long warnings and reasons thus stay inside the page's boxes."""
    pars = [block.split("\n") if block else [] for block in blocks]
    for size in FIT_SIZES_PT:
        width = int(chars_at_7pt2 * 7.2 / size)
        wrapped = ["\n".join(textwrap.fill(p, width) for p in block) for block in pars]
        used = sum(_line_count(w) for w in wrapped) * size * LINE_SPACING / 72
        if used + gap_in * max(0, sum(bool(w) for w in wrapped) - 1) <= height_in:
            return size, wrapped
    room = int((height_in - gap_in * max(0, len(blocks) - 1)) * 72 / (size * LINE_SPACING))
    cut = []
    for block in pars:
        lines = []
        for par in block:
            if room - len(lines) <= 0:
                break
            lines += textwrap.wrap(par, width, max_lines=room - len(lines), placeholder=CUT) or [""]
        room -= len(lines)
        cut.append("\n".join(lines))
    return size, cut


# ----------------------------------------------------------------------------------------------- page

def report_figure(result, xray_pixels: np.ndarray, clicked: dict | None = None, bone_dark: bool | None = None,
                  composite_rgb: np.ndarray | None = None, made_utc: str | None = None):
    """The report page as a matplotlib Figure (A4 portrait). ``composite_rgb``: the overlay image as the window
    shows it (default: ``screen_composite``); ``clicked``: {name: (u, v) px} of the X-ray clicks; ``bone_dark``:
    the X-ray's polarity (default: the registration's ``appearance``)."""
    from matplotlib.figure import Figure

    from carmreg.logic.report.result_files import result_dict

    bone_dark = result_bone_dark(result, bone_dark)
    doc = result_dict(result)
    check = result.level_check
    status = check.status if check else None
    rgb = composite_rgb if composite_rgb is not None else screen_composite(
        xray_pixels, result.drr_line_integral, bone_dark, mask=getattr(result, "field_mask", None))
    drawn = drawn_mpde_mm(doc["levels"])
    made = made_utc or _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")

    fig = Figure(figsize=A4_INCHES, dpi=100, facecolor="white")
    mono = {"family": "monospace", "fontsize": 7.2, "va": "top"}
    fig.text(0.05, 0.975, "CarmReg - CT to C-arm X-ray registration", fontsize=15, fontweight="bold", va="top")
    fig.text(0.95, 0.975, made, fontsize=8, ha="right", va="top", color="#495057")
    fig.text(0.05, 0.948, NOT_FOR_DIAGNOSIS, fontsize=9, fontweight="bold", color="#c92a2a", va="top")

    headline, reason, colour = level_answer(check, bool(doc["ok"]), detail=False)
    banner = fig.add_axes((0.05, 0.865, 0.90, 0.07))
    banner.set_axis_off()
    banner.set_xlim(0, 1)
    banner.set_ylim(0, 1)
    banner.add_patch(_box(colour))
    banner.text(0.015, 0.78, headline, fontsize=11.5, fontweight="bold", color="white", va="center",
                transform=banner.transAxes)
    paragraphs = [reason] + ([] if doc["ok"] else [_failed_checks(doc["failed_checks"], reason)])
    explained = margin_detail(check)
    paragraphs += [f"({explained})"] if explained else []  # the least needed: cut first
    size, (text,) = fit_text(["\n".join(p for p in paragraphs if p)], 128, (0.56 - 0.05) * 0.07 * A4_INCHES[1])
    banner.text(0.015, 0.56, text, fontsize=size, color="white", va="top", transform=banner.transAxes)

    ax = fig.add_axes((0.05, 0.445, 0.58, 0.41))
    draw_overlay(ax, rgb, doc["levels"], clicked, status, names=names_shown(check))
    fig.text(0.05, 0.438, "Overlay: X-ray (grey, bone bright) + DRR at the found pose (amber). Green disc: level "
             "used by the fit, with its\nPDE to the click; yellow ring: level not clicked; red cross: click"
             + (f"; '?': {UNSURE_WORDS[status]}." if status in UNSURE_WORDS else "."), fontsize=6.8, va="top",
             color="#343a40")

    fig.text(0.655, 0.853, "Named levels (projected)", fontsize=9, fontweight="bold", va="top")
    fig.text(0.655, 0.835, _levels_block(doc["levels"], check), **mono)
    fig.text(0.05, 0.39, "Pose and accuracy", fontsize=9, fontweight="bold", va="top")
    fig.text(0.05, 0.372, _pose_block(doc, drawn), **mono)
    fig.text(0.05, 0.285, "Inputs and geometry (value <- where it came from)", fontsize=9, fontweight="bold",
             va="top")
    size, (inputs,) = fit_text([_inputs_block(doc)], 118, (0.267 - INPUTS_END) * A4_INCHES[1])
    fig.text(0.05, 0.267, inputs, **{**mono, "fontsize": size})
    fig.text(0.05, 0.155, "How the levels were named", fontsize=9, fontweight="bold", va="top")
    _bottom_blocks(fig, _labellings_block(check, getattr(result, "appearance", None),
                                        getattr(result, "xray_turned", "as-stored")),
                   "Warnings: " + "; ".join(doc["warnings"]) if doc["ok"] and doc["warnings"] else "")
    fig.text(0.05, 0.045, _versions_line(doc), fontsize=6.8, va="top", color="#495057")
    fig.text(0.05, 0.028, "Frames: CT LPS mm; detector (u, v) = (column, row) px, 0-based pixel centres; PDE and "
             "mPDE in mm on the detector. Full numbers: result.json.", fontsize=6.5, va="top", color="#495057")
    return fig


INPUTS_END = 0.162  # figure fraction: the inputs block ends above "How the levels were named"
BOTTOM_TOP, BOTTOM_END = 0.137, 0.052  # figure fractions: under "How the levels were named", above the versions


def _bottom_blocks(fig, labellings: str, warnings: str, gap_in: float = 0.05) -> None:
    """The labellings tried and the warnings, one under the other, fitted into the space above the versions line
    (``fit_text``: a case with long warnings gets smaller type, then cut, never text over text)."""
    height_in = (BOTTOM_TOP - BOTTOM_END) * A4_INCHES[1]
    size, (labellings, warnings) = fit_text([labellings, warnings], 125, height_in, gap_in)
    y = BOTTOM_TOP
    for text, colour in ((labellings, "black"), (warnings, "#e8590c")):
        if text:
            fig.text(0.05, y, text, fontsize=size, color=colour, va="top")
            y -= (_line_count(text) * size * LINE_SPACING / 72 + gap_in) / A4_INCHES[1]


def _box(colour: str):
    from matplotlib.patches import FancyBboxPatch

    return FancyBboxPatch((0.0, 0.0), 1.0, 1.0, boxstyle="round,pad=0,rounding_size=0.02", facecolor=colour,
                          edgecolor="none")


def write_report_pdf(path: str | Path, result, xray_pixels: np.ndarray, clicked: dict | None = None,
                     bone_dark: bool | None = None, composite_rgb: np.ndarray | None = None) -> Path:
    """Write the one-page report as a PDF, atomically (see module docstring)."""
    return atomic_write_bytes(path, report_pdf_bytes(result, xray_pixels, clicked, bone_dark, composite_rgb))


def report_pdf_bytes(result, xray_pixels: np.ndarray, clicked: dict | None = None, bone_dark: bool | None = None,
                     composite_rgb: np.ndarray | None = None) -> bytes:
    """The one-page report as the bytes of a PDF (see module docstring)."""
    import io

    import matplotlib

    fig = report_figure(result, xray_pixels, clicked, bone_dark, composite_rgb)
    meta = {"Title": "CarmReg registration report", "Creator": "CarmReg", "Subject": NOT_FOR_DIAGNOSIS}
    buffer = io.BytesIO()
    with matplotlib.rc_context({"pdf.fonttype": 3}):
        fig.savefig(buffer, format="pdf", metadata=meta)
    return buffer.getvalue()


def write_report_png(path: str | Path, result, xray_pixels: np.ndarray, clicked: dict | None = None,
                     bone_dark: bool | None = None, composite_rgb: np.ndarray | None = None, dpi: int = 110) -> Path:
    """The same page as a PNG (for the README and quick looks)."""
    fig = report_figure(result, xray_pixels, clicked, bone_dark, composite_rgb)
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi))
