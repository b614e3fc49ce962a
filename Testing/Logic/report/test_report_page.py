"""The one-page report (``report.page``): written as a real one-page PDF whose text reads back - the level
answer in words with its reason, the named levels with their distances, the pose, the magnification, the
mPDE of the pose drawn, the inputs with the geometry sources, the versions and "not for diagnosis"."""

import numpy as np
import pytest

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project
from carmreg.logic.registration.level_check import LevelCheck
from carmreg.logic.registration.pipeline import RegistrationParameters, RegistrationResult, StageResult
from carmreg.logic.report.page import drawn_mpde_mm, write_report_pdf
from carmreg.logic.report.style import answer_banner, level_answer

pypdf = pytest.importorskip("pypdf")


def _result(status: str) -> RegistrationResult:
    """A small result by hand (no pipeline): three clicked levels and one more, 128 x 96 px detector."""
    intr = CarmIntrinsics(1000.0, (0.8, 0.8), (128, 96), sources={"sdd_mm": "manual", "pixel_spacing_mm":
                                                                   "DICOM (0018,1164) ImagerPixelSpacing"})
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0)
    pose = CarmPose(5.0, 1.0, -2.0, 1.0, 0.5, -0.5)
    P = geometry.projection_matrix(pose)
    points = {"T10": [0, 0, 15.0], "T11": [0, 0, 0.0], "T12": [0, 0, -15.0], "L1": [0, 0, -30.0]}  # in view
    levels = []
    for i, (label, point) in enumerate(points.items()):
        uv = project(P, np.array([point]))[0]
        fitted = label != "L1"
        levels.append({"label": label, "uv_px": uv.tolist(), "fitted": fitted, "in_image": True,
                       "pde_mm": [0.5, 1.5, 1.0][i] if fitted else None,
                       "clicked_uv_px": (uv + 1).tolist() if fitted else None, "name_margin": None})
    given, other = ["T10", "T11", "T12"], ["T11", "T12", "L1"]
    check = {"mode": "named", "status": status, "margin": -0.08 if status == "contradicted" else 0.08,
             "message": "level names CONTRADICTED: the image fits T11, T12, L1 better than the names given "
                        "(T10, T11, T12)" if status == "contradicted" else "level names T10, T11, T12: agree",
             "assigned_labels": given, "winner_labels": other if status == "contradicted" else given,
             "runner_up_labels": other, "hypotheses": [{"labels": given, "score": 0.6, "refined": True},
                                                       {"labels": other, "score": 0.52, "refined": True}]}
    rows, cols = 96, 128
    xray = np.add.outer(np.arange(rows), np.arange(cols)).astype(np.float32)
    stages = [StageResult("fine", pose, 0.48, 0.1), StageResult("refine", pose, 1.0, 1.0)]
    return RegistrationResult(pose=pose, projection_matrix=P, geometry=geometry, stages=stages, levels=levels,
                              drr_line_integral=xray[::-1].copy(), xray_line_integral=xray, convergence=[],
                              trajectory=[], similarity_maps={}, database_grid={}, ok=status != "contradicted",
                              warnings=[check["message"]] if status == "contradicted" else [],
                              failed_checks=[check["message"]] if status == "contradicted" else [],
                              parameters=RegistrationParameters(), level_check=LevelCheck.from_dict(check),
                              inputs={"ct": "/data/ct.nrrd", "xray": "/data/xray.dcm", "geometry_sources":
                                      dict(intr.sources)})


def test_the_page_reads_back_with_the_answer_levels_pose_inputs_and_versions(tmp_path):
    result = _result("contradicted")
    xray = result.xray_line_integral
    path = write_report_pdf(tmp_path / "report.pdf", result, xray, {"T10": [10.0, 20.0]}, bone_dark=False)
    reader = pypdf.PdfReader(str(path))
    assert len(reader.pages) == 1
    text = reader.pages[0].extract_text()
    for expected in ("NOT FOR DIAGNOSIS", "LEVEL NAMES CONTRADICTED BY THE IMAGE: T10, T11, T12",
                     "the image fits T11, T12, L1 better", "CHECKS FAILED", "T10?", "L1",
                     "mPDE of the pose drawn 1.00 mm", "magnification at the isocentre",
                     "SDD 1000.0 mm  <- manual", "<- DICOM (0018,1164) ImagerPixelSpacing", "CT: /data/ct.nrrd",
                     "CarmReg 0.1.0", "seed 1", "T10-T12 0.600"):
        assert expected in text, expected
    assert "0.48" not in text.split("mPDE of the pose drawn")[1].split("\n")[0]  # not the fine stage's


