"""Atomic writes and the JSON conversion every written document goes through."""

import json
import stat

import numpy as np

from carmreg.logic.io.atomic import atomic_write_json, to_jsonable


def test_to_jsonable_turns_numpy_tuples_and_non_finite_values_into_valid_json(tmp_path):
    doc = {"margin": float("inf"), "pose": (np.float32(1.5), np.int64(2)), "P": np.eye(2), "path": tmp_path}
    path = atomic_write_json(tmp_path / "out.json", to_jsonable(doc))  # allow_nan=False would refuse inf
    assert json.loads(path.read_text()) == {"margin": None, "pose": [1.5, 2], "P": [[1.0, 0.0], [0.0, 1.0]],
                                            "path": str(tmp_path)}


def test_atomic_write_leaves_no_temporary_file_and_a_readable_mode(tmp_path):
    atomic_write_json(tmp_path / "a.json", {"x": 1})
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) & 0o044  # not the 0600 of mkstemp
