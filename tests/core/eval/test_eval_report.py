"""Text tables and JSON output."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from voxfusion.core.eval import MeshMetrics, compute_ate, format_table, to_jsonable, write_json


def test_format_table_aligns_columns():
    rows = [{"name": "ate", "value": 1.23456, "n": 10}, {"name": "rotation error", "value": np.float32(2.0)}]
    text = format_table(rows, ["name", "value", "n"])
    lines = text.splitlines()
    assert lines[0].split() == ["name", "value", "n"]
    assert set(lines[1].replace(" ", "")) == {"-"}
    assert lines[2].split() == ["ate", "1.235", "10"]
    assert lines[3].split() == ["rotation", "error", "2.000", "-"]
    # Numbers are right-aligned: the value column ends at the same character in every row.
    ends = {line.index(tok) + len(tok) for line, tok in zip(lines[2:], ["1.235", "2.000"], strict=True)}
    assert len(ends) == 1
    assert format_table(rows, ["value"], float_fmt=".1f").splitlines()[2].strip() == "1.2"
    assert format_table([], ["a", "bb"]).splitlines() == ["a  bb", "-  --"]


def test_to_jsonable_converts_numpy_dataclasses_paths_and_nan():
    @dataclass
    class Thing:
        a: np.ndarray
        b: Path

    obj = {
        "f": np.float32(0.5), "i": np.int64(3), "b": np.bool_(True), "arr": np.eye(2), "nan": float("nan"),
        "t": (1, 2), "thing": Thing(np.array([1.0]), Path("/x/y")), 4: None,
    }
    out = to_jsonable(obj)
    assert out == {
        "f": 0.5, "i": 3, "b": True, "arr": [[1.0, 0.0], [0.0, 1.0]], "nan": None, "t": [1, 2],
        "thing": {"a": [1.0], "b": "/x/y"}, "4": None,
    }
    with pytest.raises(TypeError):
        to_jsonable(object())


def test_write_json_round_trip_uses_summaries(tmp_path):
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = np.arange(5.0)
    T[:, 1, 3] = np.arange(5.0) ** 2
    ate = compute_ate(T, T)
    mesh = MeshMetrics(0.01, 0.02, 0.9, 0.95, 0.9, 0.92, 0.05, 1000, 800, "exact")
    path = write_json(tmp_path / "sub" / "out.json", {"ate": ate, "mesh": mesh})
    data = json.loads(path.read_text())
    assert data["ate"]["n"] == 5 and data["ate"]["aligned"] is True
    assert "errors_m" not in data["ate"]  # the summary, not the per-pose errors
    assert len(data["ate"]["T_align"]) == 4
    assert data["mesh"]["method"] == "exact" and math.isclose(data["mesh"]["fscore"], 0.92)
