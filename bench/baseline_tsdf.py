"""The classic TSDF baseline every benchmark runs beside Vox-Fusion: KinectFusion-style dense RGB-D SLAM
on Open3D's tensor pipeline (``open3d.t.pipelines.slam``).

Per frame (the loop of Open3D's ``examples/python/t_reconstruction_system/dense_slam.py``):

1. ``model.track_frame_to_model(input, raycast, ...)``: multi-scale point-to-plane ICP of the frame's
   depth against the depth ray-cast from the model at the previous pose (frame-to-model odometry);
   ``T_world_cam = T_prev @ result.transformation``;
2. ``model.update_frame_pose(i, T_world_cam)`` and ``model.integrate(...)``: TSDF fusion into a
   ``VoxelBlockGrid`` (hashed 16^3 voxel blocks);
3. ``model.synthesize_model_frame(...)``: ray-cast the model at the new pose for the next frame.

At the end the mesh is ``model.voxel_grid.extract_triangle_mesh()`` (marching cubes, vertex colours).

Two corrections of Open3D 0.20's kernels are on by default (see :class:`TSDFBaselineConfig`); with both
off this is exactly Open3D's example. On the synthetic room (100 frames, 320x240, 1 cm voxels, exact
ground truth) they bring the ATE from 2.91 to 0.25 cm (unaligned drift 8.5 -> 1.5 cm, RPE 2.0 -> 0.7 mm);
on TUM fr1/desk (9 frames, motion-capture ground truth) the drift at frame 8 from 4.0 to 2.3 cm. On
7-Scenes redkitchen (300 frames, KinectFusion pseudo ground truth) RPE is unchanged (3.1 mm) and the ATE is
2.9 cm against 2.4 cm stock: drift there is dominated by accumulation, not per-frame bias (bench/README.md).

* **Ray-cast half-voxel offset.** ``VoxelBlockGrid.ray_cast`` looks voxels up by truncation
  (``int(x / voxel_size)``) while integration stores voxel ``i`` at ``i * voxel_size``; the ray-cast
  surface is therefore shifted by about +0.5 voxel along each world axis, tracking locks onto the
  shifted surface and the pose drifts by that much every frame. We ray-cast from the camera translated
  by ``+0.5 * voxel_size`` along each world axis, which samples the nearest voxel instead.
* **Integration half-pixel offset.** ``Integrate`` reads the depth pixel ``int(u), int(v)`` (truncation)
  of a voxel's projection ``(u, v)``, while pixel centres are at integer coordinates (isl-org/Open3D
  issue #7580). We integrate through a frame whose principal point is moved by +0.5 px, so the lookup
  rounds to the nearest pixel.

Inputs: our frames' float32 metre depth goes in as float32 with ``depth_scale = 1.0`` (Open3D then
requires float32 colour in [0, 1]); depth-only captures integrate a constant grey. Tracking failures (an
Open3D exception, fitness below ``min_fitness``, or a per-frame jump above ``max_step_translation_m`` /
``max_step_rotation_deg``) keep the previous pose, skip the frame's integration and are counted.

Open3D is an optional extra: ``pip install 'voxfusion[baseline]'``.

Example::

    from voxfusion.core.datasets import open_capture
    from bench.baseline_tsdf import TSDFBaselineConfig, run_tsdf_baseline, save_result

    result = run_tsdf_baseline(open_capture("../shared/data/tum_fr1_desk_9frames"), TSDFBaselineConfig())
    save_result(result, "out/tum_baseline")   # traj.txt (TUM), mesh.ply, timings.json
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets.frame import Capture, RGBDFrame
from voxfusion.core.errors import ConfigError, ShapeError, ValidationError, VoxFusionError
from voxfusion.core.trajectory import Trajectory, write_tum_trajectory

from .machine import MemoryUsage, PeakMemory

__all__ = [
    "BASELINE_PRESETS",
    "BaselineResult",
    "FrameTimings",
    "MissingDependencyError",
    "TSDFBaselineConfig",
    "TSDFBaselineRun",
    "require_open3d",
    "run_tsdf_baseline",
    "save_result",
    "timings_summary",
    "tsdf_render_back",
]

_INSTALL_HINT = "pip install 'voxfusion[baseline]'"


class MissingDependencyError(VoxFusionError, ImportError):
    """An optional dependency is not installed; the message says how to install it."""


def require_open3d():  # noqa: ANN201 (returns the open3d module)
    """Import and return ``open3d``, or raise :class:`MissingDependencyError` with the install command."""
    try:
        import open3d
    except ImportError as e:
        raise MissingDependencyError(
            f"the TSDF baseline needs Open3D, which is not installed (or failed to load: {e}). "
            f"Install the optional extra: {_INSTALL_HINT}"
        ) from e
    return open3d


@dataclass(frozen=True)
class TSDFBaselineConfig:
    """Options of the TSDF baseline (Open3D ``t.pipelines.slam``).

    Typical voxel sizes: 1 cm for 640x480 Kinect-class captures (7-Scenes, TUM, ScanNet; Open3D's own
    default is 5.8 mm) and for the noise-free synthetic room (at 320x240, 1 cm beat 2 cm on every metric:
    ATE 0.25 vs 0.67 cm, accuracy 0.79 vs 1.23 cm, at 7.6 vs 12.4 fps); 2 cm for noisy iPhone LiDAR
    depth (256x192). See :data:`BASELINE_PRESETS`.
    """

    voxel_size_m: float = 0.01
    """Edge of one TSDF voxel, metres."""
    block_resolution: int = 16
    """Voxels per block edge (blocks of ``block_resolution**3`` voxels are the hashed unit)."""
    block_count: int = 10_000
    """Initial capacity of the block hash map. Open3D allocates (and zeroes) it up front, about 12 bytes
    per voxel (10,000 blocks of 16^3: ~0.5 GB), and grows it when full, so this sets memory, not a limit."""
    depth_min_m: float = 0.1
    """Ray-casting starts this far from the camera, metres."""
    depth_max_m: float = 3.0
    """Depth beyond this is ignored for tracking, integration and ray casting, metres."""
    trunc_voxel_multiplier: float = 8.0
    """TSDF truncation distance in voxels (8 x 1 cm = 8 cm)."""
    odometry_distance_thr: float = 0.07
    """ICP correspondences farther apart than this are rejected, metres (Open3D's ``depth_diff``)."""
    mesh_weight_threshold: float = 3.0
    """Voxels observed fewer times than this are left out of the extracted mesh."""
    min_fitness: float = 0.05
    """A tracking result with a smaller inlier fraction is a failure."""
    max_step_translation_m: float = 0.3
    """A frame-to-frame camera move larger than this is a tracking failure, metres."""
    max_step_rotation_deg: float = 30.0
    """A frame-to-frame rotation larger than this is a tracking failure, degrees."""
    fix_raycast_half_voxel: bool = True
    """Compensate Open3D's half-voxel ray-cast offset (module docstring); ``False`` = stock Open3D."""
    fix_integrate_half_pixel: bool = True
    """Compensate Open3D's half-pixel depth lookup in integration (module docstring)."""
    device: str = "CPU:0"
    """Open3D device, ``"CPU:0"`` or ``"CUDA:0"`` (needs a CUDA build of Open3D; never switched silently)."""

    def __post_init__(self) -> None:
        positive = ("voxel_size_m", "depth_max_m", "trunc_voxel_multiplier", "odometry_distance_thr",
                    "max_step_translation_m", "max_step_rotation_deg")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and value > 0):
                raise ConfigError(name, f"must be > 0, got {value!r}")
        for name in ("block_resolution", "block_count"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(name, f"must be a positive integer, got {value!r}")
        if not 0 <= self.depth_min_m < self.depth_max_m:
            raise ConfigError("depth_min_m", f"must be in [0, depth_max_m={self.depth_max_m}), "
                                             f"got {self.depth_min_m}")
        if not 0 <= self.min_fitness < 1:
            raise ConfigError("min_fitness", f"must be in [0, 1), got {self.min_fitness}")
        if not self.mesh_weight_threshold >= 0:
            raise ConfigError("mesh_weight_threshold", f"must be >= 0, got {self.mesh_weight_threshold}")
        kind = self.device.split(":")[0]
        if kind not in ("CPU", "CUDA") or ":" not in self.device:
            raise ConfigError("device", f"must look like 'CPU:0' or 'CUDA:0', got {self.device!r}")


BASELINE_PRESETS: dict[str, tuple[str, TSDFBaselineConfig]] = {
    "kinect": ("640x480 Kinect-class depth (7-Scenes, TUM, ScanNet): 1 cm voxels, 3 m range",
               TSDFBaselineConfig(voxel_size_m=0.01, depth_max_m=3.0)),
    "synthetic": ("our synthetic room (noise-free, up to ~5 m deep): 1 cm voxels, 5 m range",
                  TSDFBaselineConfig(voxel_size_m=0.01, depth_max_m=5.0)),
    "lidar": ("iPhone / iPad LiDAR (256x192, noisy beyond 3 m): 2 cm voxels, 4 m range",
              TSDFBaselineConfig(voxel_size_m=0.02, depth_max_m=4.0)),
}
"""Preset name -> (one-line description, config)."""


@dataclass(frozen=True, eq=False)
class FrameTimings:
    """Wall-clock milliseconds per frame, each ``[N]`` float64.

    Attributes:
        load_ms: reading / decoding the frame from the capture (not part of the method's time).
        track_ms: frame-to-model ICP (0 for the first frame).
        integrate_ms: TSDF integration (0 when tracking failed).
        raycast_ms: ray casting the model for the next frame (0 when tracking failed).
    """

    load_ms: np.ndarray
    track_ms: np.ndarray
    integrate_ms: np.ndarray
    raycast_ms: np.ndarray

    @property
    def total_ms(self) -> np.ndarray:
        """``[N]`` processing time per frame (track + integrate + ray cast), loading excluded."""
        return self.track_ms + self.integrate_ms + self.raycast_ms


@dataclass(frozen=True, eq=False)
class BaselineResult:
    """Output of :func:`run_tsdf_baseline`.

    Attributes:
        trajectory: estimated ``T_world_cam`` per processed frame (frame timestamps), in the frame of the
            capture's first reference pose when it has one.
        mesh: extracted mesh (world frame, metres, RGBA uint8 vertex colours); empty when no voxel
            reached ``mesh_weight_threshold``.
        timings: per-frame timings.
        mesh_extraction_ms: time to extract the mesh at the end.
        fps: processed frames per second of processing time (``N / sum(timings.total_ms)``).
        memory: peak memory of the whole run, loading and mesh extraction included.
        n_tracking_failures: frames whose tracking failed (pose kept, not integrated).
        failed_frames: their indices.
        config: the options used.
    """

    trajectory: Trajectory
    mesh: trimesh.Trimesh
    timings: FrameTimings
    mesh_extraction_ms: float
    fps: float
    memory: MemoryUsage
    n_tracking_failures: int
    failed_frames: list[int]
    config: TSDFBaselineConfig
    meta: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.trajectory)


