"""Benchmark harness: run methods over one capture, evaluate them the same way, print one table and write
``bench/results/<name>.json``.

Usage (from the repository root)::

    python bench/run.py --synthetic --frames 100 --width 320 --height 240 --method baseline
    python bench/run.py --capture ../shared/data/sevenscenes_redkitchen --max-frames 300
    python bench/run.py --capture ../shared/data/tum_fr1_desk_9frames --method baseline

Every method reads the same frames through the same reader. Evaluation (``voxfusion.core.eval``):

* ATE RMSE against the capture's reference poses, Umeyama/Horn SE(3)-aligned ("ATE cm") and unaligned
  ("ATE raw cm": the estimate starts at the first reference pose, so this is the drift), plus RPE
  (1 frame); n/a without reference poses.
* Mesh accuracy / completion / completion ratio (< 5 cm) / F-score (5 cm), exact point-to-surface
  distances from ``--mesh-samples`` samples per mesh, when the capture has a ground-truth mesh (the
  synthetic room, Replica, ScanNet); the GT samples are culled to what every ``--cull-stride``-th
  reference camera saw (frustum + depth test), so completion only asks for observed surfaces (each mesh
  result says which GT it was measured against: ``gt_part`` ``"observed"`` or ``"full"``).
* Phantom-surface share (``voxfusion.core.eval.phantom``, no GT needed): the share of each method's mesh
  area farther than 5 cm from the capture's depth placed with that method's own estimated poses (<= 200
  frames), so a method is not rewarded for surfaces no depth supports.
* fps = frames / processing time (frame loading excluded); peak MB = the peak increase of this process's
  RSS during the method's run (absolute peak in the JSON), see ``bench/machine.py``.

Methods are entries of :data:`METHODS` (name -> :class:`MethodSpec`); each runner takes the capture and
the parsed arguments and returns a :class:`MethodResult`, so a new method plugs in with one entry.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from bench.machine import MemoryUsage, machine_info  # noqa: E402
from voxfusion.core.datasets.frame import BaseCapture, Capture, RGBDFrame  # noqa: E402
from voxfusion.core.errors import VoxFusionError  # noqa: E402
from voxfusion.core.eval import (  # noqa: E402
    MeshEvalConfig,
    TrajectoryEvalConfig,
    compute_ate,
    compute_mesh_metrics,
    compute_rpe,
    format_table,
    load_mesh,
    phantom_for_capture,
    views_from_frames,
    write_json,
)
from voxfusion.core.mesh.mesh_frame import camera_up_forward  # noqa: E402
from voxfusion.core.run import write_mesh_views  # noqa: E402
from voxfusion.core.trajectory import Trajectory, write_tum_trajectory  # noqa: E402

__all__ = [
    "METHODS", "PLANNED_METHODS", "MethodResult", "MethodSpec", "build_parser", "evaluate", "main", "run_benchmark",
]

DEFAULT_OUT = REPO_ROOT / "bench" / "results"
REVISIT_PAUSE_S = 1.0
"""``--revisit``: seconds without frames before the camera is back (a gap, so the retry looks again)."""


@dataclass(frozen=True, eq=False)
class MethodResult:
    """What every method returns to the harness.

    Attributes:
        trajectory: estimated camera-to-world poses with the frames' timestamps.
        mesh: reconstructed mesh (world frame, metres), or ``None`` if the method made none.
        frame_ms: ``[N]`` processing time per frame, milliseconds (frame loading excluded).
        fps: frames per second of processing time.
        memory: peak memory of the run.
        config: the method's options (JSON-ready).
        extra: method-specific figures (JSON-ready), e.g. tracking failures.
    """

    trajectory: Trajectory
    mesh: trimesh.Trimesh | None
    frame_ms: np.ndarray
    fps: float
    memory: MemoryUsage
    config: dict
    extra: dict = field(default_factory=dict)


MethodRunner = Callable[[Capture, argparse.Namespace], MethodResult]


@dataclass(frozen=True)
class MethodSpec:
    """A benchmarked method: description, runner, and a check that says why it cannot run (or ``None``)."""

    description: str
    runner: MethodRunner
    unavailable: Callable[[], str | None]


# --------------------------------------------------------------------------------------------- methods


def _baseline_unavailable() -> str | None:
    from bench.baseline_tsdf import MissingDependencyError, require_open3d

    try:
        require_open3d()
    except MissingDependencyError as e:
        return str(e)
    return None


def _baseline_config(capture: Capture, args: argparse.Namespace):  # noqa: ANN202
    from dataclasses import replace

    from bench.baseline_tsdf import BASELINE_PRESETS

    preset = args.baseline_preset
    if preset == "auto":
        if args.synthetic:
            preset = "lidar" if args.lidar else "synthetic"
        else:
            preset = "lidar" if capture[0].width <= 256 else "kinect"
    config = BASELINE_PRESETS[preset][1]
    if args.voxel_size_m is not None:
        config = replace(config, voxel_size_m=args.voxel_size_m)
    return preset, config


def run_baseline(capture: Capture, args: argparse.Namespace) -> MethodResult:
    """The classic TSDF baseline (``bench/baseline_tsdf.py``)."""
    from bench.baseline_tsdf import run_tsdf_baseline

    preset, config = _baseline_config(capture, args)
    r = run_tsdf_baseline(capture, config, progress=args.progress)
    return MethodResult(
        trajectory=r.trajectory,
        mesh=r.mesh if len(r.mesh.faces) else None,
        frame_ms=r.timings.total_ms,
        fps=r.fps,
        memory=r.memory,
        config={"preset": preset, **asdict(config)},
        extra={
            "n_tracking_failures": r.n_tracking_failures,
            "failed_frames": r.failed_frames,
            "mesh_extraction_ms": r.mesh_extraction_ms,
            "track_ms_mean": float(np.mean(r.timings.track_ms[1:])) if r.n_frames > 1 else 0.0,
            "integrate_ms_mean": float(np.mean(r.timings.integrate_ms)),
            "raycast_ms_mean": float(np.mean(r.timings.raycast_ms)),
            "load_ms_mean": float(np.mean(r.timings.load_ms)),
            **r.meta,
        },
    )


def _voxfusion_config(args: argparse.Namespace, capture: Capture):  # noqa: ANN202
    """The preset ``voxfusion run`` would pick for ``capture`` on this machine (``--vf-config`` overrides the
    name), with the capture's facts (depth range, confidence, colour registration) under it."""
    from voxfusion.core.slam.presets import load_preset, preset_for

    overrides = list(args.vf_set or [])
    if args.vf_config:
        return args.vf_config, load_preset(args.vf_config, overrides, profile=getattr(capture, "profile", None))
    choice = preset_for(capture, overrides=overrides)
    return choice.preset, choice.config


