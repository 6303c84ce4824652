"""The session manager: the one API every transport (HTTP routes, the zenoh bridge) drives.

It owns the metadata database, the open :class:`~.session.Session` objects, stored outputs of finished
sessions, pose listeners, and a housekeeping thread that closes idle sessions (each session's worker
detects its own failures and writes its own checkpoints: :mod:`.session`). Every method is synchronous and
thread-safe; HTTP routes call them from the thread pool.

Slots: at most ``max_sessions`` sessions are open (hold an engine) at once, and at most
``max_sessions_per_client`` of them may have been created without an API key by one client address from
beyond loopback (``create_session(client=...)``). A session that has received no frame for
``session_idle_timeout_s`` is closed the way a server shutdown closes it (map checkpointed, recording kept,
state in the database unchanged) and frees its slot; ``last_error`` says so, and its next frame or
:meth:`SessionManager.resume` replays its recording, as after a restart.

Example (what the zenoh bridge does)::

    sid, token = manager.create_session("desk", {"mapping": {"iters": 10}})
    manager.check_token(sid, token)                 # raises UnauthorizedError / ForbiddenError
    seq = manager.submit_frame_bytes(sid, message)  # durable when this returns
    manager.add_pose_listener(sid, lambda pose: publish(pose.model_dump_json()))
    manager.finish(sid)
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from voxfusion import __version__
from voxfusion.core.config import apply_overrides, config_from_dict, config_to_dict
from voxfusion.core.errors import ConfigError, ValidationError
from voxfusion.core.slam.presets import CPU_PRESET, VoxFusionConfig, check_preset_name, load_preset, resolve_device
from voxfusion.proto.api_extra import HealthOut, SessionStatusOut
from voxfusion.proto.recording import RECORDING_FILENAME, scan_recording
from voxfusion.proto.schemas import PoseOut, RenderRequest, SessionMode, SessionState, Trajectory

from .auth import check_session_id, hash_token, new_session_id, new_token, verify_api_key, verify_token
from .errors import (
    NotReadyError,
    PayloadTooLargeError,
    ServerError,
    SessionConflictError,
    SessionNotFoundError,
    TooManyClientSessionsError,
    TooManySessionsError,
    error_status,
)
from .ingest import check_message_limits
from .live_frame import LatestFrame, last_recorded_frame
from .outputs import MESH_DETAILS, RenderBody, encode_render
from .session import PoseListener, Session
from .settings import ServerSettings
from .store import SessionRow, SessionStore
from .stored import StoredMap

__all__ = ["SessionManager", "MESH_FORMATS", "VOXEL_FORMATS"]

log = logging.getLogger("voxfusion.server")

MESH_FORMATS = ("ply", "glb", "obj")
VOXEL_FORMATS = ("npz", "ply")
_OPEN_STATES = {SessionState.created.value, SessionState.running.value, SessionState.finishing.value}
_IDLE_STATES = (SessionState.created, SessionState.running)
"""States in which an open session may be closed for idleness (never while it finishes)."""
_SERVER_KEYS = ("device", "mode")


class EventCounts:
    """Counters of events (``(name, label value)`` -> count) that many threads add to: each addition is one
    locked read-modify-write (``Counter[key] += 1`` from several threads can lose increments)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[tuple[str, str]] = Counter()

    def add(self, name: str, label: str = "", n: int = 1) -> None:
        with self._lock:
            self._counts[(name, label)] += n

    def items(self) -> list[tuple[tuple[str, str], int]]:
        """A consistent copy of every ``((name, label), count)``."""
        with self._lock:
            return list(self._counts.items())

    def __getitem__(self, key: tuple[str, str]) -> int:
        with self._lock:
            return self._counts[key]


