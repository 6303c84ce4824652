"""One open session: its recording, its state, and the worker that runs its engine.

Data flow of a frame (``Session.ingest``)::

    admit (bounded, else QueueFullError -> 429) -> decode + check -> append to recording.vxr + fdatasync
    -> 202 -> "the recording holds n records" to the worker -> the worker maps the new record and feeds
    it to its engine (:class:`~.engine_host.EngineHost`, in a process of its own by default: :mod:`.worker`)

Backpressure policy:

* every accepted frame is recorded durably before it is acknowledged; nothing acknowledged is lost;
* at most ``max_pending_frames`` frames per session may be between admission and the engine (being
  recorded, or queued behind a replay or an ``offline`` session's tracker); more are refused with 429
  and ``Retry-After`` (nothing is recorded for a refused frame);
* ``realtime`` sessions hand frames to the engine at once; its tracker always takes the newest frame and
  drops older untracked ones (counted in ``frames_dropped``; they stay in the recording);
* ``offline`` sessions run the engine's offline mode: each frame is tracked and mapped before the next, so
  every frame is tracked, in order, against the map of all frames before it (the same recording gives the
  same poses and map every time, as ``voxfusion run`` does); replays hand the next frame over only once
  the previous one is tracked.

Failures stay inside the session. An engine exception marks it ``failed`` (``last_error`` names the
frame); ``POST /resume`` replays the recording without that frame. A worker process that dies (killed,
crashed, out of memory) is restarted at once, replaying the recording (at most ``worker_restarts`` times).
The worker checkpoints the map every ``checkpoint_interval_s`` / ``checkpoint_keyframes`` and at finish.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from voxfusion.core.checkpoint import atomic_write_bytes
from voxfusion.core.config import config_to_dict
from voxfusion.core.errors import EngineFailedError
from voxfusion.core.render.volume import RenderedImage
from voxfusion.core.slam import SlamStats
from voxfusion.core.slam.presets import VoxFusionConfig
from voxfusion.proto import FrameDecodeError, decode_frame, read_header
from voxfusion.proto.api_extra import SessionStatusOut
from voxfusion.proto.frame_codec import DecodeLimits
from voxfusion.proto.recording import RECORDING_FILENAME, RecordingWriter, iter_messages, scan_recording
from voxfusion.proto.schemas import PoseOut, RenderRequest, SessionMode, SessionState

from .engine_host import HostSpec
from .errors import NotReadyError, QueueFullError, SessionConflictError, WorkerUnavailableError
from .live_frame import LatestFrame
from .outputs import MeshDetail
from .settings import ServerSettings
from .store import SessionStore
from .worker import SessionWorker, WorkerLostError, start_worker

__all__ = ["PoseListener", "Session", "SKIP_FILE"]

log = logging.getLogger("voxfusion.server")

PoseListener = Callable[[PoseOut], None]
"""Called with each new pose right after tracking (on the worker's event thread): keep it fast."""

SKIP_FILE = "skip.json"
"""Recording positions of frames an engine failed on (``[int, ...]``): replays leave them out."""

_OPEN_STATES = (SessionState.created, SessionState.running, SessionState.finishing)
_STATS_TIMEOUT_S = 5.0
_STARTING_STATS_TIMEOUT_S = 0.5
"""How long a status query waits for a worker that has not answered one yet (still building its engine: seconds,
tens of seconds when a dozen start at once on a small CPU); its counters are zero until then."""
_NO_STATS = SlamStats(0, 0, 0, 0, 0, 0, 0, 0.0, float("nan"), 0)
"""The counters of an engine that has not answered yet."""
_QUERY_TIMEOUT_S = 300.0


class Session:
    """An open session (see the module docstring). Created by the manager; thread-safe.

    Args:
        session_id, name, mode, created_at: its identity (from the database row).
        config: engine configuration (``mode``: the session's, device set by the server).
        folder: ``<data_dir>/sessions/<id>``.
        settings: server limits, checkpoint cadence, worker kind.
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
        self._admitted = 0
        self._stop = False
        self._finishing = False
        self._finish_lock = threading.Lock()
        self._latest: PoseOut | None = None
        self._latest_frame: LatestFrame | None = None
        self._limits = DecodeLimits(max_width=settings.max_image_width, max_height=settings.max_image_height)
        folder.mkdir(parents=True, exist_ok=True)
        self.recorder = RecordingWriter(folder / RECORDING_FILENAME)
        if self.recorder.recovered_bytes:
            log.warning("session %s: cut a torn %d-byte record from the end of its recording",
                        session_id, self.recorder.recovered_bytes)
        self._seqs: set[int] = set()
        replay_total = len(self.recorder) if replay else 0
        if replay_total:
            scan = scan_recording(self.recorder.path)
            self._seqs = {read_header(m).seq for m in iter_messages(self.recorder.path, scan)}
            self.state = SessionState.running
        self.worker_restarts = 0
        self._generation = 0
        self._worker: SessionWorker | None = None
        self._stats = _NO_STATS
        self._stats_answered = False  # the current worker has answered a stats query
        self._replay = self._handed = 0  # records the current worker replays / has handed to its engine
        self._start_worker(replay_total)

    # ------------------------------------------------------------------ the worker
    def _skips(self) -> tuple[int, ...]:
        path = self.folder / SKIP_FILE
        try:
            return tuple(sorted(int(i) for i in json.loads(path.read_text())))
        except FileNotFoundError:
            return ()
        except (ValueError, TypeError):
            log.warning("session %s: ignoring an unreadable %s", self.id, path)
            return ()

    def _start_worker(self, replay: int) -> None:
        """Start a worker that replays the first ``replay`` records (paced) and then takes live frames."""
        spec = HostSpec(self.id, self.mode.value, config_to_dict(self.config), str(self.folder), replay=replay,
                        skip=self._skips(), checkpoint_interval_s=self.settings.checkpoint_interval_s,
                        checkpoint_keyframes=self.settings.checkpoint_keyframes,
                        torch_threads=self.settings.torch_threads_per_worker())
        with self._cond:
            self._generation += 1
            generation = self._generation
        worker = start_worker(self.settings.session_workers, spec,
                              on_event=lambda event: self._on_event(generation, event),
                              on_exit=lambda code: self._on_worker_exit(generation, code),
                              ray=self.settings.ray_options())
        with self._cond:
            wanted = generation == self._generation and not self._stop and self.state in _OPEN_STATES
            if wanted:
                self._latest = None
                self._stats = _NO_STATS
                self._stats_answered = False
                self._replay, self._handed = replay, 0
                self._worker = worker
                worker.available(len(self.recorder))
                self._cond.notify_all()
        if not wanted:  # closed, deleted or failed while it started
            worker.close(checkpoint=False)

    def _on_event(self, generation: int, event: tuple) -> None:
        kind = event[0]
        with self._cond:
            if generation != self._generation:
                return  # from a worker that was replaced
            if kind == "handed":
                self._handed = event[1]
                self._cond.notify_all()
                return
            if kind == "pose":
                self._latest = event[1]
        if kind == "failed":
            self.mark_failed(event[1], record=event[2])
        elif kind == "pose":
            for listener in list(self.listeners):
                try:
                    listener(event[1])
                except Exception:  # noqa: BLE001 - a bad listener must not stop the others
                    log.exception("session %s: pose listener failed; removing it", self.id)
                    try:
                        self.listeners.remove(listener)
                    except ValueError:
                        pass

    def _on_worker_exit(self, generation: int, code: int | None) -> None:
        """A worker process ended on its own: restart it (replaying the recording) or fail the session."""
        with self._cond:
            if generation != self._generation or self._stop or self.state not in _OPEN_STATES:
                return
            self._worker = None  # dead: requests get 503 until the new one is in place
            self.worker_restarts += 1
            restarts = self.worker_restarts
        if restarts > self.settings.worker_restarts:
            self.mark_failed(f"the engine's worker process died {restarts} times (last exit code {code}); "
                             f"--worker-restarts allows {self.settings.worker_restarts}")
            return
        log.warning("session %s: worker process ended (exit code %s); restarting it (%d of %d), replaying "
                    "%d recorded frames", self.id, code, restarts, self.settings.worker_restarts, len(self.recorder))
        try:
            self._start_worker(replay=len(self.recorder))
        except Exception as e:  # noqa: BLE001 - no worker: the session cannot go on
            self.mark_failed(f"restarting the worker failed: {type(e).__name__}: {e}")

    def _call(self, verb: str, *args: Any, timeout_s: float = _QUERY_TIMEOUT_S) -> Any:
        """``verb`` answered by the worker; a worker that is restarting or too slow is a 503."""
        with self._cond:
            worker = self._worker
        if worker is None:
            raise WorkerUnavailableError(f"session {self.id}: its engine worker is starting; retry in a few seconds")
        try:
            return worker.call(verb, *args, timeout_s=timeout_s)
        except WorkerLostError as e:
            raise WorkerUnavailableError(f"session {self.id}: its engine worker is restarting ({e}); retry in a "
                                         "few seconds") from e
        except TimeoutError as e:
            raise WorkerUnavailableError(str(e), retry_after_s=10) from e

    # ------------------------------------------------------------------ ingest
    def ingest(self, message: bytes) -> tuple[int, bool]:
        """Decode, record durably and hand one frame message to the worker; returns ``(seq, duplicate)``.

        A frame whose ``seq`` this session already recorded is acknowledged again without being recorded
        twice (``duplicate=True``), so a client may safely retry a frame whose answer it did not get.

        Raises:
            SessionConflictError: the session is finishing, finished or failed (409).
            QueueFullError: ``max_pending_frames`` frames are already in flight (429).
            FrameDecodeError: the message is malformed (400 / 415).
        """
        with self._cond:
            self._check_accepting()
            waiting = self._admitted + self._queued()
            if waiting >= self.settings.max_pending_frames:
                raise QueueFullError(f"session {self.id} has {waiting} frames waiting for the engine (limit "
                                     f"{self.settings.max_pending_frames}); retry shortly", retry_after_s=1)
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
                self._latest_frame = LatestFrame(seq, decoded.frame)
                if self.state == SessionState.created:
                    self.state = SessionState.running
                    self.store.set_state(self.id, self.state.value)
                if self._worker is not None:  # under the lock: a worker restarting meanwhile is told too
                    self._worker.available(len(self.recorder))
            return seq, False
        finally:
            with self._cond:
                self._admitted -= 1

    def _queued(self) -> int:
        """Recorded live frames not yet handed to the engine (frames being replayed do not count)."""
        return max(0, len(self.recorder) - max(self._handed, self._replay))

    def _check_accepting(self) -> None:
        if self.state == SessionState.failed:
            raise SessionConflictError(f"session {self.id} failed ({self.last_error}); POST /sessions/{self.id}/resume "
                                  "replays its recording, or DELETE it", "session_id")
        if self._finishing or self.state in (SessionState.finishing, SessionState.finished):
            raise SessionConflictError(f"session {self.id} is {self.state.value}; it takes no more frames",
                                  "session_id")

    # ------------------------------------------------------------------ failures
    def mark_failed(self, error: BaseException | str, record: int | None = None) -> None:
        """Mark the session failed with ``error`` (recorded in the database) and stop its worker.
        ``record``: the recording position of the frame the engine failed on; a resume leaves it out."""
        message = error if isinstance(error, str) else f"{type(error).__name__}: {error}"
        if record is None and isinstance(error, EngineFailedError):
            record = error.record
        if record is not None:
            message += (f" (on recorded frame {record}; POST /sessions/{self.id}/resume replays the recording "
                        "without it)")
        with self._cond:  # the state first: nothing below may leave a failed engine looking alive
            if self.state == SessionState.failed:
                return
            self.state = SessionState.failed
            self.last_error = message
            self._stop = True
            worker = self._worker
            self._cond.notify_all()
        log.error("session %s failed: %s", self.id, message)
        try:
            if record is not None:
                skips = sorted(set(self._skips()) | {int(record)})
                atomic_write_bytes(self.folder / SKIP_FILE, json.dumps(skips).encode())
            self.store.set_state(self.id, SessionState.failed.value, last_error=message,
                                 stats=self.status().model_dump(mode="json"))
        except Exception:  # noqa: BLE001 - e.g. a full disk: the session is failed in memory all the same
            log.exception("session %s: recording the failure failed", self.id)
        finally:
            if worker is not None:
                threading.Thread(target=worker.close, args=(False,), name=f"voxfusion-close-{self.id[:8]}",
                                 daemon=True).start()

    # ------------------------------------------------------------------ queries
    @property
    def is_open(self) -> bool:
        return self.state in _OPEN_STATES

    def status(self) -> SessionStatusOut:
        with self._cond:
            worker = self._worker
            live = self.state in _OPEN_STATES and not self._stop
            timeout_s = _STATS_TIMEOUT_S if self._stats_answered else _STARTING_STATS_TIMEOUT_S
        if live and worker is not None:
            try:
                stats = worker.call("stats", timeout_s=timeout_s)
                with self._cond:
                    if worker is self._worker:
                        self._stats = stats
                        self._stats_answered = True
            except (WorkerLostError, TimeoutError, EngineFailedError):
                pass  # a restarting or busy worker: its last known counters
        with self._cond:
            st = self._stats
            queued = self._admitted + self._queued()
            replay_pending = max(0, self._replay - self._handed) if self.state in _OPEN_STATES else 0
            pid = None if worker is None else worker.pid
            node = None if worker is None else worker.node_id
        return SessionStatusOut(
            id=self.id, name=self.name, mode=self.mode, state=self.state, created_at=self.created_at,
            frames_received=len(self.recorder), frames_tracked=st.frames_tracked, frames_mapped=st.frames_mapped,
            frames_dropped=st.frames_dropped, frames_lost=st.frames_lost, frames_retried=st.frames_retried,
            frames_relocalised=st.frames_relocalised, frames_limited=st.frames_limited,
            keyframes=st.keyframes, voxels=st.voxels,
            fps=max(0.0, st.fps), latency_ms=st.latency_ms if math.isfinite(st.latency_ms) else None,
            last_error=self.last_error, map_version=st.map_version,
            replay_pending=replay_pending, frames_queued=queued, worker_pid=pid, worker_node=node,
            worker_restarts=self.worker_restarts)

    def poses(self) -> list[PoseOut]:
        """Every tracked pose, with the newest keyframe refinements, in tracking order."""
        return self._call("poses")

    def has_pose(self) -> bool:
        with self._cond:
            return self._latest is not None

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
        return self._call("render", req)

    def mesh_bytes(self, fmt: str, detail: MeshDetail = "full") -> tuple[bytes, int]:
        """The mesh of the newest map as ``fmt`` at ``detail`` and the map version it was extracted from."""
        return self._call("mesh_bytes", fmt, detail)

    def mesh_frame(self, fmt: str) -> dict:
        """The ``.frame.json`` sidecar of the mesh as ``fmt``: which frame its coordinates are in."""
        return self._call("mesh_frame", fmt)

    def voxels_bytes(self, fmt: str) -> tuple[bytes, int]:
        return self._call("voxels_bytes", fmt)

    # ------------------------------------------------------------------ finish, close
    def finish(self, timeout_s: float) -> SessionStatusOut:
        """Stop taking frames, track and map what is recorded, run the final mapping, and have the worker
        write the final checkpoint, mesh (``mesh.ply``), poses and TUM trajectory. Idempotent; blocks until
        done. A worker that dies meanwhile is restarted (replaying the recording) and asked again.

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
                while self._admitted:  # frames admitted before finishing are recorded (and counted) first
                    self._cond.wait(0.1)
            self.store.set_state(self.id, SessionState.finishing.value)
            deadline = time.monotonic() + timeout_s
            while True:
                with self._cond:
                    worker, generation = self._worker, self._generation
                left = deadline - time.monotonic()
                try:
                    if worker is None or left <= 0:
                        raise TimeoutError(f"finish timed out after {timeout_s:.0f} s")
                    stats = worker.call("finish", left, len(self.recorder), timeout_s=left + 60)
                    break
                except WorkerLostError:
                    with self._cond:  # the exit handler starts a new worker (or fails the session)
                        while (self._generation == generation and self.state != SessionState.failed
                               and time.monotonic() < deadline):
                            self._cond.wait(0.5)
                except EngineFailedError as e:
                    self.mark_failed(e)
                except TimeoutError as e:
                    self.mark_failed(f"{e} with frames still queued")
                self._check_not_failed()
            with self._cond:
                self._stats = stats
                self.state = SessionState.finished
                self._stop = True
            status = self.status()
            self.store.set_state(self.id, SessionState.finished.value, stats=status.model_dump(mode="json"))
            self.recorder.close()
            worker.close(checkpoint=False)
            return status

    def _check_not_failed(self) -> None:
        if self.state == SessionState.failed:
            raise SessionConflictError(f"session {self.id} failed: {self.last_error}", "session_id")

    def close(self, checkpoint: bool = True) -> None:
        """Stop the worker (frames not yet handed over stay in the recording for a later resume) and, with
        ``checkpoint``, have it save the map first. Used at server shutdown, idle close and delete."""
        with self._cond:
            self._stop = True
            worker = self._worker
            failed = self.state == SessionState.failed
            self._cond.notify_all()
        if worker is not None and not failed:  # a failed session's worker is already being closed
            worker.close(checkpoint=checkpoint and self.state in _OPEN_STATES)
        self.recorder.close()