def _voxfusion_result(capture: Capture, args: argparse.Namespace, known_poses: bool) -> MethodResult:
    from bench.machine import PeakMemory
    from voxfusion.core.config import config_to_dict
    from voxfusion.core.reconstruct import map_capture
    from voxfusion.core.run import run_capture, timing_summary

    preset, config = _voxfusion_config(args, capture)
    with PeakMemory() as mem:
        if known_poses:
            r = map_capture(capture, config, progress=args.progress)
            traj, mesh, fps = r.trajectory, r.mesh, r.fps
            frame_ms = np.array([s.time_ms for s in r.steps])
            extra = {**r.timing_summary(), "voxels": r.mapper.voxels.n_voxels}
            mapper, used = r.mapper, r.config
        else:
            r = run_capture(capture, config, progress=args.progress, evaluate=False)
            traj, mesh = r.trajectory, r.mesh
            frame_ms = np.array([(rec.tracking.time_ms if rec.tracking else 0.0)
                                 + (rec.mapping.time_ms if rec.mapping else 0.0) for rec in r.slam.records])
            # the counters, then the timings: SlamStats.fps counts from the first frame to now (loading and the
            # mesh included), timing_summary's the engine's processing time, as the baseline's
            extra = {**asdict(r.stats), **timing_summary(r)}
            fps = extra["fps"] or float("nan")  # processing time: frame loading excluded, as for the baseline
            mapper, used = r.slam.mapper, r.slam.config
    mrep = mapper.voxels.memory_report(mapper.decoder)
    extra.update(embedding_mb=mrep.embedding_bytes / 1e6, decoder_mb=mrep.decoder_bytes / 1e6)
    return MethodResult(trajectory=traj, mesh=mesh if len(mesh.faces) else None, frame_ms=frame_ms,
                        fps=fps, memory=mem.result,
                        config={"preset": preset, **config_to_dict(used)}, extra=extra)


