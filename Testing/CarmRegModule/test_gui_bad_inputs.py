"""A dozen broken inputs through the window: each gives one dialog naming the file and the problem, no
traceback, and leaves what was loaded before untouched."""

import json

import numpy as np
import pytest
from PIL import Image

pytestmark = pytest.mark.gui


def _text(path, content):
    path.write_text(content)
    return path


def _rgb_png(path):
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[..., 0] = 200  # channels differ: a colour picture, not an X-ray
    Image.fromarray(rgb).save(path)
    return path


BROKEN = {
    # action, file maker -> the file's name must appear in the dialog
    "CT missing": ("_action_load_ct", lambda d: d / "missing.nrrd"),
    "CT empty": ("_action_load_ct", lambda d: _text(d / "empty.nii.gz", "")),
    "CT garbage NRRD": ("_action_load_ct", lambda d: _text(d / "broken.nrrd", "NRRD0004\ngarbage\n")),
    "CT text as MetaImage": ("_action_load_ct", lambda d: _text(d / "notes.mha", "hello")),
    "X-ray missing": ("_action_load_xray", lambda d: d / "missing.dcm"),
    "X-ray empty DICOM": ("_action_load_xray", lambda d: _text(d / "empty.dcm", "")),
    "X-ray text as PNG": ("_action_load_xray", lambda d: _text(d / "photo.png", "not a png")),
    "X-ray colour PNG": ("_action_load_xray", lambda d: _rgb_png(d / "colour.png")),
    "CT points not JSON": ("_action_import_ct", lambda d: _text(d / "points.mrk.json", "{oops")),
    "CT points unknown level": ("_action_import_ct", lambda d: _text(d / "levels.json",
                                                                     json.dumps({"X9": [0, 0, 0]}))),
    "X-ray points NaN": ("_action_import_xray", lambda d: _text(d / "nan.json", '{"T12": [NaN, 3]}')),
    "X-ray points duplicate": ("_action_import_xray",
                               lambda d: _text(d / "dup.json", '{"T12": [1, 2], "t12": [3, 4]}')),
}


@pytest.mark.parametrize("name", list(BROKEN))
def test_broken_input_gives_one_dialog_and_keeps_the_session(window, synthetic_case, tmp_path, name):
    window.load_ct(synthetic_case.ct_path)
    window.load_xray(synthetic_case.xray_path)
    before = (window.ct_volume, window.xray, len(window.ct_store.to_landmarks().labels))
    action, make = BROKEN[name]
    path = make(tmp_path)
    window.dialogs.answers["open_file"] = [str(path)]
    getattr(window, action)()
    assert len(window.dialogs.messages) == 1, window.dialogs.messages
    title, message, details = window.dialogs.messages[0]
    assert path.name in message, message
    assert details is None and "Traceback" not in message  # a user error, not a crash
    assert "\n" not in message.strip()
    assert (window.ct_volume, window.xray, len(window.ct_store.to_landmarks().labels)) == before


def _session(field: str) -> str:
    return ('{"format": "carmreg-session", "landmarks": {"ct": [{"label": "T1", "position_lps_mm": [0, 0, 0]}]}, '
            + field + "}")


BAD_SESSIONS = {  # issue 14
    "sdd text": ("sdd.carmreg.json", '"geometry_overrides": {"sdd_mm": "abc"}'),
    "version text": ("version.carmreg.json", '"version": "abc"'),
    "data list": ("list.carmreg.json", '"data": [1]'),
    "deep nesting": ("deep.carmreg.json", '"last_result": ' + "[" * 100_000 + "]" * 100_000),
}


@pytest.mark.parametrize("name", list(BAD_SESSIONS))
def test_damaged_session_gives_one_dialog_and_keeps_the_scene(window, synthetic_case, tmp_path, name):
    """A damaged session is refused whole before anything is cleared (was: CT only, X-ray and points gone; or
    an "Unexpected error" dialog with a traceback)."""
    window.load_ct(synthetic_case.ct_path)
    window.load_xray(synthetic_case.xray_path)
    before = (window.ct_volume, window.xray, len(window.ct_store.to_landmarks().labels))
    file_name, field = BAD_SESSIONS[name]
    path = _text(tmp_path / file_name, _session(field))
    window.dialogs.answers["question"] = ["Discard"]
    window.dialogs.answers["open_file"] = [str(path)]
    window._action_open_session()
    errors = [m for m in window.dialogs.messages if path.name in m[1]]
    assert len(errors) == 1, window.dialogs.messages
    title, message, details = errors[0]
    assert details is None and "Traceback" not in message and "Unexpected" not in message
    assert (window.ct_volume, window.xray, len(window.ct_store.to_landmarks().labels)) == before
