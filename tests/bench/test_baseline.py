"""The TSDF baseline (bench/baseline_tsdf.py), the machine / memory helpers and the harness (bench/run.py).

The baseline runs on tiny synthetic captures (exact ground truth) so the whole file stays fast.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")

from bench.baseline_tsdf import (  # noqa: E402
    MissingDependencyError,
    TSDFBaselineConfig,
    run_tsdf_baseline,
    save_result,
    tsdf_render_back,
)
from bench.machine import PeakMemory, machine_info  # noqa: E402
from voxfusion.core.datasets.frame import BaseCapture, RGBDFrame  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.errors import ConfigError, ValidationError  # noqa: E402
from voxfusion.core.eval import MeshEvalConfig, TrajectoryEvalConfig, compute_ate, compute_mesh_metrics  # noqa: E402
from voxfusion.core.trajectory import read_tum_trajectory  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]

# Small voxel-block capacity: the hash map grows on demand, and 1,000 blocks keep each run's memory low.
FAST = TSDFBaselineConfig(voxel_size_m=0.02, depth_max_m=5.0, block_count=1000)


class _EditedCapture(BaseCapture):
    """A capture whose frames pass through ``edit(i, frame)``."""

    def __init__(self, capture: BaseCapture, edit) -> None:
        self.capture, self.edit = capture, edit
        self.name, self.path = capture.name, capture.path

    def __len__(self) -> int:
        return len(self.capture)

    def _load(self, i: int) -> RGBDFrame:
        return self.edit(i, self.capture[i])


@pytest.fixture(scope="module")
def synthetic() -> SyntheticCapture:
    return SyntheticCapture(SyntheticConfig(n_frames=10, width=160, height=120))


@pytest.fixture(scope="module")
def result(synthetic):
    return run_tsdf_baseline(synthetic, FAST, progress=False)


def _raw_ate_m(res, capture) -> float:
    return compute_ate(res.trajectory, capture.trajectory, TrajectoryEvalConfig(align="none")).rmse_m


def test_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="voxel_size_m"):
        TSDFBaselineConfig(voxel_size_m=0.0)
    with pytest.raises(ConfigError, match="depth_min_m"):
        TSDFBaselineConfig(depth_min_m=4.0, depth_max_m=3.0)
    with pytest.raises(ConfigError, match="device"):
        TSDFBaselineConfig(device="GPU")
    with pytest.raises(ConfigError, match="block_count"):
        TSDFBaselineConfig(block_count=0)


def test_trajectory_has_one_pose_per_frame_in_gt_frame(result, synthetic):
    traj = result.trajectory
    assert len(traj) == len(synthetic) == result.n_frames
    np.testing.assert_array_equal(traj.timestamps_s, synthetic.trajectory.timestamps_s)
    # The first pose is the capture's first reference pose, so the estimate lives in the GT frame.
    np.testing.assert_allclose(traj.T_world_cam[0], synthetic.trajectory.T_world_cam[0], atol=1e-12)
    assert result.n_tracking_failures == 0 and result.failed_frames == []


def test_trajectory_error_is_small(result, synthetic):
    aligned = compute_ate(result.trajectory, synthetic.trajectory, TrajectoryEvalConfig(align="se3"))
    assert aligned.rmse_m < 0.03
    assert _raw_ate_m(result, synthetic) < 0.04


def test_mesh_is_coloured_and_close_to_gt(result, synthetic):
    mesh = result.mesh
    assert len(mesh.faces) > 1000
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape == (len(mesh.vertices), 4) and colors.dtype == np.uint8
    assert colors[:, :3].std() > 5  # textured room, not a constant fill
    m = compute_mesh_metrics(mesh, synthetic.gt_mesh, MeshEvalConfig(n_samples=5000))
    assert m.accuracy_m < 0.02


def test_timings_and_memory_are_recorded(result):
    t = result.timings
    for a in (t.load_ms, t.track_ms, t.integrate_ms, t.raycast_ms):
        assert a.shape == (result.n_frames,) and np.all(a >= 0)
    assert t.track_ms[0] == 0 and np.all(t.track_ms[1:] > 0) and np.all(t.integrate_ms > 0)
    assert result.fps == pytest.approx(result.n_frames / (t.total_ms.sum() / 1e3))
    assert result.memory.peak_rss_mb >= result.memory.start_rss_mb > 0
    assert result.memory.n_samples >= result.n_frames


def test_open3d_offset_fixes_reduce_drift(result, synthetic):
    stock = TSDFBaselineConfig(voxel_size_m=0.02, depth_max_m=5.0, block_count=1000,
                               fix_raycast_half_voxel=False, fix_integrate_half_pixel=False)
    stock_result = run_tsdf_baseline(synthetic, stock, progress=False)
    assert _raw_ate_m(result, synthetic) < 0.6 * _raw_ate_m(stock_result, synthetic)


def test_depth_only_capture_and_max_frames(synthetic):
    depth_only = _EditedCapture(synthetic, lambda i, f: f.with_(color=None))
    res = run_tsdf_baseline(depth_only, FAST, max_frames=5, progress=False)
    assert len(res.trajectory) == 5
    colors = np.asarray(res.mesh.visual.vertex_colors)
    assert len(colors) > 0 and np.all(np.abs(colors[:, :3].astype(int) - 128) <= 1)  # the grey fill


def test_tracking_failure_keeps_previous_pose(synthetic):
    blind = _EditedCapture(synthetic, lambda i, f: f.with_(depth_m=np.zeros_like(f.depth_m)) if i == 3 else f)
    res = run_tsdf_baseline(blind, FAST, max_frames=6, progress=False)
    assert res.failed_frames == [3] and res.n_tracking_failures == 1
    T = res.trajectory.T_world_cam
    np.testing.assert_array_equal(T[3], T[2])
    assert res.timings.integrate_ms[3] == 0
    assert not np.allclose(T[4], T[3])  # tracking resumes on the next frame


def test_save_result_round_trip(result, tmp_path):
    paths = save_result(result, tmp_path / "out")
    traj = read_tum_trajectory(paths["trajectory"])
    np.testing.assert_allclose(traj.T_world_cam, result.trajectory.T_world_cam, atol=1e-6)
    np.testing.assert_allclose(traj.timestamps_s, result.trajectory.timestamps_s, atol=1e-9)
    import trimesh

    mesh = trimesh.load(paths["mesh"], process=False)
    assert len(mesh.faces) == len(result.mesh.faces)
    np.testing.assert_array_equal(np.asarray(mesh.visual.vertex_colors)[:, :3],
                                  np.asarray(result.mesh.visual.vertex_colors)[:, :3])
    timings = json.loads(paths["timings"].read_text())
    assert timings["n_frames"] == result.n_frames and len(timings["per_frame_ms"]["track"]) == result.n_frames
    assert timings["config"]["voxel_size_m"] == 0.02 and "memory" in timings


def test_missing_open3d_raises_install_hint(synthetic, monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'voxfusion\[baseline\]'") as info:
        run_tsdf_baseline(synthetic, FAST, progress=False)
    assert isinstance(info.value, ImportError)


def test_tsdf_render_back_reproduces_the_frame(synthetic):
    """The baseline's side of bench/bench_outliers.py: one integration, ray cast at the same pose."""
    frame = synthetic[0]
    depth = tsdf_render_back(frame, frame.T_world_cam, TSDFBaselineConfig(voxel_size_m=0.02, depth_max_m=5.0))
    assert depth.shape == frame.depth_m.shape and depth.dtype == np.float32
    both = (depth > 0) & (frame.depth_m > 0)
    assert both.mean() > 0.9
    assert np.median(np.abs(depth[both] - frame.depth_m[both])) < 0.01