def run_voxfusion(capture: Capture, args: argparse.Namespace) -> MethodResult:
    """Vox-Fusion SLAM (tracking + mapping), ``voxfusion run``."""
    return _voxfusion_result(capture, args, known_poses=False)


def run_voxfusion_map(capture: Capture, args: argparse.Namespace) -> MethodResult:
    """Vox-Fusion mapping with the capture's reference poses, ``voxfusion map``."""
    return _voxfusion_result(capture, args, known_poses=True)


METHODS: dict[str, MethodSpec] = {
    "baseline": MethodSpec("classic TSDF (Open3D frame-to-model ICP + VoxelBlockGrid)", run_baseline,
                           _baseline_unavailable),
    "voxfusion": MethodSpec("Vox-Fusion SLAM (tracking + mapping)", run_voxfusion, lambda: None),
    "voxfusion-map": MethodSpec("Vox-Fusion mapping with reference poses (no tracking)", run_voxfusion_map,
                                lambda: None),
}
"""Method name -> spec. Add an entry to benchmark a new method."""

PLANNED_METHODS: dict[str, str] = {}
"""Methods the command line already accepts but that have no runner yet -> why they cannot run."""


# --------------------------------------------------------------------------------------------- capture


class _RecordingCapture(BaseCapture):
    """Pass frames through and remember each one's timestamp and reference pose (for the ATE)."""

    def __init__(self, capture: Capture) -> None:
        self.capture = capture
        self.name = capture.name
        self.path = Path(capture.path)
        self._profile = capture.profile  # what the reader knows (kind, depth range, colour registration)
        self.reference: dict[int, tuple[float, np.ndarray | None]] = {}

    def __len__(self) -> int:
        return len(self.capture)

    def _load(self, i: int) -> RGBDFrame:
        frame = self.capture[i]
        self.reference[i] = (frame.timestamp_s, frame.T_world_cam)
        return frame

    @property
    def gt_mesh_path(self) -> Path | None:
        return self.capture.gt_mesh_path

    def reference_trajectory(self) -> Trajectory | None:
        """Reference poses of every frame that has one (loading frames no method asked for)."""
        for i in range(len(self)):
            if i not in self.reference:
                self._load(i)
        rows = [(t, T) for t, T in (self.reference[i] for i in range(len(self))) if T is not None]
        if not rows:
            return None
        return Trajectory(np.array([t for t, _ in rows]), np.stack([T for _, T in rows]))