@contextlib.contextmanager
def _quiet_open3d(o3d) -> Iterator[None]:  # noqa: ANN001
    """Silence Open3D's per-frame INFO/WARNING lines ("Reallocating fragments ...") inside the block."""
    previous = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        yield
    finally:
        o3d.utility.set_verbosity_level(previous)


def _device(o3d, name: str):  # noqa: ANN001, ANN202
    if name.startswith("CUDA") and not o3d.core.cuda.is_available():
        raise ConfigError("device", f"{name} requested but this Open3D build has no CUDA device "
                                    "(open3d-cpu); use 'CPU:0'")
    return o3d.core.Device(name)


def _step_too_large(T_step: np.ndarray, config: TSDFBaselineConfig) -> bool:
    translation = float(np.linalg.norm(T_step[:3, 3]))
    angle_deg = float(np.degrees(Rotation.from_matrix(T_step[:3, :3]).magnitude()))
    return translation > config.max_step_translation_m or angle_deg > config.max_step_rotation_deg


def _to_trimesh(mesh_t) -> trimesh.Trimesh:  # noqa: ANN001
    legacy = mesh_t.to_legacy()
    vertices = np.asarray(legacy.vertices, dtype=np.float64)
    faces = np.asarray(legacy.triangles, dtype=np.int64)
    colors = np.asarray(legacy.vertex_colors, dtype=np.float64)
    if len(colors) != len(vertices):
        colors = np.full((len(vertices), 3), 0.5)
    rgba = np.concatenate([np.clip(np.round(colors * 255.0), 0, 255), np.full((len(colors), 1), 255.0)], 1)
    return trimesh.Trimesh(vertices=vertices, faces=faces.reshape(-1, 3), vertex_colors=rgba.astype(np.uint8),
                           process=False)