class SessionManager:
    """Sessions of one server (see the module docstring). Call :meth:`open` before use, :meth:`close` after."""

    def __init__(self, settings: ServerSettings) -> None:
        self.settings = settings
        # this process's device (stored maps, health): the server's choice, or where Ray runs the engines
        # elsewhere, whatever this host has; the sessions' presets follow where their engines run
        self.device = resolve_device("auto" if settings.session_workers == "ray" else settings.device)
        on = settings.session_device()
        session_type = self.device.type if on == "auto" else on
        self.default_preset = settings.default_preset or (CPU_PRESET if session_type == "cpu" else "default")
        self.zenoh_running = False
        self.counters = EventCounts()
        """Event counters for ``/metrics``: ``(name, label value)`` -> count."""
        self._lock = threading.RLock()
        self._open: dict[str, Session] = {}
        self._stored: dict[str, StoredMap] = {}
        self._listeners: dict[str, list[PoseListener]] = {}
        self._store: SessionStore | None = None
        self._stop = threading.Event()
        self._housekeeper: threading.Thread | None = None
        self._last_frame: dict[str, float] = {}
        """Open session id -> ``time.monotonic()`` of its last accepted frame (or its creation / resume)."""
        self._pins: Counter[str] = Counter()
        """Open session id -> calls using its :class:`Session` right now (ingest, finish): never closed idle."""
        self._closing: dict[str, threading.Event] = {}
        """Session id -> set once its idle close is done (resume and delete wait for it)."""
        self._resuming: dict[str, threading.Event] = {}
        """Session id -> set once its resume (outside the lock) is done; its slot is counted meanwhile."""
        self._owners: dict[str, str] = {}
        """Session id -> the client address that created it without an API key from beyond loopback."""

    # ------------------------------------------------------------------ lifecycle of the manager
    def open(self) -> None:
        """Open the database (sessions from earlier runs stay listed) and start housekeeping."""
        self.settings.sessions_dir.mkdir(parents=True, exist_ok=True)
        self._store = SessionStore(self.settings.database_path)
        try:  # fail early on a bad --config (or a missing presets folder)
            check_preset_name(self.default_preset)
        except ConfigError as e:
            raise ConfigError("default_preset", e.problem) from e
        if self.settings.session_workers == "ray":
            from .ray_worker import connect

            connect(self.settings.ray_address or "auto")
        elif self.settings.session_workers == "process":  # the first session should not wait for the forkserver
            from .worker import warm_up

            threading.Thread(target=warm_up, name="voxfusion-worker-warm-up", daemon=True).start()
        detached = [r.id for r in self.store.all() if r.state in _OPEN_STATES]
        if detached:
            log.info("%d session(s) were open when the server stopped; they resume on request or on their next "
                     "frame: %s", len(detached), ", ".join(detached))
        self._stop.clear()
        self._housekeeper = threading.Thread(target=self._housekeeping, name="voxfusion-housekeeping", daemon=True)
        self._housekeeper.start()

    def close(self) -> None:
        """Stop every open session (checkpointing its map; recordings are already durable)."""
        self._stop.set()
        if self._housekeeper is not None:
            self._housekeeper.join(timeout=10)
        with self._lock:
            closing = list(self._closing.values())
        for done in closing:  # an idle close the housekeeper had started
            done.wait(timeout=60)
        with self._lock:
            sessions = list(self._open.values())
            self._open.clear()
        for s in sessions:
            s.close(checkpoint=True)
        if self.settings.session_workers == "ray":
            from .ray_worker import disconnect

            disconnect()
        if self._store is not None:
            self._store.close()

    @property
    def store(self) -> SessionStore:
        if self._store is None:
            raise ValidationError("manager", "SessionManager.open() has not been called")
        return self._store

    def _housekeeping(self) -> None:
        while not self._stop.wait(0.25):
            try:
                self.close_idle_sessions()
            except Exception:  # noqa: BLE001 - retried on the next round
                log.exception("closing idle sessions failed")

    def close_idle_sessions(self, now: float | None = None) -> list[str]:
        """Close every open session that has received no frame for ``session_idle_timeout_s`` seconds
        (``now``: ``time.monotonic()`` seconds) and has none in flight; returns their ids.

        A closed session is left exactly as a server shutdown leaves it (map checkpointed, recording kept,
        state unchanged in the database, listed with ``resume_required``); its slot is free, and
        ``last_error`` says why it was closed. Called by the housekeeping thread.
        """
        timeout = self.settings.session_idle_timeout_s
        if timeout <= 0:
            return []
        now = time.monotonic() if now is None else now
        with self._lock:
            candidates = [(sid, s) for sid, s in self._open.items()
                          if s.state in _IDLE_STATES and not self._pins[sid]
                          and now - self._last_frame.setdefault(sid, now) >= timeout]
        closed = []
        for sid, s in candidates:
            st = s.status()  # outside the lock: reads the engine's counters
            with self._lock:
                if st.frames_queued or st.replay_pending:  # still working through received frames: not idle
                    self._last_frame[sid] = now
                    continue
                if (self._open.get(sid) is not s or s.state not in _IDLE_STATES or self._pins[sid]
                        or now - self._last_frame.get(sid, now) < timeout):
                    continue  # a frame, a finish or a delete came in meanwhile
                # the reason is written before the session leaves the open set: readers never see it closed
                # without one
                self.store.set_state(sid, s.state.value, last_error=(
                    f"closed after {timeout:g} s without a frame (--session-idle-timeout-s); its recording "
                    f"and map are kept: send a frame or POST /sessions/{sid}/resume to continue (the "
                    "recording is replayed), or DELETE the session"), stats=st.model_dump(mode="json"))
                del self._open[sid]
                self._last_frame.pop(sid, None)
                done = self._closing[sid] = threading.Event()
                self.counters.add("sessions_idle_closed_total", "")
            try:
                s.close(checkpoint=True)
            finally:
                with self._lock:
                    self._closing.pop(sid, None)
                done.set()
            closed.append(sid)
            log.info("session %s closed: no frame for %g s (state %s kept; it resumes on its next frame)",
                     sid, timeout, s.state.value)
        return closed

    def _wait_closed(self, session_id: str) -> None:
        """Wait (without the lock) until an idle close of ``session_id`` in progress is done."""
        while True:
            with self._lock:
                done = self._closing.get(session_id)
            if done is None:
                return
            done.wait(timeout=60)

    def _pin(self, session_id: str) -> Session | None:
        """The open session, pinned (never closed for idleness) until :meth:`_unpin`; ``None`` if not open."""
        with self._lock:
            s = self._open.get(session_id)
            if s is not None:
                self._pins[session_id] += 1
            return s

    def _unpin(self, session_id: str, got_frame: bool = False) -> None:
        with self._lock:
            self._pins[session_id] -= 1
            if self._pins[session_id] <= 0:
                del self._pins[session_id]
            if got_frame and session_id in self._open:
                self._last_frame[session_id] = time.monotonic()

    # ------------------------------------------------------------------ identity and access
    def _build_config(self, preset: str | None, overrides: dict[str, Any] | None,
                      mode: SessionMode) -> tuple[str, VoxFusionConfig]:
        preset = preset or self.default_preset
        try:
            check_preset_name(preset)  # names only, never a path from a client
        except ConfigError as e:
            raise ValidationError("preset", e.problem) from e
        cfg = load_preset(preset)
        if overrides:
            if not isinstance(overrides, dict):
                raise ValidationError("config", "must be a JSON object of configuration overrides")
            for key in _SERVER_KEYS:
                if key in overrides:
                    raise ValidationError(f"config.{key}", "is chosen by the server (device: voxfusion serve "
                                                           "--device; mode: the session's 'mode')")
            try:
                cfg = apply_overrides(cfg, overrides)
            except ConfigError as e:
                raise ConfigError(f"config.{e.field}", e.problem) from e
        return preset, self._server_config(cfg, mode)

    def _server_config(self, cfg: VoxFusionConfig, mode: SessionMode) -> VoxFusionConfig:
        """``cfg`` with what the server chooses: its device, and the session's mode as the engine's (an ``offline``
        session runs the engine's offline mode, :class:`~.engine_host.EngineHost`)."""
        return apply_overrides(cfg, {"device": self.settings.session_device(), "mode": mode.value})

    def _open_count(self) -> int:
        """Open sessions, counting those being resumed (their slot is reserved)."""
        return sum(1 for s in self._open.values() if s.is_open) + len(self._resuming)

    def _check_capacity(self) -> None:
        if self._open_count() >= self.settings.max_sessions:
            raise TooManySessionsError(f"the server holds its maximum of {self.settings.max_sessions} open sessions; "
                                  "finish or delete one, or retry later")

    def _check_client_capacity(self, client: str | None) -> None:
        """Raise :class:`TooManyClientSessionsError` when ``client`` (an address that creates sessions
        without an API key; ``None``: not limited) holds ``max_sessions_per_client`` open sessions."""
        limit = self.settings.max_sessions_per_client
        if client is None or limit == 0:
            return
        held = (sum(1 for sid, s in self._open.items() if s.is_open and self._owners.get(sid) == client)
                + sum(1 for sid in self._resuming if self._owners.get(sid) == client))
        if held >= limit:
            idle = self.settings.session_idle_timeout_s
            freed = f"; sessions without frames are closed after {idle:g} s" if idle > 0 else ""
            raise TooManyClientSessionsError(
                f"{client} holds its maximum of {limit} open sessions created without an API key: finish "
                f"(POST /sessions/<id>/finish) or delete one of them first{freed}. Servers with an API key "
                "(VOXFUSION_API_KEY) have no per-client limit; --max-sessions-per-client changes it")

    def create_session(self, name: str | None = None, overrides: dict[str, Any] | None = None, *,
                       preset: str | None = None, mode: SessionMode | str = SessionMode.realtime,
                       client: str | None = None) -> tuple[str, str]:
        """Create a session; returns ``(id, token)`` (the token is shown only here).

        ``client``: the address of a client creating it without an API key from beyond loopback (see
        :func:`~voxfusion.server.api.deps.anonymous_client`); such a client may hold at most
        ``max_sessions_per_client`` open sessions (also counted when one of them resumes). ``None``: not
        limited (API key holders, loopback, the zenoh bridge).

        Raises:
            ValidationError / ConfigError: unknown preset or bad override (422; ``field`` names the key).
            TooManyClientSessionsError: ``client`` holds ``max_sessions_per_client`` open sessions (429).
            TooManySessionsError: ``max_sessions`` are open (503).
        """
        mode = SessionMode(mode)
        preset, cfg = self._build_config(preset, overrides, mode)
        with self._lock:
            self._check_client_capacity(client)
            self._check_capacity()
            sid, token = new_session_id(), new_token()
            row = self.store.insert(sid, name, hash_token(token), preset, config_to_dict(cfg), mode.value,
                                    SessionState.created.value)
            self._listeners.setdefault(sid, [])
            self._open[sid] = self._new_session(row, cfg, replay=False)
            self._last_frame[sid] = time.monotonic()
            if client is not None:
                self._owners[sid] = client
        self.counters.add("sessions_created_total", "")
        log.info("session %s created (preset %s, mode %s)", sid, preset, mode.value)
        return sid, token

    def _new_session(self, row: SessionRow, cfg: VoxFusionConfig, replay: bool) -> Session:
        return Session(row.id, row.name, SessionMode(row.mode), row.created_at, cfg,
                       self.settings.sessions_dir / row.id, self.settings, self.store,
                       self._listeners.setdefault(row.id, []), replay=replay)

    def get(self, session_id: str) -> SessionRow:
        """The session's metadata row; raises :class:`SessionNotFoundError` (also for a malformed id)."""
        check_session_id(session_id)
        row = self.store.get(session_id)
        if row is None:
            raise SessionNotFoundError(session_id)
        return row

    def check_token(self, session_id: str, token: str | None) -> None:
        """Raise unless ``token`` is this session's (404 unknown id, 401 missing, 403 wrong; constant time)."""
        verify_token(token, self.get(session_id).token_sha256)

    def check_api_key(self, key: str | None) -> None:
        """Raise unless ``key`` is the server API key (no-op when the server has none)."""
        verify_api_key(key, self.settings.api_key)

    # ------------------------------------------------------------------ frames
    def _session_for_ingest(self, session_id: str) -> Session:
        """The open session (resumed first if it was closed: restart, idle), pinned: :meth:`_unpin` it."""
        s = self._pin(session_id)
        if s is not None:
            return s
        row = self.get(session_id)
        if row.state in _OPEN_STATES:
            self.resume(session_id)
            s = self._pin(session_id)
            if s is None:  # deleted meanwhile
                raise SessionNotFoundError(session_id)
            return s
        raise SessionConflictError(f"session {session_id} is {row.state}; it takes no more frames", "session_id")

    def submit_frame(self, session_id: str, data: bytes) -> tuple[int, bool]:
        """Check, record durably and queue one frame message; returns ``(seq, duplicate)``.

        The same path for every transport. A session left open by a restart resumes first.

        Raises:
            FrameDecodeError (400/415), PayloadTooLargeError (413), SessionNotFoundError (404),
            SessionConflictError (409), QueueFullError (429), TooManySessionsError (503: resuming needs a slot).
        """
        try:
            check_session_id(session_id)
            if len(data) > self.settings.max_frame_bytes:
                raise PayloadTooLargeError(f"frame is {len(data)} bytes, more than this server's limit of "
                                      f"{self.settings.max_frame_bytes}", "body")
            check_message_limits(data, self.settings.max_image_width, self.settings.max_image_height)
            session = self._session_for_ingest(session_id)
            accepted = False
            try:
                seq, duplicate = session.ingest(data)
                accepted = True
            finally:
                self._unpin(session_id, got_frame=accepted)
        except Exception as e:
            self.counters.add("frames_rejected_total", str(error_status(e)))
            raise
        self.counters.add("frames_duplicate_total" if duplicate else "frames_accepted_total", "")
        self.counters.add("frame_bytes_total", "", len(data))
        return seq, duplicate

    def submit_frame_bytes(self, session_id: str, data: bytes) -> int:
        """:meth:`submit_frame` returning only the frame's ``seq``."""
        return self.submit_frame(session_id, data)[0]

    # ------------------------------------------------------------------ queries
    def _open_session(self, session_id: str) -> Session | None:
        """The session's engine, while it has one (a finished session answers from its saved outputs, also
        in the moment its worker is being shut down)."""
        with self._lock:
            s = self._open.get(session_id)
        return None if s is None or s.state == SessionState.finished else s

    def _stored_map(self, session_id: str) -> StoredMap:
        with self._lock:
            sm = self._stored.get(session_id)
            if sm is None:
                sm = self._stored[session_id] = StoredMap(self.settings.sessions_dir / session_id, self.device)
            return sm

    def status(self, session_id: str) -> SessionStatusOut:
        row = self.get(session_id)
        s = self._open_session(session_id)
        if s is not None:
            return s.status()
        stats = dict(row.stats or {})
        for key in ("id", "name", "mode", "state", "created_at", "last_error", "resume_required", "replay_pending",
                    "frames_queued"):
            stats.pop(key, None)
        if "frames_received" not in stats:
            rec = self.settings.sessions_dir / session_id / RECORDING_FILENAME
            stats["frames_received"] = len(scan_recording(rec).offsets) if rec.is_file() else 0
        return SessionStatusOut(id=row.id, name=row.name, mode=SessionMode(row.mode), state=SessionState(row.state),
                                created_at=row.created_at, last_error=row.last_error,
                                resume_required=row.state in _OPEN_STATES, **stats)

    def list_sessions(self) -> list[SessionStatusOut]:
        """Every session's status, in the store's order. The open sessions' workers are asked at the same time:
        each may take its full stats timeout (a worker still importing the engine, or busy), and asked one after
        another a dozen starting workers held the listing for a minute."""
        ids = [r.id for r in self.store.all()]
        if len(ids) <= 1:
            return [self.status(i) for i in ids]
        with ThreadPoolExecutor(max_workers=min(16, len(ids)), thread_name_prefix="voxfusion-list") as pool:
            return list(pool.map(self.status, ids))

    def latest_pose(self, session_id: str) -> PoseOut:
        self.get(session_id)
        s = self._open_session(session_id)
        if s is not None and s.has_pose():
            return s.latest_pose()
        poses = self._stored_map(session_id).poses() if s is None else []
        if not poses:
            raise NotReadyError(f"session {session_id} has no tracked frame yet")
        return poses[-1]

    def trajectory(self, session_id: str) -> Trajectory:
        """Every pose of the session (with keyframe refinements), in tracking order, and how many frames it had
        received (counted after the poses were read, so they never outnumber the count)."""
        self.get(session_id)
        s = self._open_session(session_id)
        poses = s.poses() if s is not None else self._stored_map(session_id).poses()
        return Trajectory(session=session_id, poses=poses, frames_received=self.status(session_id).frames_received)

    def latest_frame(self, session_id: str) -> LatestFrame:
        """The newest frame the session received: the open session's last accepted frame, else the last
        record of its recording (finished sessions, or an open one resumed since its last frame).

        Raises:
            NotReadyError: the session has received no frame (409).
        """
        self.get(session_id)
        s = self._open_session(session_id)
        latest = s.latest_frame() if s is not None else None
        if latest is None:
            latest = last_recorded_frame(self.settings.sessions_dir / session_id / RECORDING_FILENAME)
        if latest is None:
            raise NotReadyError(f"session {session_id} has received no frame yet")
        return latest

    def render(self, session_id: str, req: RenderRequest) -> RenderBody:
        """Depth (+ validity mask, + colour if asked) rendered from the map at a client's pose."""
        self.get(session_id)
        s = self._open_session(session_id)
        image, version = s.render(req) if s is not None else self._stored_map(session_id).render(req)
        if not req.with_color:
            image = image._replace(color=None)
        return encode_render(image, req.format, version)

    def mesh_bytes(self, session_id: str, fmt: str = "ply", detail: str = "full") -> tuple[bytes, int]:
        """The mesh (``ply``/``glb``/``obj``) at ``detail`` (``full`` / ``preview``) and the map version it
        was extracted from (cached per version)."""
        if fmt not in MESH_FORMATS:
            raise ValidationError("format", f"unknown mesh format {fmt!r}; use one of {', '.join(MESH_FORMATS)}")
        if detail not in MESH_DETAILS:
            raise ValidationError("detail", f"unknown mesh detail {detail!r}; use one of {', '.join(MESH_DETAILS)}")
        self.get(session_id)
        s = self._open_session(session_id)
        return (s.mesh_bytes(fmt, detail) if s is not None  # type: ignore[arg-type]
                else self._stored_map(session_id).mesh_bytes(fmt, detail))  # type: ignore[arg-type]

    def mesh_frame(self, session_id: str, fmt: str = "ply") -> dict:
        """Which frame the mesh as ``fmt`` is in (the ``.frame.json`` sidecar object)."""
        if fmt not in MESH_FORMATS:
            raise ValidationError("format", f"unknown mesh format {fmt!r}; use one of {', '.join(MESH_FORMATS)}")
        self.get(session_id)
        s = self._open_session(session_id)
        return s.mesh_frame(fmt) if s is not None else self._stored_map(session_id).mesh_frame(fmt)

    def voxels_bytes(self, session_id: str, fmt: str = "npz") -> tuple[bytes, int]:
        if fmt not in VOXEL_FORMATS:
            raise ValidationError("format", f"unknown voxel format {fmt!r}; use one of {', '.join(VOXEL_FORMATS)}")
        self.get(session_id)
        s = self._open_session(session_id)
        return s.voxels_bytes(fmt) if s is not None else self._stored_map(session_id).voxels_bytes(fmt)

    def add_pose_listener(self, session_id: str, callback: PoseListener) -> None:
        """Call ``callback(PoseOut)`` with each new pose of the session (from its tracking thread; keep it
        fast). Listeners stay registered across a resume."""
        self.get(session_id)
        with self._lock:
            self._listeners.setdefault(session_id, []).append(callback)

    def pose_listener_count(self, session_id: str) -> int:
        """Listeners registered for the session (WebSockets, zenoh subscribers)."""
        with self._lock:
            return len(self._listeners.get(session_id, []))

    def remove_pose_listener(self, session_id: str, callback: PoseListener) -> None:
        with self._lock:
            listeners = self._listeners.get(session_id, [])
            if callback in listeners:
                listeners.remove(callback)

    # ------------------------------------------------------------------ lifecycle of sessions
    def resume(self, session_id: str) -> SessionStatusOut:
        """Replay the recording of a session left open by a restart (or failed) through a new engine.

        A running session is left as it is. Raises :class:`SessionConflictError` for a finished session and
        :class:`TooManySessionsError` when no slot is free. The slot is reserved under the manager's lock; the
        slow part (closing an old engine, reading the recording, starting the worker) runs without it, so
        other sessions never wait for a resume (a second resume of the same session waits for the first).
        """
        self.get(session_id)
        self._wait_closed(session_id)
        while True:
            with self._lock:
                s = self._open.get(session_id)
                pending = self._resuming.get(session_id)
                if pending is None and not (s is not None and s.is_open):
                    row = self.get(session_id)
                    if row.state == SessionState.finished.value:
                        raise SessionConflictError(f"session {session_id} is finished; nothing to resume",
                                                   "session_id")
                    self._check_client_capacity(self._owners.get(session_id))
                    self._check_capacity()
                    if s is not None:
                        self._open.pop(session_id)
                    done = self._resuming[session_id] = threading.Event()
                    break
            if pending is None:  # open and running: nothing to do
                return s.status()  # type: ignore[union-attr]
            pending.wait(timeout=120)  # another caller is resuming it
        try:
            if s is not None:
                s.close(checkpoint=False)
            cfg = self._server_config(config_from_dict(VoxFusionConfig, row.config), SessionMode(row.mode))
            s = self._new_session(row, cfg, replay=True)
            with self._lock:
                self._open[session_id] = s
                self._last_frame[session_id] = time.monotonic()
                self._stored.pop(session_id, None)
            self.store.set_state(session_id, s.state.value, last_error="")
        finally:
            with self._lock:
                self._resuming.pop(session_id, None)
            done.set()
        self.counters.add("sessions_resumed_total", "")
        status = s.status()
        log.info("session %s resumed: replaying %d recorded frames", session_id, status.replay_pending)
        return status

    def finish(self, session_id: str, timeout_s: float | None = None) -> SessionStatusOut:
        """Process what is queued, run the final mapping, write the final checkpoint, mesh and trajectory.

        Blocks until done; idempotent for a finished session. A session left open by a restart is
        resumed (its recording replayed) first. Raises :class:`SessionConflictError` for a failed session.
        """
        row = self.get(session_id)
        s = self._pin(session_id)
        if s is None:
            if row.state == SessionState.finished.value:
                return self.status(session_id)
            if row.state not in _OPEN_STATES:
                raise SessionConflictError(f"session {session_id} is {row.state}: it cannot be finished "
                                      f"({row.last_error})", "session_id")
            self.resume(session_id)
            s = self._pin(session_id)
            if s is None:
                raise SessionNotFoundError(session_id)
        try:
            status = s.finish(self.settings.finish_timeout_s if timeout_s is None else timeout_s)
        finally:
            self._unpin(session_id)
        with self._lock:
            if self._open.get(session_id) is s:
                del self._open[session_id]
                self._last_frame.pop(session_id, None)
                self._owners.pop(session_id, None)
        return status

    def delete(self, session_id: str) -> None:
        """Stop the session (if open) and delete its metadata, recording and outputs."""
        self.get(session_id)
        self._wait_closed(session_id)
        with self._lock:
            resuming = self._resuming.get(session_id)
        if resuming is not None:
            resuming.wait(timeout=120)
        with self._lock:
            s = self._open.pop(session_id, None)
            self._stored.pop(session_id, None)
            self._listeners.pop(session_id, None)
            self._last_frame.pop(session_id, None)
            self._owners.pop(session_id, None)
        if s is not None:
            s.close(checkpoint=False)
        self.store.delete(session_id)
        shutil.rmtree(self.settings.sessions_dir / check_session_id(session_id), ignore_errors=True)
        self.counters.add("sessions_deleted_total", "")

    # ------------------------------------------------------------------ health
    def health(self) -> HealthOut:
        with self._lock:
            n_open = self._open_count()
        return HealthOut(version=__version__, device=str(self.device), sessions_open=n_open,
                         sessions_total=len(self.store.all()), max_sessions=self.settings.max_sessions,
                         zenoh=self.zenoh_running)

    def open_statuses(self) -> list[SessionStatusOut]:
        """Status of every session holding an engine (for ``/metrics``)."""
        with self._lock:
            sessions = list(self._open.values())
        out = []
        for s in sessions:
            try:
                out.append(s.status())
            except ServerError:
                continue
        return out