def _open(args: argparse.Namespace) -> tuple[Capture, trimesh.Trimesh | None, str, dict]:
    """Build the capture; returns (capture, GT mesh or None, default name, description for the JSON)."""
    if args.synthetic:
        from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

        n = args.frames if args.max_frames is None else min(args.frames, args.max_frames)
        config = SyntheticConfig(n_frames=n, width=args.width, height=args.height, seed=args.seed,
                                 lidar=args.lidar, yaw_rate_deg_s=args.yaw_rate_deg_s)
        capture = SyntheticCapture(config)
        w, h = config.image_size
        name = (f"synthetic_{w}x{h}_{n}f_seed{args.seed}" + ("_lidar" if args.lidar else "")
                + (f"_yaw{args.yaw_rate_deg_s:g}" if args.yaw_rate_deg_s else ""))
        desc = {"kind": "synthetic", "config": asdict(config)}
        gt = capture.gt_mesh
    else:
        from voxfusion.core.datasets import detect_format, open_capture

        fmt = detect_format(args.capture)
        capture = open_capture(args.capture, limit=args.max_frames, stride=args.stride)
        gt = load_mesh(capture.gt_mesh_path) if capture.gt_mesh_path is not None else None
        name = (capture.name + (f"_{len(capture)}f" if args.max_frames is not None else "")
                + (f"_stride{args.stride}" if args.stride > 1 else ""))
        desc = {"kind": fmt, "path": str(Path(args.capture)), "gt_mesh_path": capture.gt_mesh_path,
                "stride": args.stride}
    if args.depth_gap is not None:
        from functools import partial

        from voxfusion.core.datasets.transforms import TransformedCapture, drop_depth

        start, length = args.depth_gap
        capture = TransformedCapture(capture, partial(drop_depth, start=start, stop=start + length))
        name += f"_gap{start}+{length}"
        desc["depth_gap"] = {"start": start, "frames": length}
    if args.revisit is not None:
        from voxfusion.core.datasets.transforms import RevisitCapture

        at, back_to, length = args.revisit
        capture = RevisitCapture(capture, at, back_to, length, pause_s=REVISIT_PAUSE_S)
        name += f"_revisit{at}+{back_to}+{length}"
        desc["revisit"] = {"at": at, "back_to": back_to, "frames": length, "pause_s": REVISIT_PAUSE_S}
    return capture, gt, name, desc


# ------------------------------------------------------------------------------------------ evaluation


def _plus_ints(text: str, minimums: dict[str, int], example: str) -> tuple[int, ...]:
    """``A+B+...`` -> the integers, one per name of ``minimums`` (name -> least value), or an argparse error."""
    try:
        values = tuple(int(v) for v in text.split("+"))
    except ValueError:
        values = ()
    if len(values) != len(minimums):
        raise argparse.ArgumentTypeError(f"expected {'+'.join(minimums)}, e.g. {example}, got {text!r}")
    if any(v < least for v, least in zip(values, minimums.values(), strict=True)):
        need = ", ".join(f"{name} >= {least}" for name, least in minimums.items())
        raise argparse.ArgumentTypeError(f"need {need}, got {text!r}")
    return values


def _revisit(text: str) -> tuple[int, ...]:
    """``AT+BACK+FRAMES`` -> ``(AT, BACK, FRAMES)`` (``--revisit``)."""
    return _plus_ints(text, {"AT": 1, "BACK": 0, "FRAMES": 1}, "60+15+15")


def _gap(text: str) -> tuple[int, ...]:
    """``START+FRAMES`` -> ``(START, FRAMES)`` (``--depth-gap``)."""
    return _plus_ints(text, {"START": 0, "FRAMES": 1}, "40+15")


def _cm(x: float | None) -> float | None:
    return None if x is None else 100.0 * x