class _Frames:
    """The Open3D input frames (tracking and integration) and the ray-cast frame for one image size."""

    def __init__(self, o3d, frame: RGBDFrame, device, config: TSDFBaselineConfig) -> None:  # noqa: ANN001
        slam = o3d.t.pipelines.slam
        self.o3d = o3d
        self.shape = frame.depth_m.shape
        self.K = frame.K.copy()
        h, w = self.shape
        K_t = o3d.core.Tensor(self.K)
        self.track = slam.Frame(h, w, K_t, device)
        self.raycast = slam.Frame(h, w, K_t, device)
        if config.fix_integrate_half_pixel:
            K_int = self.K.copy()
            K_int[0, 2] += 0.5
            K_int[1, 2] += 0.5
            self.integrate = slam.Frame(h, w, o3d.core.Tensor(K_int), device)
        else:
            self.integrate = self.track
        self.device = device
        self._grey = np.full((h, w, 3), 0.5, dtype=np.float32)

    def matches(self, frame: RGBDFrame) -> bool:
        return frame.depth_m.shape == self.shape and np.allclose(frame.K, self.K, rtol=0, atol=1e-9)

    def set(self, frame: RGBDFrame) -> None:
        o3d = self.o3d
        depth = np.ascontiguousarray(np.nan_to_num(frame.depth_m, nan=0.0, posinf=0.0, neginf=0.0))
        color = (frame.color.astype(np.float32) / 255.0) if frame.color is not None else self._grey
        depth_img = o3d.t.geometry.Image(o3d.core.Tensor(depth, device=self.device))
        color_img = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(color), device=self.device))
        targets = [self.track] if self.integrate is self.track else [self.track, self.integrate]
        for target in targets:
            target.set_data_from_image("depth", depth_img)
            target.set_data_from_image("color", color_img)