def test_an_advisory_is_listed_as_a_warning_not_as_a_failed_check(tmp_path):
    """A contradicted answer with the intensifier's advisory: "CHECKS FAILED" lists the failed checks only (the
    contradiction, said once as the reason), never the advisory, which the window's banner leaves out too."""
    advisory = "the X-ray's field is round, as an image intensifier's: its pincushion is not corrected"
    result = _result("contradicted")
    result.warnings = result.warnings + [advisory]
    path = write_report_pdf(tmp_path / "report.pdf", result, result.xray_line_integral, {}, bone_dark=False)
    text = " ".join(pypdf.PdfReader(str(path)).pages[0].extract_text().split())
    assert "CHECKS FAILED" in text and "CHECKS FAILED: the X-ray's field" not in text
    assert text.count("the image fits T11, T12, L1 better") == 1
    failed = answer_banner(None, False, ["fine-stage mPDE 9.0 mm exceeds 6.0 mm"])
    assert advisory not in failed[1]


def test_drawn_mpde_and_the_answer_in_words_and_colour():
    result = _result("confident")
    assert drawn_mpde_mm(result.levels) == pytest.approx(1.0)  # (0.5 + 1.5 + 1.0) / 3, L1 not clicked
    assert drawn_mpde_mm([{"label": "T1", "fitted": False, "pde_mm": None}]) is None
    headline, reason, colour = level_answer(result.level_check)
    assert headline == "LEVELS CONFIRMED BY THE IMAGE: T10, T11, T12" and colour == "#2b8a3e"
    assert "lower is better" in reason and "0.02" in reason
    assert answer_banner(None, True, []) is None
    failed = answer_banner(None, False, ["fine-stage mPDE 9.0 mm exceeds 6.0 mm"])
    assert failed[0].startswith("CHECKS FAILED") and failed[1].startswith("fine-stage") and failed[2] == "#c92a2a"
    red = level_answer(_result("contradicted").level_check, ok=False)
    assert red[0].startswith("LEVEL NAMES CONTRADICTED") and red[2] == "#c92a2a"


def _near(rgb: np.ndarray, colour: str, tolerance: float = 40.0) -> np.ndarray:
    """Mask of the pixels within ``tolerance`` (RGB distance, 0..255) of a ``#rrggbb`` colour."""
    from carmreg.logic.report.style import hex_rgb

    return np.linalg.norm(rgb.astype(float) - np.array(hex_rgb(colour), float), axis=-1) <= tolerance


@pytest.mark.parametrize("status", ["contradicted", "confident"])
def test_overlay_png_draws_contradicted_names_in_the_contradiction_colour(tmp_path, status):
    from PIL import Image

    from carmreg.logic.report.result_files import save_result
    from carmreg.logic.report.style import FITTED_COLOUR, status_ink

    result = _result(status)
    clicked = {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv["fitted"]}
    paths = save_result(result, tmp_path / "out", result.xray_line_integral, clicked)
    rgb = np.asarray(Image.open(paths["overlay"]).convert("RGB"))
    assert rgb.shape == (96, 128, 3)  # the X-ray's size, on its pixel grid
    red, green = _near(rgb, status_ink("contradicted")).sum(), _near(rgb, FITTED_COLOUR).sum()
    if status == "contradicted":  # "T10?  0.5 mm" ... in red: the wrong names never look confirmed
        assert red > 60 and green < 5, (red, green)
    else:
        assert green > 60 and red < 5, (red, green)


def test_a_margin_without_a_rival_is_written_as_null_not_a_traceback(tmp_path):
    """No clicks on a CT with few levels: one labelling only, so its margin is inf (seen on the appearance
    benchmark's second CT: the result folder was never written). result.json says null."""
    import json

    from carmreg.logic.report.result_files import save_result

    result = _result("confident")
    for level in result.levels:
        level["name_margin"] = float("inf")
    result.level_check.margin = float("inf")
    paths = save_result(result, tmp_path / "out", result.xray_line_integral)
    doc = json.loads(paths["result"].read_text())
    assert [lv["name_margin"] for lv in doc["levels"]] == [None] * 4
    assert doc["level_check"]["margin"] is None and doc["ok"] is True