def evaluate(result: MethodResult, reference: Trajectory | None, gt_mesh: trimesh.Trimesh | None,
             views: list | None, mesh_samples: int, capture: Capture | None = None) -> dict:
    """Trajectory and mesh metrics of one method (``None`` where they do not apply, with the reason); with
    ``capture``, also the phantom-surface share of its mesh (its depth placed with the method's poses)."""
    out: dict = {"ate_aligned": None, "ate_unaligned": None, "rpe": None, "mesh": None, "phantom": None,
                 "notes": []}
    if reference is None:
        out["notes"].append("no reference poses: trajectory metrics n/a")
    else:
        try:
            out["ate_aligned"] = compute_ate(result.trajectory, reference, TrajectoryEvalConfig(align="se3"))
            out["ate_unaligned"] = compute_ate(result.trajectory, reference, TrajectoryEvalConfig(align="none"))
            out["rpe"] = compute_rpe(result.trajectory, reference, TrajectoryEvalConfig(rpe_delta=1))
        except VoxFusionError as e:
            out["notes"].append(f"trajectory metrics n/a: {e}")
    if gt_mesh is None:
        out["notes"].append("no ground-truth mesh: mesh metrics n/a")
    elif result.mesh is None:
        out["notes"].append("method produced no mesh: mesh metrics n/a")
    else:
        config = MeshEvalConfig(n_samples=mesh_samples, method="exact")
        out["mesh"] = compute_mesh_metrics(result.mesh, gt_mesh, config, views=views)
    if capture is not None and result.mesh is not None:
        try:
            out["phantom"] = phantom_for_capture(result.mesh, capture, result.trajectory, n_samples=mesh_samples,
                                                 max_diff_s=1e-3)
        except VoxFusionError as e:
            out["notes"].append(f"phantom share n/a: {e}")
    return out


def _row(name: str, result: MethodResult, ev: dict) -> dict:
    na = "n/a"
    ate, raw, mesh, phantom = ev["ate_aligned"], ev["ate_unaligned"], ev["mesh"], ev["phantom"]
    return {
        "method": name,
        "frames": len(result.trajectory),
        "ATE cm": _cm(ate.rmse_m) if ate else na,
        "ATE raw cm": _cm(raw.rmse_m) if raw else na,
        "acc cm": _cm(mesh.accuracy_m) if mesh else na,
        "comp cm": _cm(mesh.completion_m) if mesh else na,
        "ratio %": 100.0 * mesh.completion_ratio if mesh else na,
        "F-score %": 100.0 * mesh.fscore if mesh else na,
        "phantom %": 100.0 * phantom.share if phantom else na,
        "fps": result.fps,
        "peak MB": result.memory.increase_mb,
    }


def _frame_ms_stats(frame_ms: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(frame_ms)), "median": float(np.median(frame_ms)),
            "p95": float(np.percentile(frame_ms, 95)), "max": float(np.max(frame_ms))}


# ---------------------------------------------------------------------------------------------- driver