def run_tsdf_baseline(capture: Capture, config: TSDFBaselineConfig | None = None,
                      max_frames: int | None = None, progress: bool = True) -> BaselineResult:
    """Run the TSDF baseline over ``capture`` (see the module docstring).

    Args:
        capture: any :class:`Capture` (frames with float32 metre depth, optional colour, ``K``).
        config: options (default :class:`TSDFBaselineConfig`).
        max_frames: process at most this many frames from the start; ``None`` = all.
        progress: show a progress bar on stderr.

    Returns:
        A :class:`BaselineResult`. The first pose is the first frame's reference pose ``T_world_cam``
        when it has one (so the trajectory lives in the reference's frame), the identity otherwise.

    Raises:
        MissingDependencyError: Open3D is not installed.
        ConfigError: bad options, or a CUDA device without a CUDA build of Open3D.
        ValidationError / ShapeError: an empty capture, or frames whose image size changes.
    """
    if max_frames is not None and max_frames < 1:
        raise ValidationError("max_frames", f"must be >= 1 or None, got {max_frames}")
    n = len(capture) if max_frames is None else min(len(capture), max_frames)
    if n == 0:
        raise ValidationError("capture", f"{getattr(capture, 'name', 'capture')} has no frames")
    run = TSDFBaselineRun(config)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, desc="tsdf-baseline", unit="frame", leave=False)
    tick = time.perf_counter
    with PeakMemory() as mem, run.quiet():
        frames_it = capture.frames(0, n)
        for _ in range(n):
            t0 = tick()
            frame = next(frames_it)
            run.step(frame, load_ms=(tick() - t0) * 1e3)
            mem.sample()
            if bar is not None:
                bar.update(1)
        run.extract_mesh()
    if bar is not None:
        bar.close()
    return run.result(mem.result, capture_name=getattr(capture, "name", None))


