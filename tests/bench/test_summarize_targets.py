"""bench/summarize_targets.py: the table it prints from targets_*.json files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import summarize_targets


def _method(ate_m: float, rpe_m: float, fps: float) -> dict:
    return {"ate_aligned": {"rmse_m": ate_m}, "rpe": {"trans_rmse_m": rpe_m, "rot_rmse_deg": 0.25},
            "fps": fps, "mesh": None, "extra": {"frames_lost": 0}}


def test_the_table_carries_ate_and_rpe_of_both_methods(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    run = {"machine": {"cpu_model": "test cpu"},
           "methods": {"voxfusion": _method(0.0022, 0.0031, 7.7), "baseline": _method(0.0017, 0.0039, 10.6)}}
    (tmp_path / "targets_tum_desk_seed1.json").write_text(json.dumps(run))
    monkeypatch.setattr(summarize_targets, "RESULTS", tmp_path)
    assert summarize_targets.main() == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| tum_desk")]
    assert row == ["| tum_desk | 1 | default | 0.22 | 0.17 | 3.10 | 3.90 | 7.70 | 10.60 | - |"]
    summary = json.loads((tmp_path / "targets_summary.json").read_text())["rows"][0]
    assert summary["voxfusion"]["rpe_mm"] == pytest.approx(3.1)
    assert summary["baseline"]["rpe_deg"] == pytest.approx(0.25)
