"""The engine's front door: Vox-Fusion SLAM over a stream of frames (paper §4).

:class:`SlamSystem` owns a :class:`~.tracking.Tracker` and a :class:`~.mapping.Mapper` and runs them in
one of two modes (``VoxFusionConfig.mode``):

* ``offline`` - :meth:`SlamSystem.process` tracks a frame against the current map snapshot and then
  maps it, on the caller's thread. Deterministic: a fixed seed reproduces the run exactly on CPU.
* ``realtime`` - :meth:`SlamSystem.submit` hands frames to a **tracking worker** thread, which always
  takes the newest frame (older untracked ones are dropped and counted) and passes tracked frames to a
  **mapping worker** thread. The mapper fuses every tracked frame (allocation + keyframe test), runs
  its optimisation round on the newest one, and then publishes a map snapshot that the tracker picks up
  by a reference swap (index tables shared, embeddings and decoder copied once per round; see
  :meth:`~.map.VoxelMap.snapshot`). The tracker never waits for mapping except for the very first
  frame, which initialises the map. On CUDA each worker runs on its own stream; on a CPU torch's intra-op
  threads are halved while they run, so the two workers do not oversubscribe the cores (``realtime_cpu_threads``).

Poses are camera-to-world ``[4, 4]`` float64, OpenCV axes, metres. Keyframe poses refined by mapping
flow back into the trajectory; other frames follow their reference keyframe (the newest keyframe when
they were tracked) rigidly.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import trimesh

from ..cpu import usable_cpu_count
from ..datasets.frame import RGBDFrame
from ..errors import EngineFailedError, MapNotReadyError, ValidationError
from ..frame_checks import MIN_INIT_VALID_PIXELS, intrinsics_problem, usable_pose
from ..framedata import FrameData, frame_to_device
from ..geometry import invert_pose, nearest_rigid, scale_motion
from ..host_memory import retain_freed_memory
from ..lie import so3_exp
from ..map import VoxelMap
from ..map.export import voxels_npz_bytes, voxels_ply_bytes
from ..map.field import SDFDecoder
from ..mesh import extract_map_mesh
from ..mesh.mesh_frame import WorldAxes, camera_up_forward
from ..optim import preload as preload_optimizer
from ..precompiled import preload as preload_precompiled
from ..render.graphs import OcclusionGraphs
from ..render.volume import RenderConfig, RenderedImage, render_depth_image
from ..trajectory import Trajectory
from .mapping import Keyframe, Mapper, MappingStep, keyframe_color_views, make_mapper, publish_keyframe_poses
from .presets import VoxFusionConfig, resolve_device
from .tracking import COST_RATIO_MIN_HISTORY, Tracker, TrackResult, device_prior_applies, predict_pose
from .tracking_sdf import PRECOMPILED_LINEARIZE

__all__ = ["FrameRecord", "TrackingState", "cost_ratio", "SlamStats", "MapSnapshot", "SlamSystem",
           "realtime_thread_count"]

log = logging.getLogger("voxfusion.slam")

TrackingState = Literal["normal", "limited", "lost"]
"""A frame's :attr:`FrameRecord.tracking_state` (ARKit's ``ARCamera.TrackingState`` has the same three)."""


def cost_ratio(cost: float, recent_costs: Sequence[float]) -> float | None:
    """``cost`` over the median of ``recent_costs`` (the tracked frames before it, at most ``tracking.retry_window``);
    None with fewer than :data:`.tracking.COST_RATIO_MIN_HISTORY` of them, a median that is not positive or a cost
    that is not finite."""
    if len(recent_costs) < COST_RATIO_MIN_HISTORY:
        return None
    median = float(np.median(recent_costs))
    return cost / median if median > 0 and np.isfinite(cost) else None


RETRY_MIN_GAIN = 0.5
"""A retry after a gap (``tracking.retry_cost_factor``) replaces a first result that was not lost only when its cost
is below this fraction of the first's: the wrong starts it recovers from cost 5-10 times a correct pose."""
FIRST_MOTION_MIN_GAIN = 0.75
"""The first-motion search (``tracking.first_motion_max_deg``) replaces the first result by one that costs under this
times its cost. Not :data:`RETRY_MIN_GAIN`: the first result's start (no motion) is no better a guess than a turned
one, so the lower cost wins once it is beyond the noise between two tracks of one frame (its points are drawn
afresh: the synthetic room's frame 1 tracked 8 times from its true pose cost within +-5 %, max / min 1.10-1.11).
A wrong first result there cost ~2x the right one (fast rotation seed 8 at 160x120: 3.6-3.9 against 1.87-2.0)."""


def _turned(axis_angles_deg: list[tuple[float, float, float]]) -> np.ndarray:
    """``[T, 4, 4]`` float64 rotations about a camera's own centre (no translation), to right-multiply a camera pose
    with: one per ``(x, y, z)`` axis-angle vector in degrees (camera axes: a positive y turns the optical axis
    towards +x, a pan; x tilts)."""
    turns = np.tile(np.eye(4), (len(axis_angles_deg), 1, 1))
    turns[:, :3, :3] = so3_exp(torch.tensor(np.radians(axis_angles_deg), dtype=torch.float64)).numpy()
    return turns


