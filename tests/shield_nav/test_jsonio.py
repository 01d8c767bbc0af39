"""The atomic JSON writer that stage markers, evaluation units and summaries go through."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from shield_nav.jsonio import write_json


def test_numpy_values_are_written_as_plain_numbers(tmp_path):
    path = str(tmp_path / "a.json")
    write_json(path, {"n": np.int64(7), "x": np.float32(0.5), "v": np.arange(3), "ok": np.bool_(True)})
    with open(path) as f:
        assert json.load(f) == {"n": 7, "x": 0.5, "v": [0, 1, 2], "ok": True}
    assert os.listdir(tmp_path) == ["a.json"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = str(tmp_path / "marker.json")
    write_json(path, {"stage": 1})
    with pytest.raises(TypeError, match="set is not JSON serialisable"):
        write_json(path, {"stage": 2, "bad": {1, 2}})
    with open(path) as f:
        assert json.load(f) == {"stage": 1}
    assert os.listdir(tmp_path) == ["marker.json"]


def test_replaces_an_existing_file_whole(tmp_path):
    path = str(tmp_path / "s.json")
    write_json(path, {"long": "x" * 1000})
    write_json(path, [1, 2])
    with open(path) as f:
        assert f.read() == "[\n 1,\n 2\n]"
