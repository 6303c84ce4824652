"""Presets: kind + size composition, the capture profiles' facts under them, the chooser (``preset_for``),
the one warning for GPU sizes on a CPU, and ``voxfusion run`` without ``--config`` end to end."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from voxfusion.cli import app
from voxfusion.core.config import config_to_dict
from voxfusion.core.datasets import CaptureProfile, open_capture
from voxfusion.core.datasets.frame import BaseCapture
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig, write_capture
from voxfusion.core.errors import ConfigError
from voxfusion.core.slam.presets import (
    GPU_SIZES_ON_CPU_FPS,
    PAPER_SIZES_ON_CPU_FPS,
    UNREGISTERED_COLOR_WEIGHT,
    check_preset_name,
    load_preset,
    preset_for,
    profile_overrides,
    size_warning,
)

TYPICAL = {
    "tum": CaptureProfile("tum", 4.0, sensor="TUM RGB-D"),
    "sevenscenes": CaptureProfile("sevenscenes", 4.0, color_registered=False),
    "replica": CaptureProfile("replica", 10.0),
    "scannet": CaptureProfile("scannet", 5.0, color_registered=False),
    "iphone": CaptureProfile("iphone", 5.0, has_confidence=True, has_color=False),
    "synthetic": CaptureProfile("synthetic", 10.0),
    "unknown": CaptureProfile(),
}


class _ProfiledCapture(BaseCapture):
    """A capture that is nothing but its profile (the chooser reads nothing else)."""

    def __init__(self, profile: CaptureProfile) -> None:
        self._profile = profile
        self.name = f"fake-{profile.kind}"
        self.path = Path(self.name)

    def __len__(self) -> int:
        return 0


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.fixture
def cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)


def test_sizes_win_over_kinds_whatever_the_order():
    a, b = load_preset("replica+cpu"), load_preset("cpu+replica")
    assert a == b
    assert (a.mapping.rays_per_frame, a.sized_for, a.device) == (256, "cpu", "cpu")  # replica's 2048 is a GPU size
    assert load_preset("replica").mapping.rays_per_frame == 2048
    assert load_preset("replica+paper").mapping.rays_per_frame == 4096


def test_per_kind_sections_and_old_names():
    iphone = load_preset("iphone+cpu")
    assert load_preset("iphone-small") == iphone
    assert load_preset("cpu-small") == load_preset("cpu")
    assert (iphone.mapping.map_every, iphone.tracking.iters, iphone.tracking.device_prior_weight) == (2, 10, 1000.0)
    assert (iphone.mapping.rays_per_frame, iphone.field.sdf_hidden) == (256, 64)
    tum = load_preset("tum+cpu")
    assert (tum.mapping.map_every, tum.tracking.iters) == (1, 20)  # the iphone section stays with iphone


def test_composition_errors_name_the_problem(tmp_path: Path):
    with pytest.raises(ConfigError, match="at most one size preset"):
        load_preset("cpu+paper")
    with pytest.raises(ConfigError, match="empty name"):
        load_preset("tum+")
    with pytest.raises(ConfigError, match="no preset named 'nope'"):
        load_preset("nope+cpu")
    (tmp_path / "kind.yaml").write_text("per_kind:\n  tum:\n    seed: 1\n")
    with pytest.raises(ConfigError) as e:
        load_preset(tmp_path / "kind.yaml")
    assert e.value.field == "per_kind"
    (tmp_path / "size.yaml").write_text("sized_for: cpu\nper_kind:\n  iphnoe:\n    seed: 1\n")
    with pytest.raises(ConfigError) as e:
        load_preset(str(tmp_path / "size.yaml"))
    assert e.value.field == "per_kind.iphnoe"
    (tmp_path / "mine.yaml").write_text("seed: 7\n")  # a user's kind file composes with a shipped size
    assert load_preset(f"{tmp_path / 'mine.yaml'}+cpu").seed == 7


def test_server_names_never_paths():
    for ok in ("tum", "iphone+cpu", "iphone-small", "cpu"):
        check_preset_name(ok)
    for bad in ("../etc", "nope", "tum+/etc/passwd", "configs/tum.yaml"):
        with pytest.raises(ConfigError) as e:
            check_preset_name(bad)
        assert e.value.field == "preset"


def test_profile_facts_become_settings():
    assert profile_overrides(TYPICAL["sevenscenes"]) == {"mapping": {"max_depth_m": 4.0},
                                                         "loss": {"w_color": UNREGISTERED_COLOR_WEIGHT},
                                                         "tracking": {"sdf_w_photo": 0.0}}
    assert profile_overrides(TYPICAL["iphone"]) == {"mapping": {"max_depth_m": 5.0, "min_confidence": 1},
                                                    "loss": {"w_color": 0.0}}
    assert profile_overrides(CaptureProfile()) == {}


def test_profile_facts_lie_under_presets_and_overrides():
    scannet = load_preset("scannet", profile=TYPICAL["scannet"])
    assert (scannet.loss.w_color, scannet.mapping.max_depth_m) == (0.2, 5.0)  # the preset's own weight wins
    cfg = load_preset("sevenscenes+cpu", ["mapping.max_depth_m=3.5"], profile=TYPICAL["sevenscenes"])
    assert (cfg.loss.w_color, cfg.mapping.max_depth_m) == (UNREGISTERED_COLOR_WEIGHT, 3.5)
    assert cfg.tracking.sdf_w_photo == 0.0  # unregistered colour: no photometric tracking term
    assert load_preset("tum+cpu", profile=TYPICAL["tum"]).tracking.sdf_w_photo > 0


@pytest.mark.parametrize("kind", list(TYPICAL))
def test_chooser_takes_the_kind_preset_at_cpu_sizes_without_cuda(no_cuda, kind: str):
    profile = TYPICAL[kind]
    choice = preset_for(_ProfiledCapture(profile))
    expected = "cpu" if kind == "unknown" else f"{kind}+cpu"
    assert choice.preset == expected
    assert choice.config == load_preset(expected, profile=profile)
    assert (choice.config.sized_for, choice.config.device) == ("cpu", "cpu")
    if profile.max_depth_m is not None:
        assert choice.config.mapping.max_depth_m == profile.max_depth_m
    assert f"preset {expected}:" in choice.reason and "no CUDA device" in choice.reason
    assert size_warning(choice.config, choice.preset) is None


def test_chooser_keeps_gpu_sizes_with_cuda_unless_cpu_is_asked_for(cuda):
    cap = _ProfiledCapture(TYPICAL["sevenscenes"])
    gpu = preset_for(cap)
    assert gpu.preset == "sevenscenes" and gpu.config.sized_for == "gpu"
    assert gpu.config.loss.w_color == UNREGISTERED_COLOR_WEIGHT and "CUDA device is present" in gpu.reason
    assert size_warning(gpu.config, gpu.preset) is None  # device auto finds the GPU
    cpu = preset_for(cap, "cpu", ["seed=3"])
    assert (cpu.preset, cpu.config.sized_for, cpu.config.seed) == ("sevenscenes+cpu", "cpu", 3)
    assert "CPU requested" in cpu.reason


def test_real_captures_get_their_kind(shared_data: Path, no_cuda):
    expected = {"tum_fr1_desk_9frames": "tum", "tum_fr3_structure_notexture_far_120": "tum",
                "sevenscenes_redkitchen": "sevenscenes", "stray_iphone_lidar": "iphone"}
    for folder, kind in expected.items():
        if not (shared_data / folder).is_dir():
            continue
        choice = preset_for(open_capture(shared_data / folder, limit=2))
        assert choice.preset == f"{kind}+cpu", folder
    stray = preset_for(open_capture(shared_data / "stray_iphone_lidar", limit=2)).config
    assert (stray.mapping.min_confidence, stray.mapping.map_every, stray.loss.w_color) == (1, 2, 0.0)  # depth only


@pytest.mark.parametrize("lidar", [True, False])
def test_server_recording_profile_from_its_first_frame(tmp_path: Path, lidar: bool):
    from voxfusion.proto import encode_frame
    from voxfusion.proto.recording import RECORDING_FILENAME, RecordingCapture, RecordingWriter

    frame = SyntheticCapture(SyntheticConfig(n_frames=1, width=32, height=24, lidar=lidar))[0]
    with RecordingWriter(tmp_path / RECORDING_FILENAME) as w:
        w.append(encode_frame(frame, seq=0, depth_encoding="raw_f32_m"))
    p = RecordingCapture(tmp_path).profile
    assert (p.kind, p.has_confidence, p.has_color) == ("iphone" if lidar else "unknown", lidar, True)
    assert p.max_depth_m == (5.0 if lidar else None)


def test_gpu_sizes_on_cpu_warn_with_speed_and_the_cpu_variant(no_cuda):
    text = size_warning(load_preset("tum"), "tum")
    lo, hi = GPU_SIZES_ON_CPU_FPS
    assert text is not None and "--config tum+cpu" in text and f"about {lo:g}-{hi:g} frames/s" in text
    paper = size_warning(load_preset("replica+paper"), "replica+paper")
    assert "--config replica+cpu" in paper and "about {:g}-{:g} frames/s".format(*PAPER_SIZES_ON_CPU_FPS) in paper
    assert "--config cpu " in size_warning(load_preset("paper"), "paper")
    assert "--config cpu " in size_warning(load_preset(None))
    assert size_warning(load_preset("tum+cpu"), "tum+cpu") is None
    assert size_warning(load_preset("tum", ["device=cuda"]), "tum") is None  # not a CPU run


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory) -> Path:
    """3 frames of the synthetic room at 32x24 in the TUM layout, without its GT mesh (no mesh metrics)."""
    out = write_capture(SyntheticCapture(SyntheticConfig(n_frames=3, width=32, height=24)),
                        tmp_path_factory.mktemp("cap") / "room")
    (out / "gt_mesh.ply").unlink()
    return out


TINY_SETS = ["mapping.first_frame_iters=3", "mapping.iters=1", "mapping.rays_per_frame=64", "tracking.iters=2",
             "tracking.rays=64", "mesh_res=2", "field.sdf_hidden=16", "field.color_hidden=16"]


def _run(args: list[str]) -> str:
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return result.output


def test_run_without_config_chooses_the_preset(tiny_capture: Path, tmp_path: Path, no_cuda):
    out = _run(["run", str(tiny_capture), "--out", str(tmp_path / "run"),
                *[a for s in TINY_SETS for a in ("--set", s)]])
    assert "preset synthetic+cpu: room is voxfusion synthetic room 32x24 (kind synthetic" in out
    assert "sized for a GPU" not in out
    assert (tmp_path / "run" / "trajectory.txt").is_file()
    metrics = (tmp_path / "run" / "metrics.json").read_text()
    assert '"sized_for": "cpu"' in metrics
    # the timings say what they time: the frames loop, and the whole command (which also builds the engine, meshes,
    # evaluates and writes), so neither is mistaken for the other; metrics.json keeps its keys
    rows = {line.rsplit("  ", 1)[0].strip(): line.rsplit(None, 1)[-1] for line in out.splitlines() if "[s]" in line}
    loop = float(rows["frames loop [s] (reading frames and the engine's work on them)"])
    whole = float(rows["the whole command until this table [s] (imports, mesh, evaluation, outputs too)"])
    assert 0 < loop < whole
    assert '"wall_s"' in metrics


def test_process_age_is_the_time_since_the_process_started():
    """The run table's whole-command time counts from the process's start (``/proc``); in a new process it is
    between 0 and the time the parent saw the child run (a wrong field of ``/proc/self/stat`` is off by hours)."""
    import subprocess
    import sys
    import time

    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", "from voxfusion.commands.run import process_age_s; "
                          "print(process_age_s())"], capture_output=True, text=True, check=True).stdout
    elapsed = time.monotonic() - t0
    age = float(out)
    assert 0.0 <= age <= elapsed + 0.05, (age, elapsed)


def test_run_with_a_gpu_preset_on_cpu_warns_once(tiny_capture: Path, tmp_path: Path):
    out = _run(["run", str(tiny_capture), "--config", "synthetic", "--device", "cpu", "--out", str(tmp_path / "run"),
                *[a for s in TINY_SETS for a in ("--set", s)]])
    assert out.count("sized for a GPU") == 1 and "--config synthetic+cpu" in out
    assert "preset synthetic" not in out  # nothing was chosen: the user named the preset


def test_shipped_kind_presets_change_only_what_their_kind_needs():
    base = config_to_dict(load_preset(None))
    for name in ("tum", "sevenscenes"):  # everything they need comes from the reader's profile
        assert config_to_dict(load_preset(name)) == base


def test_the_summary_says_why_a_depth_disagreement_is_missing():
    from voxfusion.commands.run import consistency_row

    row = consistency_row("estimate", {"gap_15_cm": 2.279, "gap_60_cm": float("nan"), "gap_240_cm": None})
    assert row["metric"] == "depth disagreement [cm] (estimate poses)"
    assert row["value"].startswith("2.28 / n/a / n/a  at frame gaps 15 / 60 / 240  (n/a: no frame pair")
    assert "n/a" not in consistency_row("estimate", {"gap_15_cm": 0.5})["value"]
