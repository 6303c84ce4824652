"""bench/gpu_suite.py: the smoke mode runs every section on the CPU; the capacity worker's protocol; the refusal
without CUDA; the back-and-forth feed."""

from __future__ import annotations

import dataclasses
import io
import json
import time
from pathlib import Path

import pytest
import torch

from bench import bench_accel, gpu_profile, gpu_suite
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig


def test_smoke_runs_every_section_and_writes_json(tmp_path: Path, monkeypatch):
    out = tmp_path / "gpu-smoke.json"
    written = []  # what each write left in the file: rewritten after every section, complete only at the end
    real_write = gpu_suite.write_json
    monkeypatch.setattr(gpu_suite, "write_json", lambda path, obj: written.append(
        json.loads(real_write(path, obj).read_text())) or Path(path))
    assert gpu_suite.main(["--smoke", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert [w["complete"] for w in written] == [False] * (len(written) - 1) + [True]
    assert [("iterations" in w, "accel" in w, "capacity" in w) for w in written[:4]] == [
        (True, False, False), (True, False, False), (True, True, False), (True, True, True)]
    assert result["smoke"] is True and result["machine"]["cpu_model"] and result["not_run"] == []
    assert result["errors"] == {}
    assert {v["target"] for v in result["targets"]} == {"tracking ms/iter", "realtime tracking Hz",
                                                         "realtime mapping rounds/s", "occlusion render ms"}
    stages = [r["stage"] for r in result["iterations"]]
    # on the CPU the default mapping path compacts its samples; the suite also times the fixed-shape one
    assert stages == [f"tracking ({m})" for m in gpu_suite.tracker_methods()] + ["mapping",
                                                                                  "mapping (fixed-shape samples)"]
    assert all(r["ms_per_iter"] > 0 and r["iters"] > 0 for r in result["iterations"])
    # the geometric tracker's figure is per field evaluation: each frame evaluates each level at least once
    sdf = next(r for r in result["iterations"] if r["stage"] == "tracking (sdf)")
    assert sdf["iters"] >= sdf["frames"] * 2
    rt = result["realtime"]["synthetic"]
    assert rt["frames_fed"] == round(gpu_suite.SMOKE.realtime_s * 30) and rt["preset"] == "synthetic+cpu"
    assert 0 <= rt["tracking_hz"] <= 31  # a busy CI machine may track none of the 9 frames in 0.3 s
    assert result["render_mesh"]["render_wh"] == list(gpu_suite.SMOKE.render_wh)
    rm = result["render_mesh"]
    assert rm["render_ms_median"] > 0 and rm["render_color_ms_median"] > 0 and rm["mesh_ms"] > 0
    # the occlusion graphs' path (its CPU stand-in here): the eager image, no fallback
    assert rm["render_graphs_recorder"] == "eager stand-in (no CUDA)" and rm["render_graphs_ms_median"] > 0
    assert rm["render_graphs_max_depth_diff_m"] < 1e-4 and rm["render_graphs_fallbacks"] == 0
    assert rm["render_graphs_captures"] == 1
    cap = result["capacity"]
    assert cap["isolation"] == "thread" and 1 <= len(cap["rows"]) <= 2 and cap["rows"][0]["sessions"] == 1
    assert set(result["memory"]) == {"iterations", "realtime/synthetic", "render_mesh", "accel", "capacity"}
    # the execution options, each measured against the float32 eager reference on the same map
    accel = result["accel"]["variants"]
    assert set(accel) == set(bench_accel.VARIANTS)
    assert all(r["mapping_ms_per_iter"] > 0 and r["tracking_ms_per_frame"] > 0 for r in accel.values())
    assert accel["float32 eager (reference)"]["sdf_dev_mm"] == 0.0
    assert accel["compile"]["sdf_dev_mm"] < 1e-3  # the same arithmetic, compiled
    assert accel["float32 eager (reference)"]["compile_fell_back"] is False
    assert isinstance(accel["compile"]["compile_fell_back"], bool)  # True would say the row is the eager decoder's
    assert 0.0 < accel["bfloat16"]["sdf_dev_mm"] < 2.0  # rounding, but within the 1 mm-scale of the field
    # the compiled tracker: the same solver, so the same pose up to rounding (0.33 mm from ground truth here)
    tracked = accel["tracking compile"]
    assert isinstance(tracked["compile_fell_back"], bool) and tracked["tracking_build_s"] > 0
    assert abs(tracked["tracking_error_mm"] - accel["float32 eager (reference)"]["tracking_error_mm"]) < 0.05
    # the compiled mapping iteration: the same map (a fixed-shape step, so rounding alone separates it)
    mapped = accel["mapping compile"]
    assert isinstance(mapped["compile_fell_back"], bool) and mapped["mapping_ms_per_iter"] > 0


def test_a_section_that_fails_is_recorded_and_the_suite_goes_on(tmp_path: Path, monkeypatch):
    def broken(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("CUDA error: an illegal memory access was encountered")

    monkeypatch.setattr(gpu_suite, "measure_iterations", broken)
    out = tmp_path / "gpu-smoke.json"
    assert gpu_suite.main(["--smoke", "--skip", "accel", "capacity", "render", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["errors"] == {"iterations": "RuntimeError: CUDA error: an illegal memory access was encountered"}
    assert "iterations" not in result and result["realtime"]["synthetic"]["frames_fed"] > 0 and result["complete"]


def test_missing_sevenscenes_folder_is_an_error_not_a_silent_skip(tmp_path: Path):
    with pytest.raises(SystemExit):
        gpu_suite.main(["--smoke", "--sevenscenes", str(tmp_path / "nowhere")])


def test_target_verdicts_judge_each_measurement_against_its_bound():
    results = {
        "iterations": [{"stage": "tracking (sdf)", "ms_per_iter": 1.5}, {"stage": "mapping", "ms_per_iter": 40.0}],
        "accel": {"preset": "paper", "variants": {"tracking compile": {"tracking_ms_per_eval": 2.5}}},
        "realtime": {"synthetic": {"tracking_hz": 29.0, "mapping_rounds_per_s": 6.0}},
        "render_mesh": {"render_wh": [256, 192], "render_ms_median": 12.0},
    }
    verdicts = [(v["target"], v["where"], v["met"]) for v in gpu_suite.target_verdicts(results)]
    assert verdicts == [("tracking ms/iter", "iterations: paper preset, default", True),
                        ("tracking ms/iter", "accel: tracking compile", False),
                        ("realtime tracking Hz", "realtime synthetic", False),
                        ("realtime mapping rounds/s", "realtime synthetic", True),
                        ("occlusion render ms", "render 256x192 (median)", False)]
    # a CPU run of bench_accel (another preset) says nothing about the paper-preset target
    results["accel"]["preset"] = "synthetic+cpu"
    assert [v["where"] for v in gpu_suite.target_verdicts(results)].count("accel: tracking compile") == 0


def test_budget_starts_no_section_once_spent_and_says_which(tmp_path: Path):
    out = tmp_path / "gpu-smoke.json"
    assert gpu_suite.main(["--smoke", "--budget-s", "0", "--skip", "sevenscenes", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["complete"] is True and result["sizes"]["budget_s"] == 0
    assert result["not_run"] == ["iterations", "realtime/synthetic", "render_mesh", "accel", "capacity"]
    assert not {"iterations", "render_mesh", "accel", "capacity"} & set(result) and result["realtime"] == {}


def test_realtime_options_run_the_synthetic_session_again_with_them(tmp_path: Path, monkeypatch):
    out = tmp_path / "gpu-smoke.json"
    monkeypatch.setattr(gpu_suite, "SMOKE", dataclasses.replace(gpu_suite.SMOKE, overfeed_hz=45.0,
                                                                realtime_options=(("tracking.sdf_points=128",),)))
    assert gpu_suite.main(["--smoke", "--skip", "iterations", "accel", "capacity", "render", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    realtime = result["realtime"]
    assert list(realtime) == ["synthetic", "synthetic, fed 45 Hz", "synthetic, tracking.sdf_points=128"]
    assert [r["feed_hz"] for r in realtime.values()] == [30.0, 45.0, 30.0]
    fed = [round(gpu_suite.SMOKE.realtime_s * hz) for hz in (30, 45, 30)]
    assert [r["frames_fed"] for r in realtime.values()] == fed
    assert [r["compile_warmup_s"] for r in realtime.values()] == [0.0, 0.0, 0.0]  # nothing compiles: no warm-up
    assert [r["graphs_compiled_during_feed"] for r in realtime.values()] == [0, 0, 0]
    # every session is held to the tracking target, the over-fed one included
    assert {v["where"] for v in result["targets"] if v["target"] == "realtime tracking Hz"} == {
        f"realtime {key}" for key in realtime}


def test_compiled_options_are_compiled_before_a_realtime_feed():
    """After the offline warm-up, a realtime session with the compiled tracker compiles nothing more while fed."""
    from voxfusion.core.slam import tracking_sdf

    torch._dynamo.reset()
    tracking_sdf.COMPILED_LINEARIZE.reset()
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=6, width=32, height=24)).frames())
    config = gpu_suite.load_preset("cpu", [*gpu_suite.TINY, "tracking.compile=true"], profile=None)
    before = gpu_suite._compiled_graphs()
    assert gpu_suite.warm_compiled(frames, config) > 0
    warmed = gpu_suite._compiled_graphs()
    assert warmed > before and not tracking_sdf.COMPILED_LINEARIZE.failed
    result, slam = gpu_suite.run_realtime(frames, gpu_suite.apply_overrides(config, ["mode=realtime"]), "cpu",
                                          "synthetic", 0.3, 30.0)
    slam.close()
    assert result.frames_fed == 9 and gpu_suite._compiled_graphs() == warmed
    plain = gpu_suite.load_preset("cpu", list(gpu_suite.TINY), profile=None)
    assert gpu_suite.warm_compiled(frames, plain) == 0.0


def test_lease_sizes_fit_a_short_slot():
    """--lease: the full suite's resolution and preset, bounded in time: a budget well inside a lent GPU's ~15
    minutes, shorter feeds, a capacity round budget, and the execution options that decide the CUDA defaults."""
    lease = gpu_suite.LEASE
    assert (lease.width, lease.height, lease.render_wh) == (gpu_suite.FULL.width, gpu_suite.FULL.height,
                                                            gpu_suite.FULL.render_wh)
    assert lease.budget_s == 360 and lease.capacity_budget_s < lease.budget_s
    assert lease.capacity_round_timeout_s < gpu_suite.FULL.capacity_round_timeout_s
    assert lease.realtime_s <= gpu_suite.FULL.realtime_s and lease.capacity_s <= gpu_suite.FULL.capacity_s
    assert set(lease.accel_variants) <= set(bench_accel.VARIANTS)
    assert {"float32 eager (reference)", "no CUDA graphs (eager tracker)"} <= set(lease.accel_variants)
    # the realtime rates without the tracker's CUDA graphs too (the same process, the same GPU)
    assert ("tracking.cuda_graphs=false",) in lease.realtime_options
    # the tracking rate read where frames come faster than the 30 Hz target, not capped by the feed
    assert lease.overfeed_hz >= 2 * lease.feed_hz and gpu_suite.FULL.overfeed_hz >= 2 * gpu_suite.FULL.feed_hz


def test_capacity_worker_waits_for_go_and_reports_one_session():
    spec = gpu_suite.SessionSpec("synthetic", 32, 24, 3, 0.1, 30.0, "cpu", tuple(gpu_suite.TINY))
    stdout = io.StringIO()
    assert gpu_suite._worker(json.dumps(dataclasses.asdict(spec)), io.StringIO("go\n"), stdout) == 0
    lines = stdout.getvalue().splitlines()
    assert lines[0] == "READY" and lines[1].startswith("RESULT ")
    result = gpu_suite.RealtimeResult(**json.loads(lines[1][len("RESULT "):]))
    assert result.frames_fed == 3 and result.feed_hz == 30.0 and result.preset == "synthetic+cpu"
    # the worker's own memory (the parent does no device work while its workers run); no GPU here
    assert result.peak_gpu_mb is None and result.peak_rss_mb > 100


def test_capacity_processes_report_or_say_why_not():
    """Real worker processes: one tiny session reports its result and memory; with no time to start up, the round
    says the workers were not ready instead of passing for a rate measurement."""
    spec = gpu_suite.SessionSpec("synthetic", 32, 24, 3, 0.1, 30.0, "cpu", tuple(gpu_suite.TINY))
    results, problem = gpu_suite._run_processes(spec, 1, timeout_s=120.0)
    assert problem is None and len(results) == 1 and results[0].frames_fed == 3 and results[0].peak_rss_mb > 100
    results, problem = gpu_suite._run_processes(spec, 2, timeout_s=120.0, ready_timeout_s=0.01)
    assert results == [] and problem == "2 of 2 session processes were not ready within 0.01 s"
    # a worker that fails at start (no such capture) ends the round at once, with its exit code
    broken = dataclasses.replace(spec, capture="/nonexistent/capture")
    t0 = time.monotonic()
    results, problem = gpu_suite._run_processes(broken, 1, timeout_s=120.0)
    assert results == [] and problem.startswith("1 of 1 session processes exited without a result")
    assert time.monotonic() - t0 < 60  # not the 900 s start-up deadline


def test_capacity_rows_carry_the_workers_memory_largest_and_summed():
    def session(gpu: float | None, rss: float | None) -> gpu_suite.RealtimeResult:
        return gpu_suite.RealtimeResult("synthetic", "p", 3, 0.1, 30.0, 30.0, 5.0, 3, 0, 0, 1.0, 0.1, 1, 10,
                                        peak_gpu_mb=gpu, peak_rss_mb=rss)

    assert gpu_suite._worker_memory([session(100.0, 900.0), session(150.0, 800.0)]) == {
        "worker_peak_gpu_mb_max": 150.0, "worker_peak_gpu_mb_sum": 250.0,
        "worker_peak_rss_mb_max": 900.0, "worker_peak_rss_mb_sum": 1700.0}
    assert gpu_suite._worker_memory([session(None, None)]) == {}  # thread isolation: nothing per session


def test_full_suite_refuses_without_cuda(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu_suite.main([]) == 2
    assert "needs a CUDA device" in capsys.readouterr().err


@pytest.mark.parametrize("unique", [1, 3])
def test_feed_plays_back_and_forth_with_new_stamps(unique: int):
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=unique, width=16, height=12)).frames())
    fed = gpu_suite.feed_order(frames, 7, 30.0)
    assert [f.index for f in fed] == list(range(7))
    assert [f.timestamp_s for f in fed] == [round(k / 30, 6) for k in range(7)]
    source = [next(j for j, g in enumerate(frames) if g.depth_m is f.depth_m) for f in fed]
    assert source == ([0] * 7 if unique == 1 else [0, 1, 2, 1, 0, 1, 2])


def test_bench_accel_times_each_mapping_path_on_one_map(tmp_path: Path, monkeypatch):
    # the eager paths only: the compiled one costs a compilation here and is held to the eager step in test_mapping
    paths = {k: v for k, v in bench_accel.MAPPING_PATHS.items() if "mapping.compile" not in v}
    monkeypatch.setattr(bench_accel, "MAPPING_PATHS", paths)
    out = tmp_path / "paths.json"
    assert bench_accel.main(["--mapping-paths", "--smoke", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["ms_per_iter"]) == set(paths) and len(paths) == 2
    assert all(v > 0 for v in result["ms_per_iter"].values()) and result["machine"]["cpu_model"]
    assert all(len(v) == result["rounds"] for v in result["ms_per_iter_all"].values())


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal without CUDA")
def test_gpu_profile_refuses_plainly_without_cuda(capsys):
    assert gpu_profile.main([]) == 2
    assert "needs a CUDA device" in capsys.readouterr().err