class TSDFBaselineRun:
    """One run of the baseline, a frame at a time: what :func:`run_tsdf_baseline` loops over, and what a caller
    interleaves frame by frame with another method so that both meet the same machine (``bench/fps_pair.py``).

    Example::

        run = TSDFBaselineRun(TSDFBaselineConfig())
        with run.quiet():
            for frame in capture.frames(0, len(capture)):
                ms = run.step(frame)        # processing time of this frame (tracking + integration + ray cast)
            run.extract_mesh()
        result = run.result(memory)
    """

    def __init__(self, config: TSDFBaselineConfig | None = None) -> None:
        config = config if config is not None else TSDFBaselineConfig()
        if not isinstance(config, TSDFBaselineConfig):
            raise ValidationError("config", f"must be a TSDFBaselineConfig, got {type(config).__name__}")
        self.config = config
        self.o3d = require_open3d()
        self.device = _device(self.o3d, config.device)
        self._shift_m = 0.5 * config.voxel_size_m if config.fix_raycast_half_voxel else 0.0
        self._model = self._frames = None
        self._T_world_cam = np.eye(4)
        self._timestamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self.failed: list[int] = []
        self._ms: dict[str, list[float]] = {"load": [], "track": [], "integrate": [], "raycast": []}
        self._mesh: trimesh.Trimesh | None = None
        self._mesh_ms = 0.0

    def quiet(self) -> contextlib.AbstractContextManager:
        """Silence Open3D's per-frame INFO/WARNING lines inside the block."""
        return _quiet_open3d(self.o3d)

    def step(self, frame: RGBDFrame, load_ms: float = 0.0) -> float:
        """Track ``frame`` against the model (not the first), integrate it and ray-cast the model at its pose;
        returns this frame's processing time in milliseconds (``load_ms``, the caller's time to read it, is
        recorded apart)."""
        o3d, config, tick = self.o3d, self.config, time.perf_counter
        i = len(self._timestamps)
        if self._frames is None:
            if frame.T_world_cam is not None:
                self._T_world_cam = np.array(frame.T_world_cam, dtype=np.float64)
            self._frames = _Frames(o3d, frame, self.device, config)
            self._model = o3d.t.pipelines.slam.Model(config.voxel_size_m, config.block_resolution,
                                                     config.block_count, o3d.core.Tensor(self._T_world_cam),
                                                     self.device)
        elif frame.depth_m.shape != self._frames.shape:
            raise ShapeError(f"frame {i} depth_m", frame.depth_m.shape,
                             f"{self._frames.shape} (the first frame's size; the baseline needs one size)")
        elif not self._frames.matches(frame):
            raycast = self._frames.raycast
            self._frames = _Frames(o3d, frame, self.device, config)
            self._frames.raycast = raycast
        frames, model = self._frames, self._model
        frames.set(frame)

        ok = True
        track_ms = integrate_ms = raycast_ms = 0.0
        if i > 0:
            t0 = tick()
            try:
                result = model.track_frame_to_model(frames.track, frames.raycast, 1.0, config.depth_max_m,
                                                     config.odometry_distance_thr)
                T_step = result.transformation.cpu().numpy().astype(np.float64)
                ok = (bool(np.all(np.isfinite(T_step))) and result.fitness >= config.min_fitness
                      and not _step_too_large(T_step, config))
            except RuntimeError:
                ok = False
            track_ms = (tick() - t0) * 1e3
            if ok:
                self._T_world_cam = self._T_world_cam @ T_step
            else:
                self.failed.append(i)
        if ok:
            t0 = tick()
            model.update_frame_pose(i, o3d.core.Tensor(self._T_world_cam))
            model.integrate(frames.integrate, 1.0, config.depth_max_m, config.trunc_voxel_multiplier)
            integrate_ms = (tick() - t0) * 1e3
            t0 = tick()
            if self._shift_m:
                T_raycast = self._T_world_cam.copy()
                T_raycast[:3, 3] += self._shift_m
                model.update_frame_pose(i, o3d.core.Tensor(T_raycast))
            model.synthesize_model_frame(frames.raycast, 1.0, config.depth_min_m, config.depth_max_m,
                                         config.trunc_voxel_multiplier, False)
            raycast_ms = (tick() - t0) * 1e3
        self._timestamps.append(frame.timestamp_s)
        self._poses.append(self._T_world_cam.copy())
        for key, ms in (("load", load_ms), ("track", track_ms), ("integrate", integrate_ms), ("raycast", raycast_ms)):
            self._ms[key].append(ms)
        return track_ms + integrate_ms + raycast_ms

    @property
    def trajectory(self) -> Trajectory:
        """The poses so far (``T_world_cam`` per processed frame, at the frames' timestamps)."""
        if not self._poses:
            raise ValidationError("capture", "no frame was processed")
        return Trajectory(np.asarray(self._timestamps), np.stack(self._poses))

    def extract_mesh(self) -> trimesh.Trimesh:
        """The model's mesh (marching cubes), timed; ValidationError before any frame."""
        if self._model is None:
            raise ValidationError("capture", "no frame was processed")
        t0 = time.perf_counter()
        self._mesh = _to_trimesh(self._model.voxel_grid.extract_triangle_mesh(self.config.mesh_weight_threshold))
        self._mesh_ms = (time.perf_counter() - t0) * 1e3
        return self._mesh

    def result(self, memory: MemoryUsage, capture_name: str | None = None) -> BaselineResult:
        """The run's :class:`BaselineResult` (after :meth:`extract_mesh`); ``memory``: the caller's measure."""
        if self._mesh is None:
            raise ValidationError("mesh", "call extract_mesh() first")
        n = len(self._timestamps)
        timings = FrameTimings(*(np.asarray(self._ms[k], dtype=np.float64)
                                 for k in ("load", "track", "integrate", "raycast")))
        total_s = float(timings.total_ms.sum()) / 1e3
        return BaselineResult(
            trajectory=self.trajectory,
            mesh=self._mesh,
            timings=timings,
            mesh_extraction_ms=self._mesh_ms,
            fps=n / total_s if total_s > 0 else float("inf"),
            memory=memory,
            n_tracking_failures=len(self.failed),
            failed_frames=list(self.failed),
            config=self.config,
            meta={"n_voxel_blocks": int(self._model.voxel_grid.hashmap().size()), "open3d": self.o3d.__version__,
                  "capture": capture_name},
        )


