"""Mapping with known poses: ``voxfusion map`` as a library call.

Every frame of a capture is fused with its reference pose; the outputs (mesh, voxel map, checkpoint,
metrics, timings) are written to one folder.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from tqdm import tqdm

from .checkpoint import save_checkpoint
from .datasets.frame import Capture, TimedFrames
from .errors import ValidationError
from .eval.report import write_json
from .framedata import frame_to_device
from .map.export import export_voxels
from .mesh import export_mesh
from .run import reference_world_axes, write_mesh_views
from .slam.mapping import Mapper, MappingStep, make_mapper
from .slam.presets import VoxFusionConfig
from .trajectory import Trajectory, write_tum_trajectory

__all__ = ["MapRunResult", "make_mapper", "map_capture", "write_map_outputs"]


@dataclass
class MapRunResult:
    """Outputs of :func:`map_capture`: the mapper, the mesh, the poses used, per-frame steps and timings."""

    mapper: Mapper
    config: VoxFusionConfig
    """The config actually used (known-pose mapping turns ``mapping.optimize_poses`` off)."""
    mesh: trimesh.Trimesh
    trajectory: Trajectory
    steps: list[MappingStep]
    wall_s: float
    mesh_s: float
    out_dir: Path | None
    frame_indices: list[int] = dataclasses.field(default_factory=list)
    """Capture index of each trajectory row (frames without a pose or depth are skipped)."""
    load_s: float = 0.0
    """Seconds of ``wall_s`` spent reading frames from the capture (not the engine's time)."""

    @property
    def fps(self) -> float:
        """Fused frames per second of processing time (``wall_s`` minus ``load_s``)."""
        busy = self.wall_s - self.load_s
        return len(self.steps) / busy if busy > 0 else float("nan")

    def timing_summary(self) -> dict[str, float]:
        iters = sum(s.iterations for s in self.steps)
        map_ms = sum(s.time_ms for s in self.steps)
        return {
            "frames": len(self.steps),
            "keyframes": sum(s.is_keyframe for s in self.steps),
            "wall_s": self.wall_s,
            "load_s": self.load_s,
            "fps": self.fps,
            "mapping_iterations": iters,
            "ms_per_mapping_iteration": map_ms / iters if iters else float("nan"),
            "mesh_extraction_s": self.mesh_s,
        }


def map_capture(capture: Capture, config: VoxFusionConfig, out_dir: str | Path | None = None,
                max_frames: int | None = None, progress: bool = True) -> MapRunResult:
    """Fuse every frame of ``capture`` with its reference pose; write outputs to ``out_dir`` if given.

    Frames without a reference pose are skipped (counted in the progress bar). Raises
    ``ValidationError`` when no frame has one.
    """
    # The poses are given: refine nothing but the map.
    config = dataclasses.replace(config, mapping=dataclasses.replace(config.mapping, optimize_poses=False))
    torch.manual_seed(config.seed)
    n = len(capture) if max_frames is None else min(max_frames, len(capture))
    if n == 0:
        raise ValidationError("capture", f"{capture.name} has no frames")
    first = capture[0]
    mapper = make_mapper(config, has_color=first.color is not None)
    steps: list[MappingStep] = []
    stamps, poses, indices = [], [], []
    skipped = 0
    t0 = time.perf_counter()
    bar = tqdm(total=n, desc=f"map {capture.name}", unit="frame", disable=not progress, dynamic_ncols=True)
    frames = TimedFrames(capture.frames(0, n))
    for frame in frames:
        if frame.T_world_cam is None:
            skipped += 1
            bar.update(1)
            continue
        data = frame_to_device(frame, mapper.device, config.mapping.min_depth_m, config.mapping.max_depth_m,
                               config.mapping.min_confidence, use_color=mapper.field_config.use_color,
                               depth_filter=config.mapping.depth_filter)
        if data.n_valid == 0:
            skipped += 1
            bar.update(1)
            continue
        steps.append(mapper.integrate(data, frame.T_world_cam))
        stamps.append(frame.timestamp_s)
        poses.append(frame.T_world_cam)
        indices.append(frame.index)
        elapsed = time.perf_counter() - t0
        bar.set_postfix(frame=frame.index, loss=f"{steps[-1].loss:.4f}", fps=f"{len(steps) / elapsed:.2f}",
                        kf=len(mapper.keyframes), vox=mapper.voxels.n_voxels, skipped=skipped)
        bar.update(1)
    bar.close()
    if not steps:
        raise ValidationError("capture", f"{capture.name}: no frame has a reference pose and valid depth")
    mapper.finish()
    wall = time.perf_counter() - t0
    t1 = time.perf_counter()
    mesh = mapper.extract_mesh(config.mesh_res, config.mesh_support, config.mesh_colors)
    mesh_s = time.perf_counter() - t1
    traj = Trajectory(np.asarray(stamps), np.stack(poses))
    result = MapRunResult(mapper, config, mesh, traj, steps, wall, mesh_s, Path(out_dir) if out_dir else None,
                          indices, load_s=frames.load_s)
    if out_dir is not None:
        write_map_outputs(result, capture)
    return result


def write_map_outputs(result: MapRunResult, capture: Capture | None = None) -> None:
    """mesh.ply (+ its ``.frame.json``), voxels.npz, voxels.ply, checkpoint.pt, trajectory.txt, timings.json in
    ``result.out_dir``, and with ``capture`` the pictures ``view_frame.png`` / ``view_overview.png``."""

    out = result.out_dir
    if out is None:
        raise ValidationError("out_dir", "no output folder given")
    out.mkdir(parents=True, exist_ok=True)
    m = result.mapper
    axes = reference_world_axes(result.trajectory)
    export_mesh(result.mesh, out / "mesh.ply", axes)
    if capture is not None and result.frame_indices:
        middle = len(result.frame_indices) // 2
        write_mesh_views(out, {"voxfusion": result.mesh}, capture, result.frame_indices[middle],
                         result.trajectory.T_world_cam[middle], axes.up_m)
    export_voxels(m.voxels, out / "voxels.npz", m.decoder)
    export_voxels(m.voxels, out / "voxels.ply")
    save_checkpoint(out / "checkpoint.pt", m, result.config, result.trajectory)
    write_tum_trajectory(out / "trajectory.txt", result.trajectory)
    mem = m.voxels.memory_report(m.decoder)
    write_json(out / "timings.json", {
        **result.timing_summary(),
        "memory": dataclasses.asdict(mem),
        "per_frame": [dataclasses.asdict(s) for s in result.steps],
    })