def build_parser() -> argparse.ArgumentParser:
    from bench.baseline_tsdf import BASELINE_PRESETS

    p = argparse.ArgumentParser(prog="python bench/run.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--capture", type=Path, help="capture folder or .r3d file (any format open_capture knows)")
    src.add_argument("--synthetic", action="store_true", help="render the synthetic room (exact GT mesh)")
    p.add_argument("--frames", type=int, default=100, help="synthetic: number of frames (default 100)")
    p.add_argument("--width", type=int, default=None, help="synthetic: image width (default 320, LiDAR 256)")
    p.add_argument("--height", type=int, default=None, help="synthetic: image height (default 240, LiDAR 192)")
    p.add_argument("--seed", type=int, default=0, help="synthetic: scene and trajectory seed")
    p.add_argument("--lidar", action="store_true", help="synthetic: iPhone-LiDAR-like noisy 256x192 depth")
    p.add_argument("--yaw-rate-deg-s", type=float, default=0.0,
                   help="synthetic: fast rotation, an extra yaw swing peaking at this rate (deg/s; 0 = off)")
    p.add_argument("--depth-gap", type=_gap, default=None, metavar="START+FRAMES",
                   help="no depth in frames START .. START+FRAMES-1 (a sensor that saw nothing): how tracking comes "
                        "back after a gap, e.g. 40+15")
    p.add_argument("--revisit", type=_revisit, default=None, metavar="AT+BACK+FRAMES",
                   help="frames 0 .. AT-1, then after a 1 s pause frames BACK .. BACK+FRAMES-1 again (re-stamped): a "
                        "camera back at a place it mapped, how tracking relocalises, e.g. 60+15+15")
    p.add_argument("--method", nargs="+", default=["baseline"], choices=[*METHODS, *PLANNED_METHODS],
                   help="methods to run, in order (default: baseline)")
    p.add_argument("--max-frames", type=int, default=None, help="use at most this many frames")
    p.add_argument("--stride", type=int, default=1,
                   help="capture: use every N-th frame (N times the motion between frames; --max-frames counts "
                        "the frames kept)")
    p.add_argument("--name", default=None, help="result name (default: from the capture)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default bench/results)")
    p.add_argument("--baseline-preset", default="auto", choices=["auto", *BASELINE_PRESETS],
                   help="baseline options: " + "; ".join(f"{k}: {v[0]}" for k, v in BASELINE_PRESETS.items())
                   + " (auto: from the capture)")
    p.add_argument("--voxel-size-m", type=float, default=None, help="override the baseline's voxel size")
    p.add_argument("--vf-config", default=None,
                   help="voxfusion preset name or YAML (default: what voxfusion run picks for the capture and device)")
    p.add_argument("--vf-set", nargs="*", default=None, help="voxfusion overrides, e.g. mapping.iters=20")
    p.add_argument("--mesh-samples", type=int, default=200_000, help="surface samples per mesh for metrics")
    p.add_argument("--cull-stride", type=int, default=5,
                   help="cull GT samples to what every N-th reference camera saw (0: no culling)")
    p.add_argument("--save-outputs", action="store_true",
                   help="also write each method's traj.txt and mesh.ply to OUT/NAME/METHOD/")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    return p