def tsdf_render_back(frame: RGBDFrame, T_world_cam: np.ndarray,
                     config: TSDFBaselineConfig | None = None) -> np.ndarray:
    """Integrate one frame at ``T_world_cam`` into a fresh TSDF and ray-cast its depth at the same pose.

    The baseline's side of the render-back probe (``bench/bench_outliers.py``): the same model, corrections
    and truncation as :func:`run_tsdf_baseline`, no tracking.

    Returns:
        ``[H, W]`` float32 ray-cast camera z-depth in metres, 0 where the ray found no surface.

    Raises:
        MissingDependencyError: Open3D is not installed. ShapeError: ``T_world_cam`` is not 4x4.
    """
    config = config if config is not None else TSDFBaselineConfig()
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError("T_world_cam", T.shape, "(4, 4)")
    o3d = require_open3d()
    device = _device(o3d, config.device)
    with _quiet_open3d(o3d):
        frames = _Frames(o3d, frame, device, config)
        frames.set(frame)
        model = o3d.t.pipelines.slam.Model(config.voxel_size_m, config.block_resolution, config.block_count,
                                           o3d.core.Tensor(T), device)
        model.update_frame_pose(0, o3d.core.Tensor(T))
        model.integrate(frames.integrate, 1.0, config.depth_max_m, config.trunc_voxel_multiplier)
        if config.fix_raycast_half_voxel:
            T_raycast = T.copy()
            T_raycast[:3, 3] += 0.5 * config.voxel_size_m
            model.update_frame_pose(0, o3d.core.Tensor(T_raycast))
        model.synthesize_model_frame(frames.raycast, 1.0, config.depth_min_m, config.depth_max_m,
                                     config.trunc_voxel_multiplier, False)
        depth = np.asarray(frames.raycast.get_data_as_image("depth").as_tensor().cpu().numpy(), np.float32)
    depth = depth.reshape(frame.depth_m.shape)
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def _stats_ms(a: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(a)), "median": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(np.max(a))}


def timings_summary(result: BaselineResult) -> dict[str, object]:
    """JSON-ready summary of a result's timing, memory and failures (what ``timings.json`` holds)."""
    t = result.timings
    return {
        "n_frames": result.n_frames,
        "fps": result.fps,
        "frame_ms": _stats_ms(t.total_ms),
        "track_ms": _stats_ms(t.track_ms[1:] if len(t.track_ms) > 1 else t.track_ms),
        "integrate_ms": _stats_ms(t.integrate_ms),
        "raycast_ms": _stats_ms(t.raycast_ms),
        "load_ms": _stats_ms(t.load_ms),
        "mesh_extraction_ms": result.mesh_extraction_ms,
        "memory": asdict(result.memory),
        "n_tracking_failures": result.n_tracking_failures,
        "failed_frames": list(result.failed_frames),
        "mesh_vertices": int(len(result.mesh.vertices)),
        "mesh_faces": int(len(result.mesh.faces)),
        "config": asdict(result.config),
        "meta": dict(result.meta),
        "per_frame_ms": {
            "load": t.load_ms.tolist(), "track": t.track_ms.tolist(),
            "integrate": t.integrate_ms.tolist(), "raycast": t.raycast_ms.tolist(),
        },
    }


def save_result(result: BaselineResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``traj.txt`` (TUM format), ``mesh.ply`` (binary, vertex colours) and ``timings.json``.

    Returns:
        ``{"trajectory": ..., "mesh": ..., "timings": ...}`` paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"trajectory": write_tum_trajectory(out / "traj.txt", result.trajectory)}
    mesh_path = out / "mesh.ply"
    mesh_path.write_bytes(trimesh.exchange.ply.export_ply(result.mesh, encoding="binary"))
    paths["mesh"] = mesh_path
    timings_path = out / "timings.json"
    timings_path.write_text(json.dumps(timings_summary(result), indent=2) + "\n")
    paths["timings"] = timings_path
    return paths
