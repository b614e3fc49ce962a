"""`carmreg register` names unnamed X-ray clicks and identifies levels without clicks, on the sample case."""

import json

import pytest

from carmreg.cli import main
from carmreg.logic.image.appearance import STORAGE_FROM_USER
from carmreg.logic.io.landmarks import read_landmarks_2d

pytestmark = pytest.mark.slow


def _args(case_dir, out, cache_dir, *clicks):
    return ["register", "--ct", str(case_dir / "ct.nrrd"), "--ct-landmarks", str(case_dir / "ct_centroids.mrk.json"),
            "--xray", str(case_dir / "xray.dcm"), "--out", str(out), "--cache-dir", cache_dir,
            *clicks]


def test_unnamed_clicks_as_a_json_list_are_named_in_result_json(sample_case_dir, tmp_path, drr_cache_dir, capsys):
    truth = read_landmarks_2d(sample_case_dir / "xray_centroids.mrk.json")
    order = [1, 2, 0]
    clicks = tmp_path / "clicks.json"
    clicks.write_text(json.dumps([truth.uv_px[i].tolist() for i in order]))  # [[column, row], ...], no names
    code = main(_args(sample_case_dir, tmp_path / "out", drr_cache_dir, "--xray-landmarks", str(clicks),
                      "--storage", "log-display"))  # set as the image finds it (the demo: "stored as log display")
    assert code == 0
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert (doc["appearance"]["storage"], doc["appearance"]["storage_from"]) == ("log-display", STORAGE_FROM_USER)
    check = doc["level_check"]
    assert check["mode"] == "unnamed" and check["status"] == "confident"
    assert check["assigned_labels"] == [truth.labels[i] for i in order]
    fitted = {lv["label"]: lv for lv in doc["levels"] if lv["fitted"]}
    assert set(fitted) == set(truth.labels)
    assert all(lv["name_margin"] == pytest.approx(check["margin"]) for lv in fitted.values())
    assert "level identification: clicks named" in capsys.readouterr().out
    # the 3D Slicer scene (Testing/Logic/report/test_slicer_files.py opens one with Slicer's loader)
    scene = tmp_path / "out" / "slicer"
    assert {"CarmReg.mrml", "ct.nrrd", "xray.nrrd", "drr.nrrd", "carm.tfm"} <= {p.name for p in scene.iterdir()}
    projected = json.loads((scene / "projected_levels.mrk.json").read_text())["markups"][0]["controlPoints"]
    assert [(p["label"], p["carmreg"]["uv_px"]) for p in projected] == [(lv["label"], lv["uv_px"])
                                                                         for lv in doc["levels"]]
    pypdf = pytest.importorskip("pypdf")  # the one-page report carmreg register writes beside result.json
    pages = pypdf.PdfReader(str(tmp_path / "out" / "report.pdf")).pages
    text = " ".join(pages[0].extract_text().split())  # the page wraps its lines where the words fall
    assert len(pages) == 1 and "LEVELS CONFIRMED BY THE IMAGE: " + ", ".join(check["assigned_labels"]) in text
    assert "NOT FOR DIAGNOSIS" in text and "unnamed clicks, named from the image" in text


def test_no_clicks_names_the_levels_in_view(sample_case_dir, tmp_path, drr_cache_dir, capsys):
    code = main(_args(sample_case_dir, tmp_path / "out", drr_cache_dir, "--no-clicks"))
    assert code == 0
    check = json.loads((tmp_path / "out" / "result.json").read_text())["level_check"]
    assert check["mode"] == "image_only" and {"T10", "T11", "T12"} <= set(check["visible_labels"])
    assert "from the image alone" in capsys.readouterr().out
