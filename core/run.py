"""``voxfusion run`` as a library call: full SLAM over a recorded capture, with every output on disk.

Outputs in the run folder: ``trajectory.txt`` (TUM), ``keyframes.json``, ``mesh.ply``, ``voxels.npz``,
``voxels.ply``, ``checkpoint.pt``, ``metrics.json`` (ATE when the capture has reference poses, mesh
accuracy / completion against the whole GT and against its observed part when it has a GT mesh, the
phantom-surface share always, timings, peak memory), ``frames.json`` (per-frame tracking / mapping
times, losses, iterations, lost flags) and ``trajectory.png`` (top view and height over time, the estimate
aligned onto the reference as for the ATE: :mod:`.eval.trajectory_plot`).
"""

from __future__ import annotations

import dataclasses
import functools
import resource
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from tqdm import tqdm

from .checkpoint import save_checkpoint
from .config import config_to_dict
from .datasets.frame import Capture, TimedFrames
from .errors import ValidationError, VoxFusionError
from .eval.consistency import depth_consistency
from .eval.mesh import MeshEvalConfig, evaluate_mesh_against_gt, load_mesh, views_from_capture
from .eval.phantom import phantom_for_capture
from .eval.photometric import photometric_check
from .eval.report import write_json
from .eval.trajectory_error import TrajectoryEvalConfig, compute_ate
from .eval.trajectory_plot import plot_trajectory
from .geometry import invert_pose
from .map.export import export_voxels
from .mesh import export_mesh, write_scene_views
from .mesh.mesh_frame import WorldAxes, camera_up_forward
from .slam.presets import VoxFusionConfig
from .slam.system import SlamStats, SlamSystem
from .trajectory import Trajectory, write_tum_trajectory

__all__ = ["write_mesh_views", "reference_world_axes", "RunResult", "run_capture", "reference_trajectory",
           "evaluate_run", "evaluate_mesh", "evaluate_phantom", "write_trajectory_plot", "ATE_CONFIG",
           "peak_memory_mb"]

ATE_CONFIG = TrajectoryEvalConfig(align="se3", max_diff_s=1e-3)
"""How a run's estimate meets the capture's reference: SE(3) Umeyama alignment (``metrics.json``'s ``ate_se3``
and ``trajectory.png``); ``ate_none`` anchors the first pose instead. The estimate carries the capture's own
timestamps, so poses pair only with their own frame (1 ms)."""


@dataclass
class RunResult:
    """What :func:`run_capture` produced."""

    slam: SlamSystem
    trajectory: Trajectory
    mesh: trimesh.Trimesh
    stats: SlamStats
    wall_s: float
    metrics: dict
    out_dir: Path | None
    reference: Trajectory | None = None
    """The capture's reference poses over the run's frames (``None`` without, or with fewer than 3)."""
    load_s: float = 0.0
    """Seconds of ``wall_s`` spent reading frames from the capture (not the engine's time)."""