def test_peak_memory_sees_an_allocation():
    with PeakMemory(interval_s=0) as mem:
        block = np.ones(100 * 2**20 // 8)  # 100 MiB, every page touched
        mem.sample()
        del block
    assert mem.result.increase_mb >= 90
    assert mem.result.peak_rss_mb >= mem.result.start_rss_mb + 90


def test_machine_info_is_json_ready_and_hostname_free():
    info = machine_info()
    for key in ("cpu_model", "cpu_logical_cores", "ram_total_gb", "python", "torch", "open3d", "cuda_device"):
        assert key in info
    assert info["open3d"] is not None and info["cpu_logical_cores"] >= 1
    text = json.dumps(info)
    assert "hostname" not in text
    host = socket.gethostname()
    if len(host) >= 6:
        assert host not in text


def test_run_py_end_to_end(tmp_path):
    cmd = [sys.executable, "bench/run.py", "--synthetic", "--frames", "8", "--width", "160", "--height", "120",
           "--out", str(tmp_path), "--mesh-samples", "20000", "--no-progress"]
    proc = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "ATE cm" in proc.stdout and "baseline" in proc.stdout
    doc = json.loads((tmp_path / "synthetic_160x120_8f_seed0.json").read_text())
    assert doc["machine"]["cpu_model"] and "bench/run.py --synthetic" in doc["command"]
    base = doc["methods"]["baseline"]
    assert base["n_frames"] == 8 and base["config"]["preset"] == "synthetic"
    assert base["ate_aligned"]["rmse_m"] < 0.03 and base["ate_unaligned"]["aligned"] is False
    assert base["mesh"]["accuracy_m"] < 0.02 and 0.5 < base["mesh"]["completion_ratio"] <= 1.0
    assert base["memory"]["increase_mb"] >= 0 and base["fps"] > 0


def test_run_py_refuses_unknown_method(capsys):
    from bench.run import main

    with pytest.raises(SystemExit) as info:
        main(["--synthetic", "--method", "baseline", "nope"])
    assert info.value.code == 2
    assert "nope" in capsys.readouterr().err


def test_run_py_runs_voxfusion_beside_the_baseline(tmp_path):
    from bench.run import main

    main(["--synthetic", "--frames", "3", "--width", "48", "--height", "36", "--method", "voxfusion",
          "voxfusion-map", "--vf-config", "cpu-small", "--vf-set", "mapping.first_frame_iters=5", "mapping.iters=2",
          "tracking.iters=3", "mesh_res=2", "--mesh-samples", "2000", "--out", str(tmp_path), "--no-progress"])
    result = json.loads(next(tmp_path.glob("*.json")).read_text())
    assert set(result["methods"]) == {"voxfusion", "voxfusion-map"}
    assert result["methods"]["voxfusion"]["ate_aligned"]["rmse_m"] < 0.05


def test_run_py_picks_the_preset_voxfusion_run_picks():
    """The harness's frame recorder passes the reader's profile on, so voxfusion gets the preset and capture
    facts `voxfusion run` would (it once saw an unknown capture and ran every real one with `cpu`)."""
    import argparse

    from bench.run import _RecordingCapture, _voxfusion_config
    from voxfusion.core.slam.presets import preset_for

    capture = SyntheticCapture(SyntheticConfig(n_frames=2, width=48, height=36))
    recorder = _RecordingCapture(capture)
    assert recorder.profile == capture.profile and capture.profile.kind == "synthetic"
    name, config = _voxfusion_config(argparse.Namespace(vf_set=None, vf_config=None), recorder)
    expected = preset_for(capture)
    assert name == expected.preset and name.startswith("synthetic")
    assert config == expected.config


def test_real_tum_capture(shared_data):
    from voxfusion.core.datasets import open_capture

    capture = open_capture(shared_data / "tum_fr1_desk_9frames")
    res = run_tsdf_baseline(capture, TSDFBaselineConfig(block_count=2000), progress=False)
    ref = np.stack([f.T_world_cam for f in capture.frames()])
    ate = compute_ate(res.trajectory.T_world_cam, ref, TrajectoryEvalConfig(align="se3"))
    assert len(res.trajectory) == len(capture) and res.n_tracking_failures == 0
    assert ate.rmse_m < 0.03 and len(res.mesh.faces) > 1000


def test_run_py_depth_gap_blanks_frames_and_names_the_result():
    from bench.run import _open, build_parser

    args = build_parser().parse_args(["--synthetic", "--frames", "6", "--width", "32", "--height", "24",
                                      "--depth-gap", "2+3"])
    capture, _, name, desc = _open(args)
    assert name.endswith("_gap2+3") and desc["depth_gap"] == {"start": 2, "frames": 3}
    assert [bool((capture[i].depth_m > 0).any()) for i in range(6)] == [True, True, False, False, False, True]
    for bad in ("2", "2+0", "-1+3", "a+b"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["--synthetic", "--depth-gap", bad])


def test_run_py_revisit_comes_back_and_names_the_result():
    from bench.run import _open, build_parser

    args = build_parser().parse_args(["--synthetic", "--frames", "6", "--width", "32", "--height", "24",
                                      "--revisit", "5+1+2"])
    capture, _, name, desc = _open(args)
    assert name.endswith("_revisit5+1+2") and desc["revisit"] == {"at": 5, "back_to": 1, "frames": 2, "pause_s": 1.0}
    assert [capture[i].meta["source_index"] for i in range(len(capture))] == [0, 1, 2, 3, 4, 1, 2]
    np.testing.assert_array_equal(capture[5].T_world_cam, capture[1].T_world_cam)  # the reference pose comes along
    assert capture[5].timestamp_s > capture[4].timestamp_s + 0.99
    for bad in ("5+1", "0+1+2", "5+-1+2", "5+1+0", "a+b+c"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["--synthetic", "--revisit", bad])


def test_run_py_stride_keeps_every_nth_frame_with_its_reference_pose(shared_data):
    from bench.run import _open, build_parser
    from voxfusion.core.datasets import open_capture

    path = shared_data / "tum_fr1_desk_9frames"
    args = build_parser().parse_args(["--capture", str(path), "--stride", "3"])
    capture, _, name, desc = _open(args)
    full = open_capture(path)
    assert name.endswith("_stride3") and desc["stride"] == 3 and len(capture) == 3
    for i in range(3):
        assert capture[i].timestamp_s == full[3 * i].timestamp_s
        np.testing.assert_array_equal(capture[i].T_world_cam, full[3 * i].T_world_cam)
    for bad in (["--capture", str(path), "--stride", "0"], ["--synthetic", "--stride", "2"]):
        with pytest.raises(SystemExit):
            _check_parsed(bad)


def _check_parsed(argv: list[str]) -> None:
    from bench.run import _check_args, build_parser

    parser = build_parser()
    _check_args(parser, parser.parse_args(argv))


def test_run_py_with_a_depth_gap_runs_and_evaluates(tmp_path):
    from bench.run import main

    main(["--synthetic", "--frames", "6", "--width", "48", "--height", "36", "--depth-gap", "2+2", "--method",
          "voxfusion", "--vf-config", "cpu-small", "--vf-set", "mapping.first_frame_iters=5", "mapping.iters=2",
          "mesh_res=2", "--mesh-samples", "2000", "--out", str(tmp_path), "--no-progress"])
    result = json.loads(next(tmp_path.glob("*_gap2+2.json")).read_text())
    assert result["capture"]["depth_gap"] == {"start": 2, "frames": 2}
    ours = result["methods"]["voxfusion"]
    assert ours["n_frames"] == 6 and ours["extra"]["frames_lost"] == 2 and ours["ate_aligned"]["rmse_m"] < 0.05


def test_the_baseline_a_frame_at_a_time_is_the_whole_run(synthetic, result):
    """TSDFBaselineRun.step is what run_tsdf_baseline loops over: the same poses (Open3D's parallel ICP sums differ
    between runs by ~2.5 mm here, whichever way it is called), and a time per frame."""
    from bench.baseline_tsdf import TSDFBaselineRun

    run = TSDFBaselineRun(FAST)
    with run.quiet():
        ms = [run.step(frame) for frame in synthetic.frames(0, len(synthetic))]
        with pytest.raises(ValidationError, match="extract_mesh"):
            run.result(None)
        run.extract_mesh()
    assert ms[0] > 0 and all(m > 0 for m in ms)
    np.testing.assert_allclose(run.trajectory.T_world_cam, result.trajectory.T_world_cam, rtol=0, atol=0.01)


def test_fps_pair_interleaves_both_methods_and_reports_their_ratio(tmp_path):
    from bench.fps_pair import block_ratios, interleave, main

    seen = []
    ms_a, ms_b = interleave([0, 1, 2, 3], lambda f: seen.append(("a", f)), lambda f: seen.append(("b", f)))
    assert seen == [("a", 0), ("b", 0), ("b", 1), ("a", 1), ("a", 2), ("b", 2), ("b", 3), ("a", 3)]
    assert ms_a.shape == ms_b.shape == (4,)
    np.testing.assert_allclose(block_ratios(np.array([1.0, 1, 2, 2, 9]), np.array([2.0, 2, 2, 2, 1]), 2), [2.0, 1.0])
    np.testing.assert_allclose(block_ratios(np.array([1.0, 3]), np.array([2.0, 2]), 10), [1.0])
    assert main(["--synthetic", "--frames", "4", "--width", "64", "--height", "48", "--vf-set",
                 "mapping.first_frame_iters=5", "mapping.iters=2", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "fps_pair_synthetic_64x48_4f_seed0.json").read_text())
    assert doc["voxfusion"]["fps"] > 0 and doc["baseline"]["fps"] > 0 and doc["machine"]["cpu_model"]
    assert doc["fps_ratio"] == pytest.approx(doc["voxfusion"]["fps"] / doc["baseline"]["fps"])
    assert doc["ate_cm"]["voxfusion"] < 5 and doc["ate_cm"]["baseline"] < 5