def test_the_labellings_line_lists_each_labellings_best_registration_and_marks_the_stopped_ones():
    from carmreg.logic.report.page import _labellings_block

    hypotheses = [{"labels": ["T10", "T11", "T12"], "score": 0.60, "refined": True},
                  {"labels": ["T11", "T12", "L1"], "score": 0.52, "refined": True},
                  {"labels": ["T10", "T11", "T12"], "score": 0.58, "refined": True},  # its refit: the better one
                  {"labels": ["T8", "T9", "T10"], "score": 0.95, "refined": True, "stopped_at_evaluations": 480},
                  {"labels": ["T9", "T10", "T11"], "score": 0.9, "refined": False}]  # planned, never registered
    check = LevelCheck("named", "confident", hypotheses=hypotheses)
    text = " ".join(_labellings_block(check).split())
    assert "T11-L1 0.520, T10-T12 0.580, T8-T10 0.950*." in text and "T9-T11" not in text
    assert text.endswith("*: stopped early, too far behind to matter.")
    hypotheses[3].pop("stopped_at_evaluations")
    assert "*" not in _labellings_block(check)


REFUSED = ("the X-ray matches the CT best mirrored left right (GC 0.78 against 0.40 as stored): the display is "
           "mirrored or rotated; export the image as acquired and register again")


def test_a_refused_image_names_no_level_on_any_front_door(tmp_path):
    """A refused X-ray (mirrored display) withholds the names (``LevelCheck.withheld_for``): result.json keeps the
    contest's record but names no click; overlay.png, the report page and the command line write no level name
    (the 3D Slicer scene: ``test_slicer_files``)."""
    import json

    from PIL import Image

    from carmreg.logic.report.result_files import save_result
    from carmreg.logic.report.style import FITTED_COLOUR, level_banner, level_summary

    shown = _result("confident")
    refused = _result("confident")
    refused.level_check = refused.level_check.withheld_for(REFUSED)
    refused.ok, refused.warnings, refused.failed_checks = False, [REFUSED], [REFUSED]
    check = refused.level_check
    assert (check.status, check.assigned_labels, check.names(), check.winner_labels) == (
        "ambiguous", [], [], ["T10", "T11", "T12"])  # never confident; the contest's winner kept as its record
    assert LevelCheck.from_dict(check.to_dict()) == check
    assert answer_banner(check, False, [REFUSED]) == ("IMAGE REFUSED - NO LEVEL NAMED",
                                                      "level names WITHHELD: " + REFUSED, "#c92a2a")
    assert level_banner(check)[0] == "Levels: IMAGE REFUSED - NO LEVEL NAMED"
    assert level_summary(check) == "level identification: level names WITHHELD: " + REFUSED

    def written(result, name):
        clicked = {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv["fitted"]}
        return save_result(result, tmp_path / name, result.xray_line_integral, clicked, ct=None)

    paths, before = written(refused, "refused"), written(shown, "shown")
    doc = json.loads(paths["result"].read_text())["level_check"]
    assert doc["withheld"] == REFUSED and doc["assigned_labels"] == [] and doc["status"] == "ambiguous"
    text = pypdf.PdfReader(str(paths["report"])).pages[0].extract_text()
    assert "IMAGE REFUSED - NO LEVEL NAMED" in text and "No level is named" in text
    assert "a record, not an answer" in " ".join(text.split())
    # the refusal said once in the banner (its reason; "CHECKS FAILED" adds nothing it says) and once beside the image
    assert " ".join(text.split()).count("GC 0.78 against 0.40") == 2 and "CHECKS FAILED" in text
    assert not any(line.split()[:2] in (["T11", "yes"], ["L1", "no"]) for line in text.splitlines())
    names = {}
    for key, result_paths in (("refused", paths), ("shown", before)):
        rgb = np.asarray(Image.open(result_paths["overlay"]).convert("RGB"))
        names[key] = _near(rgb, FITTED_COLOUR).sum()  # the green discs, and the names beside them when shown
    assert names["refused"] < 0.5 * names["shown"], names


