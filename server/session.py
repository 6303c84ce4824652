"""One open session: its recording, its engine (tracking + mapping workers), a feeder thread, checkpoints.

Data flow of a frame (``Session.ingest``)::

    admit (bounded queue, else QueueFullError -> 429) -> decode + check -> append to recording.vxr + fdatasync
    -> 202 -> feeder queue -> SlamSystem.submit (tracking worker -> mapping worker)

Backpressure policy:

* every accepted frame is recorded durably before it is acknowledged; nothing acknowledged is lost;
* at most ``max_pending_frames`` frames per session may be between admission and the engine (being
  recorded, or queued behind a replay or an ``offline`` session's tracker); more are refused with 429
  and ``Retry-After`` (nothing is recorded for a refused frame);
* ``realtime`` sessions hand frames to the engine at once; its tracker always takes the newest frame and
  drops older untracked ones (counted in ``frames_dropped``; they stay in the recording);
* ``offline`` sessions and replays hand the next frame over only once the previous one is tracked, so
  every frame is tracked, in order.

A worker exception marks only this session ``failed`` (``last_error``); it never propagates to others.
The map is checkpointed atomically every ``checkpoint_interval_s`` / ``checkpoint_keyframes`` (from the
published snapshot, without stopping the workers) and at finish.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from voxfusion.core.checkpoint import atomic_write_bytes, save_checkpoint
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.mesh import mesh_bytes
from voxfusion.core.mesh.frame import sidecar_path
from voxfusion.core.render import RenderedImage, render_depth_image
from voxfusion.core.slam import FrameRecord, SlamError, SlamSystem
from voxfusion.core.slam_config import VoxFusionConfig
from voxfusion.core.trajectory import write_tum_trajectory
from voxfusion.core.voxel_export import voxels_npz_bytes, voxels_ply_bytes
from voxfusion.proto import FrameDecodeError, decode_frame, read_header
from voxfusion.proto.api_extra import SessionStatusOut
from voxfusion.proto.frame_codec import DecodeLimits
from voxfusion.proto.recording import RECORDING_FILENAME, RecordingWriter, iter_messages, scan_recording
from voxfusion.proto.schemas import PoseOut, RenderRequest, SessionMode, SessionState

from .errors import NotReadyError, QueueFullError, SessionConflictError
from .live_frame import LatestFrame
from .outputs import MeshDetail, pose_out
from .settings import ServerSettings
from .store import SessionStore
from .stored import CHECKPOINT_FILE, MESH_FILE, POSES_FILE, TRAJECTORY_FILE

__all__ = ["PoseListener", "Session"]

log = logging.getLogger("voxfusion.server")

PoseListener = Callable[[PoseOut], None]
"""Called with each new pose right after tracking, on the tracking thread: keep it fast."""

_OPEN_STATES = (SessionState.created, SessionState.running, SessionState.finishing)


class Session:
    """An open session (see the module docstring). Created by the manager; thread-safe.

    Args:
        session_id, name, mode, created_at: its identity (from the database row).
        config: engine configuration (``mode="realtime"``, device set by the server).
        folder: ``<data_dir>/sessions/<id>``.
        settings: server limits and checkpoint cadence.
        store: the metadata database (state changes are written through).
        listeners: called with every new pose (the manager's list for this id, shared across resumes).
        replay: replay the recording's frames through the engine first (resume after a restart).
    """

    def __init__(self, session_id: str, name: str | None, mode: SessionMode, created_at: datetime,
                 config: VoxFusionConfig, folder: Path, settings: ServerSettings, store: SessionStore,
                 listeners: list[PoseListener], replay: bool = False) -> None:
        self.id = session_id
        self.name = name
        self.mode = SessionMode(mode)
        self.created_at = created_at
        self.config = config
        self.folder = folder
        self.settings = settings
        self.store = store
        self.listeners = listeners
        self.state = SessionState.created
        self.last_error: str | None = None
        self._cond = threading.Condition()
        self._queue: deque[RGBDFrame] = deque()
        self._admitted = 0
        self._stop = False
        self._finishing = False
        self._finish_lock = threading.Lock()
        self._mesh_lock = threading.Lock()
        self._mesh_cache: dict[tuple[int, str, int], bytes] = {}
        self._latest: PoseOut | None = None
        self._latest_frame: LatestFrame | None = None
        self._submitted = 0
        self._tracked = 0
        self._limits = DecodeLimits(max_width=settings.max_image_width, max_height=settings.max_image_height)
        folder.mkdir(parents=True, exist_ok=True)
        self.recorder = RecordingWriter(folder / RECORDING_FILENAME)
        if self.recorder.recovered_bytes:
            log.warning("session %s: cut a torn %d-byte record from the end of its recording",
                        session_id, self.recorder.recovered_bytes)
        scan = scan_recording(self.recorder.path)
        self._seqs: set[int] = set()
        self._replay_total = len(scan.offsets) if replay else 0
        self._replay_left = self._replay_total
        if replay and self._replay_total:
            self._seqs = {read_header(m).seq for m in iter_messages(self.recorder.path, scan)}
            self.state = SessionState.running
        self.slam = SlamSystem(config, on_pose=self._on_pose)
        self._ckpt_time = time.monotonic()
        self._ckpt_version = 0
        self._ckpt_keyframes = 0
        self._feeder = threading.Thread(target=self._feed, name=f"voxfusion-feeder-{session_id[:8]}", daemon=True)
        self._feeder.start()

    # ------------------------------------------------------------------ ingest
    def ingest(self, message: bytes) -> tuple[int, bool]:
        """Decode, record durably and queue one frame message; returns ``(seq, duplicate)``.

        A frame whose ``seq`` this session already recorded is acknowledged again without being recorded
        twice (``duplicate=True``), so a client may safely retry a frame whose answer it did not get.

        Raises:
            SessionConflictError: the session is finishing, finished or failed (409).
            QueueFullError: ``max_pending_frames`` frames are already in flight (429).
            FrameDecodeError: the message is malformed (400 / 415).
        """
        with self._cond:
            self._check_accepting()
            if self._admitted + len(self._queue) >= self.settings.max_pending_frames:
                raise QueueFullError(f"session {self.id} has {self._admitted + len(self._queue)} frames waiting for "
                                f"the engine (limit {self.settings.max_pending_frames}); retry shortly",
                                retry_after_s=1)
            self._admitted += 1
        seq: int | None = None
        try:
            decoded = decode_frame(message, limits=self._limits)
            if decoded.session is not None and decoded.session != self.id:
                raise FrameDecodeError("header", f"the frame names session {decoded.session!r} but was posted to "
                                                 f"session {self.id!r}")
            seq = decoded.seq
            with self._cond:
                if seq in self._seqs:
                    return seq, True
                self._seqs.add(seq)
            try:
                self.recorder.append(message)
            except BaseException:
                with self._cond:
                    self._seqs.discard(seq)
                raise
            with self._cond:
                self._queue.append(decoded.frame)
                self._latest_frame = LatestFrame(seq, decoded.frame)
                if self.state == SessionState.created:
                    self.state = SessionState.running
                    self.store.set_state(self.id, self.state.value)
                self._cond.notify_all()
            return seq, False
        finally:
            with self._cond:
                self._admitted -= 1

    def _check_accepting(self) -> None:
        if self.state == SessionState.failed:
            raise SessionConflictError(f"session {self.id} failed ({self.last_error}); POST /sessions/{self.id}/resume "
                                  "replays its recording, or DELETE it", "session_id")
        if self._finishing or self.state in (SessionState.finishing, SessionState.finished):
            raise SessionConflictError(f"session {self.id} is {self.state.value}; it takes no more frames",
                                  "session_id")

    # ------------------------------------------------------------------ feeder
    def _on_pose(self, rec: FrameRecord) -> None:
        try:
            pose = pose_out(rec, refined=False)
        except Exception:  # noqa: BLE001 - e.g. a non-finite pose: never let it kill the tracking worker
            log.exception("session %s: frame %d has no valid pose to publish", self.id, rec.index)
            with self._cond:
                self._tracked += 1
                self._cond.notify_all()
            return
        with self._cond:
            self._tracked += 1
            self._latest = pose
            self._cond.notify_all()
        for listener in list(self.listeners):
            try:
                listener(pose)
            except Exception:  # noqa: BLE001 - a bad listener must not kill tracking
                log.exception("session %s: pose listener failed; removing it", self.id)
                try:
                    self.listeners.remove(listener)
                except ValueError:
                    pass

    def _submit(self, frame: RGBDFrame, paced: bool) -> None:
        self.slam.submit(frame)
        self._submitted += 1
        if not paced:
            return
        target = self._submitted
        with self._cond:
            while self._tracked < target and self.slam.error is None and not self._stop:
                self._cond.wait(0.5)
        if self.slam.error is not None:
            raise SlamError(f"SLAM worker failed: {type(self.slam.error).__name__}: {self.slam.error}")

    def _feed(self) -> None:
        try:
            if self._replay_total:
                for message in iter_messages(self.recorder.path, stop=self._replay_total):
                    if self._stop:
                        return
                    try:
                        frame = decode_frame(message).frame
                    except FrameDecodeError as e:  # recorded before the door refused such frames: skip it
                        log.warning("session %s: replay skips a recorded frame: %s", self.id, e)
                    else:
                        self._submit(frame, paced=True)
                    with self._cond:
                        self._replay_left -= 1
            paced = self.mode == SessionMode.offline
            while True:
                with self._cond:
                    while not self._queue and not self._stop and not self._finishing:
                        self._cond.wait(0.5)
                    if self._stop or (not self._queue and self._finishing):
                        return
                    frame = self._queue.popleft()
                    self._cond.notify_all()
                self._submit(frame, paced)
        except Exception as e:  # noqa: BLE001 - any failure fails this session only
            self.mark_failed(e)

    # ------------------------------------------------------------------ health, checkpoints
    def mark_failed(self, error: BaseException | str) -> None:
        """Mark the session failed with ``error`` (recorded in the database); stop its engine."""
        cause = self.slam.error  # the worker's own exception, when a worker failed
        if isinstance(error, str):
            message = error
        elif cause is not None:
            message = f"{type(cause).__name__}: {cause}"
        else:
            message = f"{type(error).__name__}: {error}"
        with self._cond:
            if self.state == SessionState.failed:
                return
            self.state = SessionState.failed
            self.last_error = message
            self._stop = True
            self._cond.notify_all()
        log.error("session %s failed: %s", self.id, message)
        self.store.set_state(self.id, SessionState.failed.value, last_error=message,
                             stats=self.status().model_dump(mode="json"))
        threading.Thread(target=self.slam.close, name=f"voxfusion-close-{self.id[:8]}", daemon=True).start()

    def poll(self, now: float | None = None) -> None:
        """Housekeeping (called every fraction of a second): detect worker failures, write periodic
        checkpoints."""
        if self.state in (SessionState.failed, SessionState.finished):
            return
        if self.slam.error is not None:
            self.mark_failed(SlamError(str(self.slam.error)))
            return
        if self.state == SessionState.finishing:
            return
        now = time.monotonic() if now is None else now
        snap = self.slam.snapshot
        mapper = self.slam.mapper
        if snap is None or mapper is None or snap.version == self._ckpt_version:
            return
        new_kfs = len(mapper.keyframes) - self._ckpt_keyframes
        due = now - self._ckpt_time >= self.settings.checkpoint_interval_s
        if due or new_kfs >= self.settings.checkpoint_keyframes:
            try:
                self.write_checkpoint(from_snapshot=True)
            except Exception:  # noqa: BLE001 - a failed periodic checkpoint is retried, not fatal
                log.exception("session %s: periodic checkpoint failed", self.id)
            self._ckpt_time = now

    def write_checkpoint(self, from_snapshot: bool) -> None:
        """Write ``checkpoint.pt`` and ``poses.json`` atomically.

        ``from_snapshot``: save the newest published snapshot (safe while the workers run); otherwise the
        mapper itself (the workers must be stopped).
        """
        mapper = self.slam.mapper
        snap = self.slam.snapshot
        if mapper is None or snap is None:
            return
        keyframes = list(mapper.keyframes)
        if from_snapshot:
            source = SimpleNamespace(voxels=snap.voxels, decoder=snap.decoder, keyframes=keyframes,
                                     version=snap.version)
        else:
            source = mapper
        poses = self.poses()
        save_checkpoint(self.folder / CHECKPOINT_FILE, source, self.config, self.slam.trajectory())  # type: ignore[arg-type]
        atomic_write_bytes(self.folder / POSES_FILE, json.dumps([p.model_dump(mode="json") for p in poses]).encode())
        self._ckpt_version = source.version
        self._ckpt_keyframes = len(keyframes)

    # ------------------------------------------------------------------ queries
    @property
    def is_open(self) -> bool:
        return self.state in _OPEN_STATES

    def status(self) -> SessionStatusOut:
        st = self.slam.stats()
        with self._cond:
            queued = len(self._queue) + self._admitted
            replay_left = self._replay_left
        lat = st.latency_ms if np.isfinite(st.latency_ms) else None
        return SessionStatusOut(
            id=self.id, name=self.name, mode=self.mode, state=self.state, created_at=self.created_at,
            frames_received=len(self.recorder), frames_tracked=st.frames_tracked, frames_mapped=st.frames_mapped,
            frames_dropped=st.frames_dropped, frames_lost=st.frames_lost, keyframes=st.keyframes, voxels=st.voxels,
            fps=max(0.0, st.fps),
            latency_ms=lat, last_error=self.last_error, map_version=st.map_version, replay_pending=replay_left,
            frames_queued=queued)

    def poses(self) -> list[PoseOut]:
        """Every tracked pose, with the newest keyframe refinements, in tracking order."""
        records = list(self.slam.records)  # a copy: the tracking thread only appends
        poses = []
        for r in records:
            try:
                poses.append(pose_out(r))
            except Exception:  # noqa: BLE001 - a frame without a finite pose is left out, not fatal
                log.warning("session %s: frame %d has no finite pose; left out of the trajectory", self.id, r.index)
        return poses

    def latest_pose(self) -> PoseOut:
        with self._cond:
            latest = self._latest
        if latest is None:
            raise NotReadyError(f"session {self.id} has no tracked frame yet")
        return latest

    def latest_frame(self) -> LatestFrame | None:
        """The last frame this session accepted since it was opened (``None`` before the first)."""
        with self._cond:
            return self._latest_frame

    def render(self, req: RenderRequest) -> tuple[RenderedImage, int]:
        snap = self.slam.snapshot
        if snap is None:
            raise NotReadyError(f"session {self.id} has no map yet: no frame has been mapped")
        image = render_depth_image(snap.voxels, snap.decoder, req.K(), req.T_world_cam_cv(), req.width, req.height,
                                   self.config.render)
        return image, snap.version

    def mesh_bytes(self, fmt: str, detail: MeshDetail = "full") -> tuple[bytes, int]:
        """The mesh of the newest map as ``fmt`` at ``detail`` (``full``: ``config.mesh_res``; ``preview``:
        its cheap preview lattice), and the map version it was extracted from; cached per version."""
        snap = self.slam.snapshot
        if snap is None:
            raise NotReadyError(f"session {self.id} has no map yet: no frame has been mapped")
        res = self.config.preview_mesh_res() if detail == "preview" else self.config.mesh_res
        with self._mesh_lock:
            key = (snap.version, fmt, res)
            if key not in self._mesh_cache:
                mesh = self.slam.mesh(res, snapshot=snap)
                self._mesh_cache = {k: v for k, v in self._mesh_cache.items() if k[0] == snap.version}
                self._mesh_cache[key] = mesh_bytes(mesh, fmt, self.slam.world_axes())
            return self._mesh_cache[key], snap.version

    def mesh_frame(self, fmt: str) -> dict:
        """The ``.frame.json`` sidecar of the mesh as ``fmt``: which frame its coordinates are in."""
        return self.slam.world_axes().sidecar(f"mesh.{fmt}", fmt)

    def voxels_bytes(self, fmt: str) -> tuple[bytes, int]:
        snap = self.slam.snapshot
        if snap is None:
            raise NotReadyError(f"session {self.id} has no map yet: no frame has been mapped")
        data = voxels_npz_bytes(snap.voxels, snap.decoder) if fmt == "npz" else voxels_ply_bytes(snap.voxels)
        return data, snap.version

    # ------------------------------------------------------------------ finish, close
    def finish(self, timeout_s: float) -> SessionStatusOut:
        """Stop taking frames, track and map what is queued, run the final mapping, and write the final
        checkpoint, mesh (``mesh.ply``), poses and TUM trajectory. Idempotent; blocks until done.

        Raises:
            SessionConflictError: the session failed (before or while finishing).
        """
        with self._finish_lock:
            if self.state == SessionState.finished:
                return self.status()
            with self._cond:
                self._check_not_failed()
                self._finishing = True
                self.state = SessionState.finishing
                self._cond.notify_all()
            self.store.set_state(self.id, SessionState.finishing.value)
            deadline = time.monotonic() + timeout_s
            self._feeder.join(timeout_s)
            if self._feeder.is_alive():
                self.mark_failed(f"finish timed out after {timeout_s:.0f} s with frames still queued")
            self._check_not_failed()
            try:
                # Always let the engine drain its queue: a realtime session finished before its first frame
                # was tracked has no mapper yet, but frames waiting for the tracker.
                self.slam.finish(timeout_s=max(1.0, deadline - time.monotonic()))
                if self.slam.mapper is not None and self.slam.mapper.keyframes:  # a map exists (some frame was usable)
                    self.write_checkpoint(from_snapshot=False)
                    mesh = self.slam.mesh()
                    atomic_write_bytes(self.folder / MESH_FILE, mesh_bytes(mesh, "ply"))
                    atomic_write_bytes(sidecar_path(self.folder / MESH_FILE), json.dumps(
                        self.slam.world_axes().sidecar(MESH_FILE, "ply"), indent=2).encode())
                    write_tum_trajectory(self.folder / TRAJECTORY_FILE, self.slam.trajectory())
            except Exception as e:  # noqa: BLE001 - fails this session only
                self.mark_failed(e)
                self._check_not_failed()
            with self._cond:
                self.state = SessionState.finished
            status = self.status()
            self.store.set_state(self.id, SessionState.finished.value, stats=status.model_dump(mode="json"))
            self.recorder.close()
            return status

    def _check_not_failed(self) -> None:
        if self.state == SessionState.failed:
            raise SessionConflictError(f"session {self.id} failed: {self.last_error}", "session_id")

    def close(self, checkpoint: bool = True) -> None:
        """Stop the feeder and the workers (queued frames stay in the recording for a later resume) and,
        with ``checkpoint``, save the map. Used at server shutdown and on delete."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._feeder.join(timeout=30)
        if self.slam.error is None:
            self.slam.close()
        # else mark_failed is already closing the failed engine on a thread of its own; never block on it
        if checkpoint and self.state in _OPEN_STATES and self.slam.error is None:
            try:
                self.write_checkpoint(from_snapshot=False)
            except Exception:  # noqa: BLE001 - shutdown goes on; the recording holds every frame
                log.exception("session %s: checkpoint at shutdown failed", self.id)
        self.recorder.close()
