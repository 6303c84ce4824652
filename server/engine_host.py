"""A session's engine behind a handful of verbs: what runs inside a session's worker process
(:mod:`.worker`), or on threads of the API process (``voxfusion serve --session-workers thread``).

The API process appends every accepted frame to the session's recording (durable before it is
acknowledged) and then tells the host how many records exist (:meth:`EngineHost.available`). The host
reads those records straight from the recording's memory-mapped pages (:class:`RecordingReader`: the
frame bytes are never copied between the processes), feeds them to a :class:`SlamSystem`, writes the
periodic checkpoints and, at :meth:`~EngineHost.finish`, the final outputs, and answers the requests that
need the map (status, poses, render, mesh, voxels).

Feeding: the engine runs in the session's mode. An ``offline`` session's engine is in offline mode: each
record is tracked and mapped (:meth:`SlamSystem.process`) before the next is read, so every frame meets the
map of all frames before it, as in ``voxfusion run``, and the same recording gives the same trajectory and
map every time. A ``realtime`` session's engine runs its tracking and mapping workers: records are handed
over at once and its tracker drops stale ones, except the first ``spec.replay`` records (a resume or a
worker restart replays what was recorded), which are handed over only once the previous one is tracked.
Records in ``spec.skip`` (frames an earlier engine failed on) are skipped.

Events sent with ``emit`` (from the host's threads; the API process dispatches them):

=================================  ==========================================================
``("pose", PoseOut)``              a frame was tracked (its pose before keyframe refinements)
``("handed", n)``                  the first ``n`` records have been handed to the engine
``("failed", message, record)``    the engine failed (``record``: the frame it was on, or None)
=================================  ==========================================================
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from voxfusion.core.checkpoint import atomic_write_bytes
from voxfusion.core.config import config_from_dict
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import EngineFailedError, MapNotReadyError
from voxfusion.core.mesh import mesh_bytes
from voxfusion.core.mesh.mesh_frame import sidecar_path
from voxfusion.core.render.volume import RenderedImage
from voxfusion.core.slam import FrameRecord, MapSnapshot, SlamStats, SlamSystem
from voxfusion.core.slam.presets import VoxFusionConfig
from voxfusion.core.trajectory import write_tum_trajectory
from voxfusion.proto import FrameDecodeError, decode_frame
from voxfusion.proto.recording import RECORDING_FILENAME, RecordingReader
from voxfusion.proto.schemas import PoseOut, RenderRequest

from .outputs import MeshDetail, pose_out
from .stored import CHECKPOINT_FILE, MESH_FILE, POSES_FILE, TRAJECTORY_FILE

__all__ = ["HostSpec", "EngineHost", "HOST_VERBS", "Emit"]

log = logging.getLogger("voxfusion.server")

Emit = Callable[[tuple], None]
"""Where a host sends its events (see the module docstring)."""

HOST_VERBS = frozenset({"stats", "poses", "render", "mesh_bytes", "mesh_frame", "voxels_bytes", "finish", "close"})
"""The methods a worker process answers for the API process (:meth:`EngineHost.available` is a notice)."""


@dataclass(frozen=True)
class HostSpec:
    """Everything a host needs, in plain values (it crosses into the worker process).

    Attributes:
        session_id: the session's id (log lines).
        mode: ``realtime`` or ``offline`` (the session's mode, and its engine's: ``config["mode"]`` is set to it).
        config: the engine configuration as a dict (:func:`~voxfusion.core.config.config_to_dict`).
        folder: ``<data_dir>/sessions/<id>``: the recording is read from it, checkpoints written to it.
        replay: the first ``replay`` records are replayed (paced) before live frames.
        skip: record positions never handed to the engine (frames an earlier engine failed on).
        checkpoint_interval_s, checkpoint_keyframes: when the running map is checkpointed.
        torch_threads: intra-op threads of torch in a worker process (0: torch's default).
        shared_process: the host runs on threads of a process that other sessions' engines share
            (``--session-workers thread``): its engine leaves torch's process-wide thread count alone
            (``tracking.cpu_threads`` and ``realtime_cpu_threads`` 0), so sessions never reset each other's.
    """

    session_id: str
    mode: str
    config: dict[str, Any]
    folder: str
    replay: int = 0
    skip: tuple[int, ...] = ()
    checkpoint_interval_s: float = 30.0
    checkpoint_keyframes: int = 10
    torch_threads: int = 0
    shared_process: bool = False


class EngineHost:
    """One session's engine and its feeder (see the module docstring). Thread-safe.

    Args:
        spec: what to run.
        emit: receives the host's events (called from the host's threads; keep it fast).
    """

    def __init__(self, spec: HostSpec, emit: Emit) -> None:
        self.spec = spec
        # the session's mode is the engine's (sessions stored before the engine ran offline say "realtime")
        config = dataclasses.replace(config_from_dict(VoxFusionConfig, spec.config), mode=spec.mode)
        if spec.shared_process:
            config = dataclasses.replace(config, realtime_cpu_threads=0,
                                         tracking=dataclasses.replace(config.tracking, cpu_threads=0))
        self.config: VoxFusionConfig = config
        self.folder = Path(spec.folder)
        self._emit = emit
        self._offline = spec.mode == "offline"
        self._skip = frozenset(spec.skip)
        self._cond = threading.Condition()
        self._available = 0
        self._next = 0  # the next record to hand to the engine
        self._failed_record: int | None = None  # the frame the engine failed on, when that is certain
        self._paced_record: int | None = None  # the record a paced submit is waiting on (the engine's only frame)
        self._submitted = 0
        self._tracked = 0
        self._stop = False
        self._finishing = False
        self._finished = False
        self.error: str | None = None
        self._finish_lock = threading.Lock()
        self._mesh_lock = threading.Lock()
        self._ckpt_time = time.monotonic()
        self._ckpt_version = 0
        self._ckpt_keyframes = 0
        self._reader = RecordingReader(self.folder / RECORDING_FILENAME)
        self.slam = SlamSystem(self.config, on_pose=self._on_pose)
        self._feeder = threading.Thread(target=self._feed, name=f"voxfusion-feeder-{spec.session_id[:8]}",
                                        daemon=True)
        self._keeper = threading.Thread(target=self._housekeeping, name=f"voxfusion-ckpt-{spec.session_id[:8]}",
                                        daemon=True)
        self._feeder.start()
        self._keeper.start()

    # ------------------------------------------------------------------ frames in
    def available(self, count: int) -> None:
        """The recording now holds at least ``count`` records (the first ``count`` may be read)."""
        with self._cond:
            if count > self._available:
                self._available = count
                self._cond.notify_all()

    def _on_pose(self, rec: FrameRecord) -> None:
        try:
            pose: PoseOut | None = pose_out(rec, refined=False)
        except Exception:  # noqa: BLE001 - e.g. a non-finite pose: never let it kill the tracking worker
            log.exception("session %s: frame %d has no valid pose to publish", self.spec.session_id, rec.index)
            pose = None
        with self._cond:
            self._tracked += 1
            self._cond.notify_all()
        if pose is not None:
            self._emit(("pose", pose))

    def _submit(self, frame: RGBDFrame, paced: bool) -> None:
        """Hand ``frame`` to the engine: offline, track and map it before returning; realtime, queue it for the
        tracker and, when ``paced``, wait until it is tracked."""
        if self._offline:
            self.slam.process(frame)
            self._submitted += 1
            return
        self.slam.submit(frame)
        self._submitted += 1
        if not paced:
            return
        target = self._submitted
        with self._cond:
            while self._tracked < target and self.slam.error is None and not self._stop:
                self._cond.wait(0.5)
        if self.slam.error is not None:
            raise EngineFailedError(f"{type(self.slam.error).__name__}: {self.slam.error}")

    def _feed(self) -> None:
        try:
            while True:
                with self._cond:
                    while self._next >= self._available and not self._stop and not self._finishing:
                        self._cond.wait(0.5)
                    if self._stop or (self._next >= self._available and self._finishing):
                        return
                    index = self._next
                message = self._reader.next()
                with self._cond:
                    self._next = index + 1
                self._emit(("handed", index + 1))
                if index in self._skip:
                    log.warning("session %s: record %d is skipped (an earlier engine failed on it)",
                                self.spec.session_id, index)
                    continue
                try:
                    frame = decode_frame(message).frame
                except FrameDecodeError as e:  # recorded before the door refused such frames: skip it
                    log.warning("session %s: skipping recorded frame %d: %s", self.spec.session_id, index, e)
                    continue
                paced = self._offline or index < self.spec.replay
                self._paced_record = index if paced else None
                try:
                    self._submit(frame, paced=paced)
                    self._paced_record = None
                except Exception as e:  # noqa: BLE001 - fails this session only
                    if not (self._offline or isinstance(e, EngineFailedError)):
                        raise
                    # paced, the engine was working on this frame alone: it is the one to leave out on resume;
                    # unpaced (realtime), it may have been an older frame: a resume replays paced and finds it
                    self._fail(e, record=index if paced else None)
                    return
        except Exception as e:  # noqa: BLE001 - any failure fails this session only
            self._fail(e)

    # ------------------------------------------------------------------ health, checkpoints
    def _fail(self, error: BaseException | str, record: int | None = None) -> None:
        """Fail the session once; ``record``: the recording position of the frame the engine failed on, only
        when that is certain (a paced frame), so that a resume can leave it out."""
        cause = self.slam.error
        if isinstance(error, str):
            message = error
        elif cause is not None:
            message = f"{type(cause).__name__}: {cause}"
        else:
            message = f"{type(error).__name__}: {error}"
        with self._cond:
            if self.error is not None:
                return
            self.error = message
            self._failed_record = record
            self._stop = True
            self._cond.notify_all()
        log.error("session %s: engine failed (record %s): %s", self.spec.session_id, record, message)
        self._emit(("failed", message, record))
        threading.Thread(target=self.slam.close, name=f"voxfusion-close-{self.spec.session_id[:8]}",
                         daemon=True).start()

    def _housekeeping(self) -> None:
        while True:
            with self._cond:
                self._cond.wait(0.25)
                if self._stop or self._finishing:
                    return
            if self.slam.error is not None:
                self._fail(EngineFailedError(str(self.slam.error)), record=self._paced_record)
                return
            try:
                self._periodic_checkpoint(time.monotonic())
            except Exception:  # noqa: BLE001 - a failed periodic checkpoint is retried, not fatal
                log.exception("session %s: periodic checkpoint failed", self.spec.session_id)
                self._ckpt_time = time.monotonic()

    def _periodic_checkpoint(self, now: float) -> None:
        snap, mapper = self.slam.snapshot, self.slam.mapper
        if snap is None or mapper is None or snap.version == self._ckpt_version:
            return
        due = now - self._ckpt_time >= self.spec.checkpoint_interval_s
        if due or len(mapper.keyframes) - self._ckpt_keyframes >= self.spec.checkpoint_keyframes:
            self.write_checkpoint(from_snapshot=True)
            self._ckpt_time = now

    def write_checkpoint(self, from_snapshot: bool) -> None:
        """Write ``checkpoint.pt`` and ``poses.json`` atomically.

        ``from_snapshot``: save the newest published snapshot (safe while the workers run); otherwise the
        mapper itself (the workers must be stopped).
        """
        mapper, snap = self.slam.mapper, self.slam.snapshot
        if mapper is None or snap is None:
            return
        keyframes = tuple(mapper.keyframes)
        source = dataclasses.replace(snap, keyframes=keyframes) if from_snapshot else MapSnapshot.of(mapper)
        poses = self.poses()
        source.save(self.folder / CHECKPOINT_FILE, self.config, self.slam.trajectory())
        atomic_write_bytes(self.folder / POSES_FILE, json.dumps([p.model_dump(mode="json") for p in poses]).encode())
        self._ckpt_version = source.version
        self._ckpt_keyframes = len(keyframes)

    # ------------------------------------------------------------------ queries (verbs)
    def stats(self) -> SlamStats:
        """The engine's counters (``latency_ms`` NaN before the first pose); the API process counts handed and
        replayed records itself, from the ``handed`` events."""
        return self.slam.stats()

    def poses(self) -> list[PoseOut]:
        """Every tracked pose, with the newest keyframe refinements, in tracking order."""
        records = list(self.slam.records)  # a copy: the tracking thread only appends
        poses = []
        for r in records:
            try:
                poses.append(pose_out(r))
            except Exception:  # noqa: BLE001 - a frame without a finite pose is left out, not fatal
                log.warning("session %s: frame %d has no finite pose; left out of the trajectory",
                            self.spec.session_id, r.index)
        return poses

    def _snapshot(self) -> MapSnapshot:
        snap = self.slam.snapshot
        if snap is None:
            raise MapNotReadyError(f"session {self.spec.session_id} has no map yet: no frame has been mapped")
        return snap

    def render(self, req: RenderRequest) -> tuple[RenderedImage, int]:
        """Depth (+ colour) at a client's camera from the newest map, and that map's version."""
        snap = self._snapshot()
        return self.slam.render_depth(req.K(), req.T_world_cam_cv(), req.width, req.height,
                                      with_color=req.with_color, snapshot=snap), snap.version

    def mesh_bytes(self, fmt: str, detail: MeshDetail = "full") -> tuple[bytes, int]:
        """The mesh of the newest map as ``fmt`` at ``detail`` (``full``: ``config.mesh_res``; ``preview``:
        its cheap preview lattice), and the map version it was extracted from. The engine caches the mesh per
        version (:meth:`SlamSystem.mesh`, the one cache of a live map); encoding it again is cheap (a 330k-face
        PLY: ~16 ms, GLB ~46 ms on this project's CPU)."""
        snap = self._snapshot()
        res = self.config.preview_mesh_res() if detail == "preview" else self.config.mesh_res
        with self._mesh_lock:  # one extraction at a time; others wait for it and hit the cache
            mesh = self.slam.mesh(res, snapshot=snap)
        return mesh_bytes(mesh, fmt, self.slam.world_axes()), snap.version

    def mesh_frame(self, fmt: str) -> dict:
        """The ``.frame.json`` sidecar of the mesh as ``fmt``: which frame its coordinates are in."""
        return self.slam.world_axes().sidecar(f"mesh.{fmt}", fmt)

    def voxels_bytes(self, fmt: str) -> tuple[bytes, int]:
        snap = self._snapshot()
        return snap.export(fmt), snap.version

    # ------------------------------------------------------------------ finish, close (verbs)
    def finish(self, timeout_s: float, records: int | None = None) -> SlamStats:
        """Track and map every available record, run the final mapping, and write the final checkpoint,
        mesh (``mesh.ply`` + sidecar), poses and TUM trajectory. Idempotent; blocks until done.

        ``records``: how many records the recording holds now (every acknowledged frame), so that none is left
        out whatever the order notices arrived in.

        Raises:
            EngineFailedError: the engine failed (before or while finishing); ``record`` names the frame.
        """
        if records is not None:
            self.available(records)
        with self._finish_lock:
            if self._finished:
                return self.stats()
            self._raise_if_failed()
            with self._cond:
                self._finishing = True
                self._cond.notify_all()
            deadline = time.monotonic() + timeout_s
            self._keeper.join(timeout_s)  # no periodic checkpoint may land after the final one
            self._feeder.join(timeout_s)
            if self._feeder.is_alive():
                self._fail(f"finish timed out after {timeout_s:.0f} s with frames still queued")
            self._raise_if_failed()
            try:
                # Always let the engine drain its queue: a realtime session finished before its first frame
                # was tracked has no mapper yet, but frames waiting for the tracker.
                self.slam.finish(timeout_s=max(1.0, deadline - time.monotonic()))
                if self.slam.mapper is not None and self.slam.mapper.keyframes:  # a map exists
                    self.write_checkpoint(from_snapshot=False)
                    mesh = self.slam.mesh()
                    atomic_write_bytes(self.folder / MESH_FILE, mesh_bytes(mesh, "ply"))
                    atomic_write_bytes(sidecar_path(self.folder / MESH_FILE), json.dumps(
                        self.slam.world_axes().sidecar(MESH_FILE, "ply"), indent=2).encode())
                    write_tum_trajectory(self.folder / TRAJECTORY_FILE, self.slam.trajectory())
            except Exception as e:  # noqa: BLE001 - fails this session only
                self._fail(e)
                self._raise_if_failed()
            self._finished = True
            return self.stats()

    def _raise_if_failed(self) -> None:
        if self.error is not None:
            raise EngineFailedError(self.error, self._failed_record)

    def close(self, checkpoint: bool = True) -> None:
        """Stop the feeder and the engine (records not yet handed over stay in the recording for a later
        resume) and, with ``checkpoint``, save the map."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._feeder.join(timeout=30)
        self._keeper.join(timeout=5)
        if self.slam.error is None:
            self.slam.close()
        if checkpoint and self.error is None and not self._finished:
            try:
                self.write_checkpoint(from_snapshot=False)
            except Exception:  # noqa: BLE001 - shutdown goes on; the recording holds every frame
                log.exception("session %s: checkpoint at close failed", self.spec.session_id)
        self._reader.close()