def realtime_thread_count(setting: int | None, current: int, usable_cores: int) -> int:
    """Torch intra-op threads for a realtime session's two workers on a CPU (``realtime_cpu_threads``):
    ``setting`` when > 0, ``current`` (torch's setting) when 0, and when None half the usable cores but
    never more than ``current`` (at least one)."""
    if setting is None:
        return max(1, min(current, usable_cores // 2))
    return setting if setting > 0 else current


@dataclass
class FrameRecord:
    """One tracked frame of the trajectory.

    ``T_tracked`` is the pose tracking produced (or the prior, when lost). ``ref_keyframe`` and
    ``T_ref_frame`` (``T_keyframe^-1 @ T_tracked``) let the frame follow its keyframe's refinements, and
    ``next_keyframe`` (the keyframe made after it, once there is one) the next keyframe's too
    (:meth:`current_pose`).
    """

    index: int
    timestamp_s: float
    T_tracked: np.ndarray
    lost: bool = False
    is_keyframe: bool = False
    keyframe: Keyframe | None = None
    ref_keyframe: Keyframe | None = None
    T_ref_frame: np.ndarray | None = None
    next_keyframe: Keyframe | None = None
    tracking: TrackResult | None = None
    mapping: MappingStep | None = None
    received_at: float = 0.0
    tracked_at: float = 0.0
    data: FrameData | None = dataclasses.field(default=None, repr=False)
    """The frame's observations while it waits for the mapper (released once mapped)."""
    T_device: np.ndarray | None = dataclasses.field(default=None, repr=False)
    """The frame's device pose (ARKit), when it carries a usable one: the motion prior of the next frames."""
    cost_ratio: float | None = None
    """The frame's tracking cost over the median cost of the tracked frames before it (:func:`cost_ratio`); None for
    the first frames, frames not tracked and lost ones."""
    limited: bool = False
    """Tracked, but its cost jumped (``cost_ratio`` over ``tracking.limited_cost_factor``): the pose may be wrong
    (:attr:`tracking_state`)."""

    @property
    def tracking_state(self) -> TrackingState:
        """``lost`` (not tracked: the pose is the motion model's guess, the frame is not fused), ``limited`` (tracked,
        but its cost jumped against the frames before it: a start beyond the solver's reach, or a view turning into
        space the map has not seen, which also costs more; still fused) or ``normal``."""
        return "lost" if self.lost else "limited" if self.limited else "normal"

    def current_pose(self) -> np.ndarray:
        """Pose ``[4, 4]`` with the newest keyframe refinements applied.

        A keyframe's is its refined pose. A frame between two keyframes gets both keyframes' corrections
        (world-frame transforms, refined pose times the pose the frame was tracked against), blended along
        the geodesic by time: the earlier keyframe's at the earlier keyframe, the later one's at the later
        keyframe. With the earlier keyframe's correction alone, every frame of a segment moved with that one
        keyframe and the trajectory jumped at the next keyframe (by ~3-4 mm on the synthetic room, against ~1
        mm between other frames); blended, ATE on the synthetic room (seeds 0 / 1 / 2) 0.17 / 0.31 / 0.23 ->
        0.15 / 0.27 / 0.19 cm, under fast rotation 0.42 / 0.44 / 0.47 -> 0.30 / 0.35 / 0.37, 7-Scenes 0-499
        3.89 -> 3.85, TUM fr1 desk (seed 0) 0.40 -> 0.32 (the same tracked poses, only reported differently).
        A frame after the newest keyframe follows that keyframe alone."""
        if self.keyframe is not None:
            return nearest_rigid(self.keyframe.published_pose())
        if self.ref_keyframe is None or self.T_ref_frame is None:
            return self.T_tracked
        T = self.ref_keyframe.published_pose() @ self.T_ref_frame
        nxt = self.next_keyframe
        if nxt is None:
            return nearest_rigid(T)
        t0, t1 = self.ref_keyframe.data.timestamp_s, nxt.data.timestamp_s
        a = min(max((self.timestamp_s - t0) / (t1 - t0), 0.0), 1.0) if t1 > t0 else 1.0
        C_ref = T @ invert_pose(self.T_tracked)
        C_next = nxt.published_pose() @ invert_pose(nxt.T_base_host)
        return nearest_rigid(C_ref @ scale_motion(invert_pose(C_ref) @ C_next, a) @ self.T_tracked)


@dataclass(frozen=True)
class SlamStats:
    """Counters of a run. Latency is from :meth:`SlamSystem.submit`/``process`` to a tracked pose."""

    frames_received: int
    frames_tracked: int
    frames_mapped: int
    frames_dropped: int
    frames_lost: int
    keyframes: int
    voxels: int
    fps: float
    latency_ms: float
    map_version: int
    frames_retried: int = 0
    """Frames tracked again from other start poses after a gap (``tracking.retry_cost_factor``), and the first frame
    after the map's first where the search over turned starts replaced its result
    (``tracking.first_motion_max_deg``)."""
    frames_relocalised: int = 0
    """Of those, the frames placed from a keyframe's pose (``tracking.retry_keyframes``)."""
    frames_limited: int = 0
    """Frames tracked with a cost jump (:attr:`FrameRecord.tracking_state` ``limited``; not counted as lost)."""


@dataclass(frozen=True)
class MapSnapshot:
    """A frozen map for readers on other threads: voxels (shared index, copied embeddings) + decoder, and the
    map's verbs (render, mesh, export). The one place a map is rendered or meshed: live sessions, finished
    ones (:meth:`load`) and offline runs all go through it."""

    voxels: VoxelMap
    decoder: SDFDecoder
    version: int
    keyframes: tuple[Keyframe, ...] = ()
    """The keyframes when the snapshot was taken (their images colour meshes; their published poses are read
    when a mesh is made, so building a snapshot costs no pose evaluation)."""

    @classmethod
    def of(cls, mapper: Mapper) -> MapSnapshot:
        """The mapper's map as it is now, without copying (only for a mapper no thread is optimising)."""
        return cls(mapper.voxels, mapper.decoder, int(mapper.version), tuple(mapper.keyframes))

    @classmethod
    def load(cls, path: str | Path, device: torch.device | str = "cpu") -> tuple[MapSnapshot, VoxFusionConfig]:
        """The map of a checkpoint (:func:`.checkpoint.save_checkpoint`) and its configuration; checkpoints
        keep no keyframe images, so meshes of a loaded map take their colours from the colour head."""
        from ..checkpoint import load_checkpoint

        ckpt = load_checkpoint(path, device)
        return cls.of(ckpt.mapper), ckpt.config

    def save(self, path: str | Path, config: VoxFusionConfig, trajectory: Trajectory | None = None) -> Path:
        """Write this map (voxels, decoder, keyframe poses) with ``config`` and ``trajectory`` as an atomic
        checkpoint (:func:`.checkpoint.save_checkpoint`); any thread may save a snapshot."""
        from ..checkpoint import save_checkpoint

        return save_checkpoint(path, self, config, trajectory)

    def render(self, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
               config: RenderConfig, with_color: bool = True) -> RenderedImage:
        """Depth (and colour) at a camera: ``K`` ``[3, 3]``, ``T_world_cam`` ``[4, 4]`` camera-to-world (OpenCV
        axes, metres), an image of ``width`` x ``height`` pixels (:func:`.render.render_depth_image`);
        ``with_color=False``: depth alone (AR occlusion), without the colour head's work."""
        return render_depth_image(self.voxels, self.decoder, K, T_world_cam, width, height, config,
                                  with_color=with_color)

    def mesh(self, mesh_res: int, support: bool = True, colors: str = "images") -> trimesh.Trimesh:
        """Triangle mesh of the zero level set at ``mesh_res`` samples per voxel edge where observations
        support it (``support``), coloured from the keyframe images (``colors="images"``, when the snapshot has
        keyframes with colour) or by the colour head (:func:`.mesh.extract_map_mesh`)."""
        views = keyframe_color_views(self.keyframes) if colors == "images" else None
        return extract_map_mesh(self.voxels, self.decoder, mesh_res, support, color_views=views)

    def export(self, fmt: str) -> bytes:
        """The voxels as ``npz`` (codes, embeddings and decoder: :func:`~.map.export.voxels_npz_bytes`) or as
        a ``ply`` point cloud of voxel centres."""
        if fmt == "npz":
            return voxels_npz_bytes(self.voxels, self.decoder)
        if fmt == "ply":
            return voxels_ply_bytes(self.voxels)
        raise ValidationError("format", f"unknown voxel format {fmt!r}; use npz or ply")


class SlamSystem:
    """Vox-Fusion SLAM over a stream of :class:`RGBDFrame` (see the module docstring).

    Args:
        config: the run's configuration (``config.mode`` picks offline or realtime).
        use_color: train the colour head; None decides from the first frame (depth-only -> False).
        on_pose: called with every new :class:`FrameRecord` right after tracking (from the tracking
            thread in realtime mode); keep it fast.
    """

    def __init__(self, config: VoxFusionConfig, use_color: bool | None = None,
                 on_pose: Callable[[FrameRecord], None] | None = None) -> None:
        self.config = config
        self.device = resolve_device(config.device)
        preload_optimizer()  # the map and its optimisers are built with the first frame
        if config.tracking.method == "sdf" and config.tracking.precompiled and self.device.type == "cpu":
            preload_precompiled()  # Inductor's loading machinery: ~2 s on a 2-core CPU, once per process
            PRECOMPILED_LINEARIZE.preload_artifacts()  # the tracker's artifacts: ~0.5 s, before the first frame
        if self.device.type == "cpu":
            retain_freed_memory()  # per-iteration temporaries reuse heap pages (host_memory)
        self._use_color = use_color
        self.on_pose = on_pose
        self.mapper: Mapper | None = None
        self.tracker: Tracker | None = None
        self._world: str = "first_camera"  # what the world frame is, set with the first pose (world_axes)
        self._gravity_y_up = False  # the world is a device's (ARKit) world, +y up
        self.records: list[FrameRecord] = []
        self._snapshot: MapSnapshot | None = None
        self._mesh_cache: dict[tuple[int, int], trimesh.Trimesh] = {}
        self._render_graphs: OcclusionGraphs | None = None
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._pending: deque[tuple[RGBDFrame, float]] = deque()
        self._to_map: deque[FrameRecord] = deque()
        self._received = self._dropped = self._mapped = 0
        self._tracking_busy = self._mapping_busy = False
        self._closing = False
        self._threads: list[threading.Thread] = []
        self.error: BaseException | None = None
        self._t_start: float | None = None
        self._latencies: deque[float] = deque(maxlen=100)
        self._streams: dict[str, torch.cuda.Stream] = {}
        self._good_tail: deque[FrameRecord] = deque(maxlen=2)  # the last two frames not lost, for priors
        self._recent_costs: deque[float] = deque(maxlen=config.tracking.retry_window)  # tracked frames' costs
        # seconds between consecutive tracked frames (none lost between them), the yardstick of a late frame
        self._recent_intervals: deque[float] = deque(maxlen=config.tracking.retry_window)
        self._retried_since_good = False  # a retry was made since the last tracked frame (one per gap)
        self.retried: list[int] = []
        """Frame indices that were tracked again from other start poses after a gap (``tracking.retry_cost_factor``;
        every attempt, whether or not a retry's result was kept), and the first frame after the map's first where the
        search over turned starts replaced its result (``tracking.first_motion_max_deg``; that search runs in every
        session, and is counted only where it changed the pose)."""
        self.relocalised: list[int] = []
        """Frame indices the retry placed from a keyframe's pose (``tracking.retry_keyframes``), a subset of
        ``retried``."""
        self._first_good: FrameRecord | None = None  # the frame the map started with (world_axes)
        self._threads_before: tuple[int, int] | None = None  # (torch's threads, the workers') while they run

    # ------------------------------------------------------------------ shared helpers
    def _init_engine(self, frame: RGBDFrame) -> None:
        use_color = self._use_color if self._use_color is not None else frame.color is not None
        self._use_color = use_color
        self.mapper = make_mapper(self.config, has_color=use_color, device=self.device)
        self.tracker = Tracker(self.config.tracking, self.config.render, use_color, seed=self.config.seed)

    def _to_device(self, frame: RGBDFrame) -> FrameData:
        m = self.config.mapping
        return frame_to_device(frame, self.device, m.min_depth_m, m.max_depth_m, m.min_confidence,
                               use_color=bool(self._use_color), depth_filter=m.depth_filter)

    def _first_pose(self, frame: RGBDFrame) -> np.ndarray:
        choice = self.config.first_pose
        if choice == "reference" and frame.T_world_cam is not None:
            self._world = "reference"
            # a capture whose reference poses are the device's own (iPhone: ARKit) has a gravity-up world
            self._gravity_y_up = frame.T_world_cam_device is not None and np.allclose(
                frame.T_world_cam, frame.T_world_cam_device, atol=1e-6)
            return frame.T_world_cam.copy()
        if choice in ("reference", "device") and frame.T_world_cam_device is not None:
            self._world, self._gravity_y_up = "device", True
            return frame.T_world_cam_device.copy()
        self._world = "first_camera"
        return np.eye(4)

    def world_axes(self) -> WorldAxes:
        """What the session's world frame is (reference, device or first camera), where "up" is in it and
        the inverse of the first pose: what mesh files and their ``.frame.json`` sidecars need. Up is +y
        in a device world (ARKit's gravity axis, also when the capture's reference poses are the device's),
        else estimated from the cameras' orientations."""
        with self._lock:
            poses = np.stack([r.current_pose() for r in self.records if not r.lost] or
                             [r.current_pose() for r in self.records[:1]] or [np.eye(4)])
            first_rec = self._first_good or (self.records[0] if self.records else None)  # first frames may be lost
            first = first_rec.current_pose() if first_rec is not None else None
        up, forward = camera_up_forward(poses)
        world = self._world
        if self._gravity_y_up:  # ARKit-style world: +y is up
            up = np.array([0.0, 1.0, 0.0])
        return WorldAxes(world, tuple(up.tolist()), tuple(forward.tolist()),
                         None if first is None else invert_pose(first))

    def _prior(self, frame: RGBDFrame) -> tuple[np.ndarray, bool]:
        """Prior pose from the last two frames that were not lost (however long ago), so a run of lost
        frames keeps chaining from the last good pose (with the device's relative motion when frames carry
        one) instead of jumping to an absolute pose. Returns the pose and whether device poses gave it."""
        good = list(self._good_tail)
        if not good:
            return self._first_pose(frame), False
        prev = good[-1]
        prev2 = good[-2] if len(good) > 1 else None
        dev_prev = prev.T_device
        dev_cur = frame.T_world_cam_device
        ratio = 1.0
        if prev2 is not None and prev.timestamp_s > prev2.timestamp_s:
            ratio = (frame.timestamp_s - prev.timestamp_s) / (prev.timestamp_s - prev2.timestamp_s)
        T = predict_pose(prev.current_pose(), None if prev2 is None else prev2.current_pose(),
                         self.config.tracking, dev_prev, dev_cur, dt_ratio=ratio)
        return T, device_prior_applies(self.config.tracking, dev_prev, dev_cur)

    def _publish(self) -> None:
        """Swap in a new frozen snapshot of the map for the tracker and for readers."""
        m = self.mapper
        if m is None:
            return
        stream = self._streams.get("mapping")
        voxels = m.voxels.snapshot()
        decoder = m.decoder.frozen_copy()
        publish_keyframe_poses(m.keyframes)  # other threads read keyframe poses from these copies only
        if stream is not None:
            stream.synchronize()
        snap = MapSnapshot(voxels, decoder, m.version, tuple(m.keyframes))
        with self._lock:
            self._snapshot = snap
        if self.tracker is not None:
            self.tracker.set_map(snap.voxels, snap.decoder)

    def _track(self, frame: RGBDFrame, received_at: float) -> FrameRecord:
        """Track one frame (or place the first one) and record it; ``record.data`` holds its tensors.

        A frame the engine cannot use is recorded as lost and skipped, never an error: implausible
        intrinsics (:func:`.frame_checks.intrinsics_problem`), or, before the map exists, fewer than
        :data:`.frame_checks.MIN_INIT_VALID_PIXELS` valid depth pixels (the map starts with the first usable
        frame). Reference / device poses out of reach (:func:`.frame_checks.pose_problem`) are ignored."""
        T_ref, T_dev = usable_pose(frame.T_world_cam), usable_pose(frame.T_world_cam_device)
        if T_ref is not frame.T_world_cam or T_dev is not frame.T_world_cam_device:  # rare: copy only then
            frame = frame.with_(T_world_cam=T_ref, T_world_cam_device=T_dev)
        if self.mapper is None:
            self._init_engine(frame)
        data = self._to_device(frame)
        unusable = intrinsics_problem(float(frame.K[0, 0]), float(frame.K[1, 1]), frame.width, frame.height)
        if unusable is None and not self._good_tail and data.n_valid < MIN_INIT_VALID_PIXELS:
            unusable = f"{data.n_valid} valid depth pixels, fewer than the {MIN_INIT_VALID_PIXELS} the map starts with"
        if unusable is not None:
            log.info("frame %d skipped (lost): %s", frame.index, unusable)
            T = self._prior(frame)[0] if self._good_tail else self._first_pose(frame)
            rec = FrameRecord(frame.index, frame.timestamp_s, T, lost=True, received_at=received_at)
        elif not self._good_tail:
            T = self._first_pose(frame)
            rec = FrameRecord(frame.index, frame.timestamp_s, T, received_at=received_at)
        else:
            prior, prior_from_device = self._prior(frame)
            if data.n_valid == 0:
                res = None
                rec = FrameRecord(frame.index, frame.timestamp_s, prior, lost=True, received_at=received_at)
            else:
                with self._tracking_threads():
                    res = self.tracker.track(data, prior, prior_from_device)
                    if not prior_from_device and self._needs_retry(frame, res):
                        res = self._retry_from_other_starts(data, res, prior)
                    elif not prior_from_device and self._needs_first_motion_search():
                        res = self._search_first_motion(data, res)
                ratio = None if res.lost else cost_ratio(res.loss, self._recent_costs)
                if not res.lost:
                    self._note_tracked(frame, res)
                factor = self.config.tracking.limited_cost_factor
                rec = FrameRecord(frame.index, frame.timestamp_s, res.T_world_cam, lost=res.lost, tracking=res,
                                  received_at=received_at, cost_ratio=ratio,
                                  limited=factor > 0 and ratio is not None and ratio > factor)
                if rec.limited:
                    log.info("frame %d tracked with limited confidence: cost %.3g, %.1f times the recent median",
                             frame.index, res.loss, ratio)
        rec.data = None if rec.lost else data
        rec.T_device = frame.T_world_cam_device
        kfs = self.mapper.keyframes
        if kfs and not rec.lost:
            ref = kfs[-1]
            rec.ref_keyframe = ref
            rec.T_ref_frame = invert_pose(ref.published_pose()) @ rec.T_tracked
        rec.tracked_at = time.perf_counter()
        self._latencies.append((rec.tracked_at - received_at) * 1e3)
        with self._lock:
            self.records.append(rec)
        if not rec.lost:
            self._good_tail.append(rec)
            self._first_good = self._first_good or rec
            self.tracker.remember(data, rec.T_tracked)
        if self.on_pose is not None:
            self.on_pose(rec)
        return rec

    def _note_tracked(self, frame: RGBDFrame, res: TrackResult) -> None:
        """Remember a tracked (not lost) frame's cost, and the time since the previous tracked frame when no frame
        was lost between them (what :meth:`_needs_retry` compares with)."""
        self._recent_costs.append(res.loss)
        good = self._good_tail
        if good and not (self.records and self.records[-1].lost) and frame.timestamp_s > good[-1].timestamp_s:
            self._recent_intervals.append(frame.timestamp_s - good[-1].timestamp_s)
        self._retried_since_good = False

    def _needs_retry(self, frame: RGBDFrame, res: TrackResult) -> bool:
        """Whether a tracked frame looks like a wrong start after a gap (``tracking.retry_cost_factor``): it follows
        lost frames, or comes ``retry_gap`` times the usual interval between tracked frames (their median) after the
        last tracked one; it is lost or costs more than ``retry_cost_factor`` times the recent tracked frames'
        median; and no retry was made since the last tracked frame (one per gap: a long lost streak, e.g. a view of
        what was never mapped, is not searched again at every frame)."""
        cfg = self.config.tracking
        if cfg.retry_cost_factor <= 0 or not self._good_tail or self._retried_since_good:
            return False
        after_lost = bool(self.records) and self.records[-1].lost
        usual = float(np.median(self._recent_intervals)) if self._recent_intervals else 0.0
        late = usual > 0 and frame.timestamp_s - self._good_tail[-1].timestamp_s >= cfg.retry_gap * usual
        return (after_lost or late) and (res.lost or not self._cost_is_usual(res.loss))

    def _cost_is_usual(self, cost: float) -> bool:
        """Whether ``cost`` is within ``retry_cost_factor`` times the recent tracked frames' median (True while fewer
        than ``retry_window`` frames were tracked)."""
        costs = self._recent_costs
        return len(costs) < costs.maxlen or cost <= self.config.tracking.retry_cost_factor * float(np.median(costs))

    def _needs_first_motion_search(self) -> bool:
        """Whether the frame being tracked is the first after the map's first frame (no motion to extrapolate yet;
        ``tracking.first_motion_max_deg``; a grid narrower than one step has no turned start to try)."""
        cfg = self.config.tracking
        return cfg.first_motion_max_deg >= cfg.first_motion_step_deg and len(self._good_tail) == 1

    def _search_first_motion(self, data: FrameData, first: TrackResult) -> TrackResult:
        """Track ``data`` again from the last tracked pose turned by a grid of pans and tilts (``tracking.
        first_motion_step_deg`` up to ``first_motion_max_deg``), from the two turned starts where its depth fits the
        map best (:meth:`.tracking.Tracker.pose_costs`; ``first`` started from no turn); a result replaces
        ``first`` when it is not lost and costs under :data:`FIRST_MOTION_MIN_GAIN` times ``first``'s (any cost,
        where ``first`` was lost), the lowest winning. Where ``first`` stands, the tracker's random stream is put
        back as the search found it, so that the frames after it sample the points they sample without the
        search."""
        t0 = time.perf_counter()
        cfg = self.config.tracking
        stream = self.tracker.generator.get_state()
        n = int(np.floor(cfg.first_motion_max_deg / cfg.first_motion_step_deg + 1e-9))
        angles = np.arange(-n, n + 1) * cfg.first_motion_step_deg
        starts = self._good_tail[-1].current_pose() @ _turned([(tilt, pan, 0.0) for tilt in angles for pan in angles])
        order = np.argsort(self.tracker.pose_costs(data, starts, n_points=256), kind="stable")
        no_turn = len(starts) // 2  # the grid's centre
        tries = [int(k) for k in order if k != no_turn][:2]
        best, iterations = first, first.iterations
        for k in tries:
            again = self.tracker.track(data, starts[k], False)
            iterations += again.iterations
            clearly_lower = first.lost or again.loss < FIRST_MOTION_MIN_GAIN * first.loss
            if not again.lost and clearly_lower and (best is first or again.loss < best.loss):
                best = again
        if best is not first:
            self.retried.append(first.frame_index)
        else:
            self.tracker.generator.set_state(stream)
        log.info("frame %d (the first after the map's first frame) tracked again from %d of %d turned starts: cost "
                 "%.3g%s -> %s", first.frame_index, len(tries), len(starts), first.loss,
                 " (lost)" if first.lost else "", "kept the first" if best is first else f"{best.loss:.3g}")
        return dataclasses.replace(best, iterations=iterations,
                                   time_ms=first.time_ms + (time.perf_counter() - t0) * 1e3)

    def _retry_turns(self) -> np.ndarray:
        """The ``[T, 3, 3]`` rotations of :meth:`_turn_poses`."""
        return self._turn_poses()[:, :3, :3]

    def _turn_poses(self) -> np.ndarray:
        """``[T, 4, 4]`` rotations about the camera's own centre to try after a gap (no translation; to right-multiply
        a camera pose with), nearest first: pan (about the camera's y axis; positive turns the optical axis towards
        +x) by 0, +-step, ... +-max degrees (``tracking.retry_step_deg``, ``retry_max_deg``), then tilt (x axis) by
        +-step."""
        cfg = self.config.tracking
        step = cfg.retry_step_deg
        n = int(np.floor(cfg.retry_max_deg / step + 1e-9))
        pans = [0.0] + [sign * k * step for k in range(1, n + 1) for sign in (1.0, -1.0)]
        return _turned([(0.0, p, 0.0) for p in pans] + [(step, 0.0, 0.0), (-step, 0.0, 0.0)])

    def _retry_starts(self, prior: np.ndarray) -> np.ndarray:
        """``[K, 4, 4]`` start poses to try after a gap: the last tracked pose turned by each of :meth:`_retry_turns`
        and moved, in its camera's frame, by the translation the motion prior (``prior``) extrapolated or by an
        offset of a horizontal grid (camera x and z, every ``retry_step_m`` up to ``retry_reach_m`` either way)."""
        cfg = self.config.tracking
        last = self._good_tail[-1].current_pose()
        t_prior = invert_pose(last)[:3, :3] @ (prior[:3, 3] - last[:3, 3])  # the prior's translation, camera frame
        n = int(round(cfg.retry_reach_m / cfg.retry_step_m))
        grid = np.arange(-n, n + 1) * cfg.retry_step_m
        moves = np.array([t_prior] + [[x, 0.0, z] for x in grid for z in grid])  # [M, 3]
        starts = np.repeat(self._turn_poses()[None], len(moves), axis=0)  # [M, T, 4, 4]
        starts[:, :, :3, 3] = moves[:, None, :]
        return last @ starts.reshape(-1, 4, 4)

    def _keyframe_starts(self) -> tuple[np.ndarray, list[Keyframe], np.ndarray]:
        """Start poses for relocalisation (``tracking.retry_keyframes``): ``(starts [K T, 4, 4], keyframes [K],
        poses [K, 4, 4])``, the published map's keyframes (at most that many, spread evenly over them), their
        published poses read once, and each pose turned by :meth:`_retry_turns` (start ``k T + j``: keyframe ``k``,
        turn ``j``); none when off or before a map exists."""
        n = self.config.tracking.retry_keyframes
        snap = self.snapshot
        if n == 0 or snap is None or not snap.keyframes:
            return np.zeros((0, 4, 4)), [], np.zeros((0, 4, 4))
        kfs = list(snap.keyframes)
        if len(kfs) > n:
            kfs = [kfs[i] for i in np.linspace(0, len(kfs) - 1, n).round().astype(int)]
        poses = np.stack([kf.published_pose() for kf in kfs])
        return (poses[:, None] @ self._turn_poses()[None]).reshape(-1, 4, 4), kfs, poses

    def _retry_from_other_starts(self, data: FrameData, first: TrackResult, prior: np.ndarray) -> TrackResult:
        """Track ``data`` again from the :meth:`_retry_starts` where its depth fits the map best
        (:meth:`.tracking.Tracker.pose_costs`), best first, until one costs as usual (``tracking.retry_cost_factor``).
        A retry replaces the first result only when it is not lost and, if the first was lost, costs as usual (a
        lost frame is not fused, a wrong pose would be), else costs under :data:`RETRY_MIN_GAIN` times the first
        (among poses that are all wrong, the lowest cost is no better a guess than the motion prior's); of those,
        the lowest cost wins. Otherwise the first result stands, its pose the motion prior's.

        Where no start around the last pose gives a result that costs as usual, relocalisation: the
        :meth:`_keyframe_starts` are ranked the same way, the best turn of each keyframe kept, and the best
        ``retry_tracks`` keyframes tracked from there against their own depth (the frame-to-frame terms'
        reference; the last tracked frame may be far away). A result from there must cost as usual whatever the
        first was: it may be anywhere in the map. ``relocalised`` lists the frames placed this way."""
        t0 = time.perf_counter()
        self.retried.append(first.frame_index)
        self._retried_since_good = True
        cfg = self.config.tracking
        starts = self._retry_starts(prior)
        order = np.argsort(self.tracker.pose_costs(data, starts), kind="stable")
        best, tries, iterations = first, 0, first.iterations
        for k in order[:cfg.retry_tracks]:
            again = self.tracker.track(data, starts[k], False)
            tries += 1
            iterations += again.iterations
            acceptable = not again.lost and (self._cost_is_usual(again.loss) if first.lost
                                             else again.loss < RETRY_MIN_GAIN * first.loss)
            if acceptable and (best is first or again.loss < best.loss):
                best = again
            if best is not first and self._cost_is_usual(best.loss):
                break
        placed_at = None
        if not (best is not first and self._cost_is_usual(best.loss)):
            far, keyframes, kf_poses = self._keyframe_starts()
            if len(keyframes):
                n_turns = len(far) // len(keyframes)
                costs = self.tracker.pose_costs(data, far).reshape(len(keyframes), n_turns)
                turn = costs.argmin(1)  # each keyframe's best turn, then the best keyframes
                for kk in np.argsort(costs.min(1), kind="stable")[:cfg.retry_tracks]:
                    with self.tracker.referenced_to(keyframes[kk].data, kf_poses[kk]):
                        again = self.tracker.track(data, far[kk * n_turns + turn[kk]], False)
                    tries += 1
                    iterations += again.iterations
                    if not again.lost and self._cost_is_usual(again.loss):  # below any earlier result: none was usual
                        best, placed_at = again, keyframes[kk]
                        break
                starts = np.concatenate([starts, far])
        if placed_at is not None:
            self.relocalised.append(first.frame_index)
        log.info("frame %d tracked again from %d of %d other starts: cost %.3g%s -> %s", first.frame_index,
                 tries, len(starts), first.loss, " (lost)" if first.lost else "",
                 "kept the first" if best is first else f"{best.loss:.3g}" + (
                     "" if placed_at is None else f", relocalised at the keyframe of frame {placed_at.data.index}"))
        return dataclasses.replace(best, iterations=iterations,
                                   time_ms=first.time_ms + (time.perf_counter() - t0) * 1e3)

    @contextmanager
    def _tracking_threads(self) -> Iterator[None]:
        """Offline mode on the CPU: run tracking with ``tracking.cpu_threads`` intra-op threads (its operations
        are small, and on a 2-core CPU two threads were slower than one), mapping with torch's setting. The
        thread count is process-wide, so realtime mode (tracking and mapping at once) leaves it alone."""
        n = self.config.tracking.cpu_threads
        if n <= 0 or self.device.type != "cpu" or self.config.mode != "offline" or torch.get_num_threads() == n:
            yield
            return
        before = torch.get_num_threads()
        torch.set_num_threads(n)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    def _map(self, recs: list[FrameRecord], optimize: bool = True) -> None:
        """Fuse the records' frames in order (:meth:`.mapping.Mapper.integrate_batch`: one pass for all; only the
        last is optimised, when ``optimize``) and link each new keyframe to the records it now follows."""
        steps = self.mapper.integrate_batch([(rec.data, rec.T_tracked) for rec in recs], optimize=optimize)
        kfs = self.mapper.keyframes
        k = len(kfs) - sum(step.is_keyframe for step in steps)  # index of the batch's first new keyframe
        for rec, step in zip(recs, steps, strict=True):
            rec.data = None
            rec.mapping = step
            with self._lock:
                if step.is_keyframe:
                    rec.keyframe = kfs[k]
                    rec.ref_keyframe, rec.T_ref_frame = None, None
                    if k > 0:
                        self._link_next_keyframe(kfs[k - 1], kfs[k])
                    k += 1
                self._mapped += 1

    def _link_next_keyframe(self, previous: Keyframe, new: Keyframe) -> None:
        """The frames that follow ``previous`` and have no later keyframe yet now have ``new`` (caller holds the
        lock; the scan stops at ``previous``' own record, so it covers one keyframe interval)."""
        for r in reversed(self.records):
            if r.keyframe is previous:
                break
            if r.ref_keyframe is previous and r.next_keyframe is None:
                r.next_keyframe = new

    # ------------------------------------------------------------------ offline mode
    def process(self, frame: RGBDFrame) -> FrameRecord:
        """Offline mode: track ``frame`` and map it (unless lost) before returning its record."""
        if self.config.mode != "offline":
            raise ValidationError("mode", "process() is for offline mode; use submit() in realtime mode")
        t = time.perf_counter()
        if self._t_start is None:
            self._t_start = t
        with self._lock:
            self._received += 1
        rec = self._track(frame, t)
        if not rec.lost:
            self._map([rec])
            self._publish()
        return rec

    # ------------------------------------------------------------------ realtime mode
    def start(self) -> None:
        """Realtime mode: start the tracking and mapping workers."""
        if self.config.mode != "realtime":
            raise ValidationError("mode", "start() is for realtime mode")
        if self._threads:
            return
        self._set_worker_threads()
        if self.device.type == "cuda":
            self._streams = {"tracking": torch.cuda.Stream(self.device), "mapping": torch.cuda.Stream(self.device)}
        self._threads = [threading.Thread(target=self._worker, args=(name, fn), name=f"voxfusion-{name}",
                                          daemon=True)
                         for name, fn in (("tracking", self._tracking_loop), ("mapping", self._mapping_loop))]
        for th in self._threads:
            th.start()

    def _set_worker_threads(self) -> None:
        """Realtime mode on a CPU: torch's intra-op threads for the workers (``realtime_cpu_threads``, see
        :func:`realtime_thread_count`); :meth:`_restore_threads` puts torch's setting back when they stop."""
        if self.device.type != "cpu":
            return
        before = torch.get_num_threads()
        n = realtime_thread_count(self.config.realtime_cpu_threads, before, usable_cpu_count())
        if n != before:
            torch.set_num_threads(n)
            self._threads_before = (before, n)

    def _restore_threads(self) -> None:
        """Undo :meth:`_set_worker_threads`, unless someone changed torch's setting since."""
        saved, self._threads_before = self._threads_before, None
        if saved is not None and torch.get_num_threads() == saved[1]:
            torch.set_num_threads(saved[0])

    def submit(self, frame: RGBDFrame) -> None:
        """Realtime mode: hand a frame to the tracker (never blocks on tracking or mapping)."""
        self._raise_if_failed()
        if not self._threads:
            self.start()
        with self._cond:
            if self._closing:
                raise ValidationError("frame", "the SLAM system is finishing or closed; no new frames")
            if self._t_start is None:
                self._t_start = time.perf_counter()
            self._received += 1
            self._pending.append((frame, time.perf_counter()))
            self._cond.notify_all()

    @contextmanager
    def _stream(self, name: str) -> Iterator[None]:
        stream = self._streams.get(name)
        if stream is None:
            yield
        else:
            with torch.cuda.stream(stream):
                yield

    def _worker(self, name: str, loop: Callable[[], None]) -> None:
        try:
            with self._stream(name):
                loop()
        except BaseException as e:  # noqa: BLE001 - any worker failure fails the run, with its cause
            with self._cond:
                self.error = e
                self._closing = True
                self._tracking_busy = self._mapping_busy = False
                self._pending.clear()
                self._to_map.clear()
                self._cond.notify_all()

    def _tracking_loop(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not (self._closing and not self._pending):
                    self._cond.wait()
                if not self._pending:
                    return
                frame, received_at = self._pending.pop()  # the newest frame
                self._dropped += len(self._pending)  # older untracked frames are dropped
                self._pending.clear()
                self._tracking_busy = True
            first = not self._good_tail
            rec = self._track(frame, received_at)
            with self._cond:
                if not rec.lost:
                    self._to_map.append(rec)
                self._tracking_busy = False
                self._cond.notify_all()
                if first and not rec.lost:  # the map must exist before the next frame can be tracked
                    while self._snapshot is None and self.error is None:
                        self._cond.wait()

    def _mapping_loop(self) -> None:
        while True:
            with self._cond:
                while not self._to_map and not (self._closing and not self._tracking_busy and not self._pending):
                    self._cond.wait()
                if not self._to_map or self.error is not None:
                    return
                batch = list(self._to_map)
                self._to_map.clear()
                self._mapping_busy = True
            self._map(batch)  # the frames tracked since the last round, fused together; the newest optimised
            self._publish()
            with self._cond:
                self._mapping_busy = False
                self._cond.notify_all()

    def finish(self, timeout_s: float | None = None) -> None:
        """Process what is queued, run the final mapping iterations and publish the final map."""
        if self.config.mode == "realtime" and self._threads:
            with self._cond:
                self._closing = True
                self._cond.notify_all()
            deadline = None if timeout_s is None else time.monotonic() + timeout_s
            for th in self._threads:
                th.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
                if th.is_alive():
                    raise EngineFailedError(f"{th.name} did not finish within {timeout_s} s")
            self._threads = []
            self._restore_threads()
        self._raise_if_failed()
        if self.mapper is not None and self.mapper.keyframes:  # no usable frame yet: no map to finish
            self.mapper.finish()
            self._publish()

    def close(self) -> None:
        """Stop the workers without further work (pending frames are discarded)."""
        with self._cond:
            self._closing = True
            self._dropped += len(self._pending)
            self._pending.clear()
            self._to_map.clear()
            self._cond.notify_all()
        for th in self._threads:
            th.join(timeout=60)
        self._threads = []
        self._restore_threads()

    def _raise_if_failed(self) -> None:
        if self.error is not None:
            raise EngineFailedError(f"SLAM worker failed: {type(self.error).__name__}: {self.error}") from self.error

    # ------------------------------------------------------------------ outputs
    @property
    def snapshot(self) -> MapSnapshot | None:
        """The newest published map (None before the first frame is mapped)."""
        with self._lock:
            return self._snapshot

    def trajectory(self, include_lost: bool = True) -> Trajectory:
        """Every tracked frame's current pose (keyframe refinements applied), in tracking order."""
        with self._lock:
            recs = [r for r in self.records if include_lost or not r.lost]
        if not recs:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([r.timestamp_s for r in recs]), np.stack([r.current_pose() for r in recs]))

    def latest(self) -> FrameRecord | None:
        with self._lock:
            return self.records[-1] if self.records else None

    def stats(self) -> SlamStats:
        with self._lock:
            tracked = len(self.records)
            lost = sum(r.lost for r in self.records)
            elapsed = time.perf_counter() - self._t_start if self._t_start else 0.0
            lat = float(np.mean(self._latencies)) if self._latencies else float("nan")
            return SlamStats(
                frames_received=self._received, frames_tracked=tracked, frames_mapped=self._mapped,
                frames_dropped=self._dropped, frames_lost=lost, frames_limited=sum(r.limited for r in self.records),
                keyframes=len(self.mapper.keyframes) if self.mapper else 0,
                voxels=self.mapper.voxels.n_voxels if self.mapper else 0,
                fps=tracked / elapsed if elapsed > 0 else 0.0, latency_ms=lat,
                map_version=self._snapshot.version if self._snapshot else 0, frames_retried=len(self.retried),
                frames_relocalised=len(self.relocalised))

    def render_depth(self, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
                     with_color: bool = True, snapshot: MapSnapshot | None = None) -> RenderedImage:
        """Depth (and colour) rendered from ``snapshot`` (default: the newest) at a camera pose (AR occlusion;
        :meth:`MapSnapshot.render`, or its CUDA graph with ``render.cuda_graphs``). Pass the snapshot whose version
        you label the image with: mapping may publish a newer one meanwhile."""
        snap = self.snapshot if snapshot is None else snapshot
        if snap is None:
            raise MapNotReadyError("the map is empty: no frame has been mapped yet")
        graphs = self._occlusion_graphs()
        if graphs is not None:
            image = graphs.render(snap.voxels, snap.decoder, K, T_world_cam, width, height, self.config.render,
                                  with_color)
            if image is not None:
                return image
        return snap.render(K, T_world_cam, width, height, self.config.render, with_color=with_color)

    def _occlusion_graphs(self) -> OcclusionGraphs | None:
        """The session's :class:`~.render.graphs.OcclusionGraphs` (``render.cuda_graphs`` on a CUDA device), made on
        first use."""
        if not self.config.render.cuda_graphs or self.device.type != "cuda":
            return None
        with self._lock:
            if self._render_graphs is None:
                self._render_graphs = OcclusionGraphs(self.device)
            return self._render_graphs

    def mesh(self, mesh_res: int | None = None, snapshot: MapSnapshot | None = None) -> trimesh.Trimesh:
        """Mesh of ``snapshot`` (default: the newest) at ``mesh_res`` samples per voxel edge (default
        ``config.mesh_res``; :meth:`VoxFusionConfig.preview_mesh_res` for a cheap preview), cached per map
        version and res. Pass the snapshot whose version you label the mesh with: mapping may publish a
        newer one meanwhile."""
        snap = self.snapshot if snapshot is None else snapshot
        if snap is None:
            raise MapNotReadyError("the map is empty: no frame has been mapped yet")
        res = self.config.mesh_res if mesh_res is None else int(mesh_res)
        key = (snap.version, res)
        cached = self._mesh_cache.get(key)
        if cached is not None:
            return cached

        mesh = snap.mesh(res, self.config.mesh_support, self.config.mesh_colors)
        self._mesh_cache = {k: m for k, m in self._mesh_cache.items() if k[0] == snap.version}
        self._mesh_cache[key] = mesh
        return mesh