def _check_args(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    for name in ("frames", "max_frames", "width", "height", "mesh_samples", "stride"):
        v = getattr(args, name)
        if v is not None and v < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {v}")
    if args.cull_stride < 0:
        p.error(f"--cull-stride must be >= 0, got {args.cull_stride}")
    if not args.synthetic and (args.width or args.height or args.lidar):
        p.error("--width/--height/--lidar apply to --synthetic only")
    if args.synthetic and args.stride != 1:
        p.error("--stride applies to --capture only (--yaw-rate-deg-s makes a synthetic trajectory fast)")
    if args.voxel_size_m is not None and not args.voxel_size_m > 0:
        p.error(f"--voxel-size-m must be > 0, got {args.voxel_size_m}")
    methods = list(dict.fromkeys(args.method))
    problems = [f"{m}: {PLANNED_METHODS[m]}" for m in methods if m in PLANNED_METHODS]
    problems += [f"{m}: {why}" for m in methods if m in METHODS and (why := METHODS[m].unavailable())]
    if problems:
        p.exit(2, "error: cannot run " + "; ".join(problems) + "\n")
    args.method = methods


def _write_pictures(args: argparse.Namespace, name: str, capture: Capture, results: dict[str, MethodResult],
                    gt_mesh: trimesh.Trimesh | None) -> list[Path]:
    """``OUT/<name>_view_frame.png`` (the middle frame's input beside every method's mesh, and the GT mesh,
    at that frame's pose) and ``OUT/<name>_view_overview.png``. The pose is the reference pose when the
    frame has one (every mesh here lives in the reference frame: runs start at the first reference pose),
    else the first method's estimate."""
    first = next(iter(results.values()))
    if len(first.trajectory) == 0:
        return []
    i = len(first.trajectory) // 2
    frame = capture[i]
    T = frame.T_world_cam if frame.T_world_cam is not None else first.trajectory.T_world_cam[i]
    up, _ = camera_up_forward(first.trajectory.T_world_cam)
    if frame.T_world_cam_device is not None:  # iPhone captures: ARKit's world, +y is up
        up = np.array([0.0, 1.0, 0.0])
    panels = {method: r.mesh for method, r in results.items()}
    if gt_mesh is not None:
        panels["ground truth"] = gt_mesh
    return write_mesh_views(args.out, panels, capture, i, T, up, prefix=f"{name}_view")


def run_benchmark(args: argparse.Namespace, argv: list[str]) -> dict:
    """Run ``args.method`` on the capture, evaluate, print the table; returns the JSON document."""
    capture, gt_mesh, default_name, capture_desc = _open(args)
    name = args.name or default_name
    recorder = _RecordingCapture(capture)
    results: dict[str, MethodResult] = {}
    for method in args.method:
        print(f"[bench] {method} on {name} ({len(recorder)} frames) ...", file=sys.stderr, flush=True)
        results[method] = METHODS[method].runner(recorder, args)
    from voxfusion.core.datasets.synthetic import SyntheticCapture

    # the synthetic room knows its whole trajectory; any other capture (a wrapped one too) gives its frames' poses
    reference = capture.trajectory if isinstance(capture, SyntheticCapture) else recorder.reference_trajectory()
    views = None
    if gt_mesh is not None and reference is not None and args.cull_stride > 0:
        views = views_from_frames(f for f in capture.frames(step=args.cull_stride) if f.T_world_cam is not None)

    rows, doc_methods = [], {}
    for method, result in results.items():
        ev = evaluate(result, reference, gt_mesh, views, args.mesh_samples, capture)
        rows.append(_row(method, result, ev))
        doc_methods[method] = {
            "description": METHODS[method].description,
            "n_frames": len(result.trajectory),
            "fps": result.fps,
            "frame_ms": _frame_ms_stats(result.frame_ms),
            "memory": asdict(result.memory),
            "ate_aligned": ev["ate_aligned"],
            "ate_unaligned": ev["ate_unaligned"],
            "rpe": ev["rpe"],
            "mesh": ev["mesh"],
            "phantom": ev["phantom"],
            "notes": ev["notes"],
            "config": result.config,
            "extra": result.extra,
        }
        if args.save_outputs:
            out_dir = args.out / name / method
            write_tum_trajectory(out_dir / "traj.txt", result.trajectory)
            if result.mesh is not None:
                result.mesh.export(out_dir / "mesh.ply")
    pictures = _write_pictures(args, name, capture, results, gt_mesh)
    columns = list(rows[0].keys())
    table = format_table(rows, columns, float_fmt=".2f")
    machine = machine_info()
    print(f"\n{name}: {len(recorder)} frames, {machine['cpu_model']} ({machine['cpu_usable_cores']} cores)"
          + (f", {machine['cuda_device']['name']}" if machine["cuda_device"] else ", no GPU"))
    print(table)
    for method, doc in doc_methods.items():
        for note in doc["notes"]:
            print(f"  {method}: {note}")
    doc = {
        "name": name,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": shlex.join(["python", "bench/run.py", *argv]),
        "machine": machine,
        "capture": {**capture_desc, "name": capture.name, "n_frames": len(recorder),
                    "has_reference_poses": reference is not None, "has_gt_mesh": gt_mesh is not None},
        "evaluation": {"ate": "RMSE; aligned = SE(3) Umeyama, unaligned = first pose anchored",
                       "mesh_method": "exact", "mesh_samples": args.mesh_samples,
                       "mesh_threshold_m": 0.05, "gt_culled_to_views_every": args.cull_stride if views else None,
                       "mesh_gt_part": "observed" if views else "full",
                       "phantom": "share of the mesh area > 5 cm from the depth placed with the method's own poses",
                       "peak_mb": "peak RSS increase during the method's run"},
        "table": table,
        "methods": doc_methods,
        "pictures": [str(p) for p in pictures],
    }
    path = write_json(args.out / f"{name}.json", doc)
    print(f"\nwrote {path}")
    return doc


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_args(parser, args)
    try:
        run_benchmark(args, argv)
    except VoxFusionError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