def peak_memory_mb(device: torch.device) -> dict[str, float]:
    """Peak resident memory of this process (MB, from getrusage) and peak CUDA allocation if on CUDA."""
    out = {"peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if device.type == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out


def reference_trajectory(capture: Capture, frames: int, step: int = 1) -> Trajectory | None:
    """The capture's reference poses over its first ``frames`` frames (None when it has none)."""
    stamps, poses = [], []
    for f in capture.frames(0, frames, step):
        if f.T_world_cam is not None:
            stamps.append(f.timestamp_s)
            poses.append(f.T_world_cam)
    if len(poses) < 3:
        return None
    return Trajectory(np.asarray(stamps), np.stack(poses))


def evaluate_run(trajectory: Trajectory, mesh: trimesh.Trimesh, capture: Capture, frames: int,
                 mesh_samples: int = 200_000, tracked: Trajectory | None = None,
                 reference: Trajectory | None = None) -> dict:
    """ATE (aligned and anchored at the first frame, :data:`ATE_CONFIG`), mesh metrics (``mesh_full_gt`` /
    ``mesh_observed_gt``) and the phantom-surface share (``phantom``: the mesh against the depth placed with
    ``tracked``, the estimate without its lost frames; ``trajectory`` when not given). ``reference``: the
    capture's reference poses over those frames when already known (else read from the capture)."""
    metrics: dict = {}
    ref = reference if reference is not None else reference_trajectory(capture, frames)
    if ref is not None and len(trajectory) >= 3:
        for align in ("se3", "none"):
            ate = compute_ate(trajectory, ref, dataclasses.replace(ATE_CONFIG, align=align))
            metrics[f"ate_{align}"] = ate.summary()
        if len(trajectory) == len(ref) == frames:  # every frame has a pose (offline runs)
            metrics["depth_consistency"] = compare_depth_consistency(capture, trajectory, ref)
    metrics.update(evaluate_mesh(mesh, capture, frames, mesh_samples))
    metrics.update(evaluate_phantom(mesh, capture, frames, trajectory if tracked is None else tracked,
                                    mesh_samples, max_diff_s=1e-3))
    photometric = evaluate_photometric(mesh, capture, frames, trajectory)
    if photometric is not None:
        metrics["photometric"] = photometric
    return metrics


def evaluate_photometric(mesh: trimesh.Trimesh, capture: Capture, frames: int, trajectory: Trajectory,
                         n_views: int = 5) -> dict | None:
    """The mesh's vertex colours against ``n_views`` input frames (:mod:`.eval.photometric`), placed with
    the estimated poses; frames halfway between the keyframe-interval marks (``i = 5 + 10 k``) so they are
    usually not keyframes, whose images colour the mesh. None for depth-only captures or an empty mesh."""
    if len(mesh.faces) == 0 or len(trajectory) != frames:
        return None
    picks = np.unique(np.linspace(0, max(0, (frames - 6) // 10), n_views).round().astype(int) * 10 + 5)
    picks = [int(i) for i in picks if i < frames] or [frames // 2]
    views = []
    for i in picks:
        f = capture[i]
        if f.color is None:
            return None
        views.append((f.color, f.depth_m, f.K, trajectory.T_world_cam[i]))
    return dataclasses.asdict(photometric_check(mesh, views)) | {"frames": picks}


def compare_depth_consistency(capture: Capture, estimate: Trajectory, reference: Trajectory) -> dict:
    """Multi-view depth disagreement (cm, per frame gap; lower is more self-consistent) of the estimated
    and the reference trajectory over the same frames: tells which is closer to the truth when the
    reference is itself an estimate (ARKit poses)."""
    n = len(estimate)
    gaps = tuple(g for g in (15, 60, 240) if g < n) or (max(1, n // 3),)

    @functools.cache  # both trajectories are judged on the same frames: read each once
    def load(i: int) -> tuple[np.ndarray, np.ndarray]:
        f = capture[i]
        return f.depth_m, f.K

    every = max(1, n // 50)
    return {name: depth_consistency(load, traj.T_world_cam, gaps, every).as_dict()
            for name, traj in (("estimate", estimate), ("reference", reference))}


def evaluate_mesh(mesh: trimesh.Trimesh, capture: Capture, frames: int, mesh_samples: int = 200_000) -> dict:
    """Exact accuracy / completion against the capture's GT mesh (``{}`` without one), by
    :func:`~.eval.mesh.evaluate_mesh_against_gt` (what ``voxfusion eval --capture`` runs too): ``mesh_full_gt``
    against the whole GT, ``mesh_observed_gt`` against the GT culled to what the reference cameras saw
    (:func:`~.eval.mesh.views_from_capture`, <= 200 views; absent when the capture has no reference poses).
    The mesh is evaluated as it is, in the frame the engine built it in."""
    gt = getattr(capture, "gt_mesh", None)
    if gt is None and capture.gt_mesh_path is not None:
        gt = load_mesh(capture.gt_mesh_path)
    if gt is None or not len(mesh.faces) or not mesh.area > 0:
        return {}
    views = views_from_capture(capture, frames) or None
    return evaluate_mesh_against_gt(mesh, gt, views, MeshEvalConfig(n_samples=mesh_samples)).summary()


def evaluate_phantom(mesh: trimesh.Trimesh, capture: Capture, frames: int, poses: Trajectory | None,
                     mesh_samples: int = 200_000, max_diff_s: float = 1e-3) -> dict:
    """Phantom-surface share of ``mesh`` (``{"phantom": PhantomResult}``; needs no GT): its area farther than
    5 cm from the depth of the first ``frames`` frames (<= 200 of them) placed with ``poses`` (the
    estimate's, the frame the mesh lives in), or with the capture's reference poses when ``poses`` is None.
    ``{}`` for an empty mesh; ``{"phantom_skipped": reason}`` when no frame has a pose or valid depth."""
    if not len(mesh.faces) or not mesh.area > 0:
        return {}
    try:
        return {"phantom": phantom_for_capture(mesh, capture, poses, frames, n_samples=mesh_samples,
                                               max_diff_s=max_diff_s)}
    except VoxFusionError as e:
        return {"phantom_skipped": str(e)}


def run_capture(capture: Capture, config: VoxFusionConfig, out_dir: str | Path | None = None,
                max_frames: int | None = None, progress: bool = True, speed: float = 1.0,
                evaluate: bool = True) -> RunResult:
    """Run SLAM over ``capture`` and (with ``out_dir``) write every output.

    In ``realtime`` mode frames are submitted at ``speed`` times their recorded rate, so frames the
    tracker cannot keep up with are dropped, as they would be live; ``offline`` processes every frame.
    """
    n = len(capture) if max_frames is None else min(max_frames, len(capture))
    if n == 0:
        raise ValidationError("capture", f"{capture.name} has no frames")
    torch.manual_seed(config.seed)
    slam = SlamSystem(config)
    bar = tqdm(total=n, desc=f"run {capture.name}", unit="frame", disable=not progress, dynamic_ncols=True)
    t0 = time.perf_counter()
    t_first: float | None = None
    ref_stamps, ref_poses = [], []  # the reference poses come with the frames: no second pass over the images
    frames = TimedFrames(capture.frames(0, n))
    for frame in frames:
        if frame.T_world_cam is not None:
            ref_stamps.append(frame.timestamp_s)
            ref_poses.append(frame.T_world_cam)
        if config.mode == "offline":
            rec = slam.process(frame)
        else:
            if t_first is None:
                t_first = frame.timestamp_s
            wait = (frame.timestamp_s - t_first) / speed - (time.perf_counter() - t0)
            if wait > 0:
                time.sleep(wait)
            slam.submit(frame)
            rec = slam.latest()
        st = slam.stats()
        if rec is not None:
            loss = rec.tracking.loss if rec.tracking else float("nan")
            bar.set_postfix(frame=rec.index, fps=f"{st.fps:.2f}", loss=f"{loss:.3f}", kf=st.keyframes,
                            lost=st.frames_lost, limited=st.frames_limited, dropped=st.frames_dropped)
        bar.update(1)
    slam.finish()
    bar.close()
    wall = time.perf_counter() - t0
    traj = slam.trajectory()
    mesh = slam.mesh()
    stats = slam.stats()
    ref = Trajectory(np.asarray(ref_stamps), np.stack(ref_poses)) if len(ref_poses) >= 3 else None
    metrics = evaluate_run(traj, mesh, capture, n, tracked=slam.trajectory(include_lost=False),
                           reference=ref) if evaluate else {}
    result = RunResult(slam, traj, mesh, stats, wall, metrics, Path(out_dir) if out_dir else None, ref,
                       load_s=frames.load_s)
    if out_dir is not None:
        write_run_outputs(result, capture, n)
    return result


def write_mesh_views(out_dir: Path, panels: dict[str, trimesh.Trimesh | None], capture: Capture,
                     frame_index: int, T_world_cam: np.ndarray, up: tuple[float, float, float] | np.ndarray,
                     prefix: str = "view") -> list[Path]:
    """Pictures next to the meshes (:func:`.mesh.write_scene_views`): frame ``frame_index``'s input colour
    image beside every mesh rendered at ``T_world_cam`` ``[4, 4]`` (that frame's pose in the meshes' world),
    and an overview from above (``up`` in that world). Returns the paths (none when no mesh has a face)."""
    frame = capture[frame_index]
    h, w = frame.depth_m.shape
    return write_scene_views(out_dir, panels, frame.K, T_world_cam, w, h, frame.color,
                             tuple(np.asarray(up, dtype=float)), prefix)


def reference_world_axes(trajectory: Trajectory) -> WorldAxes:
    """:class:`.mesh.mesh_frame.WorldAxes` of a map built with reference poses (``voxfusion map``)."""
    up, forward = camera_up_forward(trajectory.T_world_cam)
    return WorldAxes("reference", tuple(up.tolist()), tuple(forward.tolist()),
                     invert_pose(trajectory.T_world_cam[0]) if len(trajectory) else None)


def write_trajectory_plot(path: Path, slam: SlamSystem, trajectory: Trajectory,
                          reference: Trajectory | None) -> Path | None:
    """``trajectory.png`` (:func:`.eval.trajectory_plot.plot_trajectory`): the estimate, aligned onto
    ``reference`` as the ATE is (:data:`ATE_CONFIG`), lost and limited frames marked. "Up" is the session's
    (:meth:`SlamSystem.world_axes`: gravity in an ARKit world) when the estimate lives in the reference's
    world or there is no reference, else the reference cameras' (:func:`reference_world_axes`).
    ``None`` when there is no pose to draw."""
    if len(trajectory) == 0:
        return None
    axes = slam.world_axes()
    up = axes.up_m if reference is None or axes.world == "reference" else reference_world_axes(reference).up_m
    lost = np.array([r.lost for r in slam.records], dtype=bool)
    limited = np.array([r.limited for r in slam.records], dtype=bool)
    one_each = len(lost) == len(trajectory)
    return plot_trajectory(path, trajectory, up, reference, ATE_CONFIG, lost=lost if one_each else None,
                           limited=limited if one_each else None)


def _frame_rows(slam: SlamSystem) -> list[dict]:
    rows = []
    for r in slam.records:
        t, m = r.tracking, r.mapping
        rows.append({
            "index": r.index, "timestamp_s": r.timestamp_s, "lost": r.lost, "keyframe": r.keyframe is not None,
            "tracking_state": r.tracking_state, "cost_ratio": r.cost_ratio,
            "tracking_ms": t.time_ms if t else None, "tracking_iters": t.iterations if t else 0,
            "tracking_loss": t.loss if t else None, "valid_rays": t.valid_rays if t else None,
            "depth_residual_m": t.depth_residual_m if t else None,
            "lost_reason": t.reason if t else "",
            "mapping_ms": m.time_ms if m else None, "mapping_iters": m.iterations if m else 0,
            "mapping_loss": m.loss if m else None,
        })
    return rows


def timing_summary(result: RunResult) -> dict:
    """Frames per second and ms per tracking / mapping iteration over a run.

    ``fps`` is frames per second of the engine's time: in offline mode the wall time minus the time spent
    reading frames (``load_s``), as the TSDF baseline counts it; in realtime mode the wall time (frames
    arrive paced by their timestamps, so the wall clock is the session's clock).
    """
    slam, wall_s = result.slam, result.wall_s
    rows = _frame_rows(slam)
    busy_s = wall_s - result.load_s if slam.config.mode == "offline" else wall_s
    t_ms = sum(r["tracking_ms"] or 0.0 for r in rows)
    t_it = sum(r["tracking_iters"] for r in rows)
    m_ms = sum(r["mapping_ms"] or 0.0 for r in rows)
    m_it = sum(r["mapping_iters"] for r in rows)
    return {
        "wall_s": wall_s, "load_s": result.load_s, "fps": len(rows) / busy_s if busy_s > 0 else None,
        "tracking_ms_per_frame": t_ms / max(1, sum(1 for r in rows if r["tracking_iters"])),
        "tracking_ms_per_iter": t_ms / t_it if t_it else None,
        "mapping_ms_per_iter": m_ms / m_it if m_it else None,
        "tracking_iters": t_it, "mapping_iters": m_it,
    }


def write_run_outputs(result: RunResult, capture: Capture, frames: int) -> None:
    """Write trajectory (TUM and ``trajectory.png``), keyframes, mesh, voxels, checkpoint, metrics and
    per-frame timings."""
    out = result.out_dir
    if out is None:
        raise ValidationError("out_dir", "no output folder given")
    out.mkdir(parents=True, exist_ok=True)
    slam = result.slam
    mapper = slam.mapper
    write_tum_trajectory(out / "trajectory.txt", result.trajectory)
    write_trajectory_plot(out / "trajectory.png", slam, result.trajectory, result.reference)
    write_json(out / "keyframes.json", [
        {"index": kf.data.index, "timestamp_s": kf.data.timestamp_s, "T_world_cam": kf.T_world_cam.cpu().numpy()}
        for kf in mapper.keyframes])
    axes = slam.world_axes()
    export_mesh(result.mesh, out / "mesh.ply", axes)
    middle = slam.records[len(slam.records) // 2]
    write_mesh_views(out, {"voxfusion": result.mesh}, capture, middle.index, middle.current_pose(), axes.up_m)
    export_voxels(mapper.voxels, out / "voxels.npz", mapper.decoder)
    export_voxels(mapper.voxels, out / "voxels.ply")
    save_checkpoint(out / "checkpoint.pt", mapper, slam.config, result.trajectory)
    write_json(out / "frames.json", _frame_rows(slam))
    mem = mapper.voxels.memory_report(mapper.decoder)
    write_json(out / "metrics.json", {
        "capture": str(capture.path), "frames": frames, "config": config_to_dict(slam.config),
        "stats": dataclasses.asdict(result.stats), "timings": timing_summary(result),
        "memory": {**dataclasses.asdict(mem), **peak_memory_mb(slam.device)},
        **result.metrics,
    })