@pytest.mark.parametrize("words", [60, 400])
def test_long_reasons_and_warnings_stay_in_their_boxes_smaller_then_cut(words):
    """An unclear image's page carries long texts (the level message, the polarity note, every warning): each text
    block stays inside its place - the banner's reason inside the banner, the labellings and the warnings above the
    versions line and not over each other - in smaller type when needed, cut with a pointer to result.json when even
    that is too long (measured on the drawn page, not estimated)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from carmreg.logic.report.page import CUT, FIT_SIZES_PT, report_figure

    result = _result("confident")
    long = " ".join(f"word{i % 10}" for i in range(words))
    result.level_check.status, result.level_check.message = "ambiguous", "level names AMBIGUOUS: " + long
    result.warnings = [f"X-ray polarity: {long}", "X-ray orientation: check that the display is not mirrored"]
    fig = report_figure(result, result.xray_line_integral, {}, bone_dark=False)
    renderer = FigureCanvasAgg(fig).get_renderer()
    texts = {t.get_text().split()[0]: t for t in fig.texts + fig.axes[0].texts if t.get_text()}
    banner_box = fig.axes[0].get_window_extent(renderer)
    reason = next(t for t in fig.axes[0].texts if t.get_text().startswith("level names AMBIGUOUS"))
    assert banner_box.contains(*reason.get_window_extent(renderer).p0)  # the reason's lower left is in the banner
    blocks = [texts["Mode:"], texts["Warnings:"], texts["Versions:"]]
    boxes = [t.get_window_extent(renderer) for t in blocks]
    assert boxes[0].y0 > boxes[1].y1 and boxes[1].y0 > boxes[2].y1  # one under the other, none over another
    sizes = {t.get_fontsize() for t in (reason, blocks[0], blocks[1])}
    assert sizes <= set(FIT_SIZES_PT) and min(sizes) < FIT_SIZES_PT[0]  # smaller type than a short page's
    cut = any(t.get_text().endswith(CUT.strip()) for t in (reason, blocks[1]))
    assert cut == (words == 400)  # cut only when even the smallest type cannot hold it


def test_the_overlay_banners_reason_never_covers_a_level():
    """overlay.png: the banner's reason is written under its headline only while it stays above the highest
    level drawn (the demo without clicks lost T8's name under it)."""
    from carmreg.logic.report.overlay import render_overlay

    rgb = np.full((400, 400, 3), 90, np.uint8)
    check = _result("ambiguous").level_check

    def banner_rows(v_px: float) -> int:
        level = {"label": "T8", "uv_px": [200.0, v_px], "fitted": False, "pde_mm": None, "in_image": True}
        out = render_overlay(rgb, [level], None, check, True, [])
        column = out[:, 3].astype(int)
        return int(np.sum(np.abs(column - 90).sum(axis=1) > 30))  # rows of the banner's colour at the left edge

    low, high = banner_rows(390.0), banner_rows(30.0)
    assert high < low  # the reason left out when a level sits high
    assert high > 5  # the headline stays


def test_every_name_the_image_did_not_confirm_carries_a_question_mark():
    """The levels not clicked are placed by the pose fitted to the names: when the image contradicts those names,
    or cannot confirm them (ambiguous), they may sit on a neighbour, so every name is marked unsure (the levels
    not clicked keeping their colour, the fitted ones in the status's ink); confident, proposed and unchecked
    names stay plain."""
    from carmreg.logic.report.style import CHECK_COLOUR, FITTED_COLOUR, level_marker, status_ink

    clicked = {"label": "T10", "fitted": True, "pde_mm": 1.2}
    other = {"label": "L1", "fitted": False, "pde_mm": None}
    for status in ("confident", "proposed", None):
        assert [level_marker(lv, status).text for lv in (clicked, other)] == ["T10  1.2 mm", "L1"]
        assert level_marker(clicked, status).colour == FITTED_COLOUR
    for status in ("ambiguous", "contradicted"):
        assert [level_marker(lv, status).text for lv in (clicked, other)] == ["T10?  1.2 mm", "L1?"]
        assert level_marker(clicked, status).colour == status_ink(status) != FITTED_COLOUR
        assert level_marker(other, status).colour == CHECK_COLOUR


def test_an_ambiguous_page_lists_and_draws_its_names_with_a_question_mark(tmp_path):
    """An ambiguous answer: the page's list of named levels carries the "?", and so does the caption."""
    result = _result("ambiguous")
    path = write_report_pdf(tmp_path / "report.pdf", result, result.xray_line_integral, {}, bone_dark=False)
    text = " ".join(pypdf.PdfReader(str(path)).pages[0].extract_text().split())
    assert "LEVELS AMBIGUOUS" in text
    assert "T10? yes" in text and "'?': name not confirmed by the image" in text
