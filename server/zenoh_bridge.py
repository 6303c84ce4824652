"""The zenoh side of the server: frames in, poses out, queries answered, for every session.

The bridge opens one zenoh session from a JSON5 config (default ``configs/zenoh/server.json5``: a peer
listening on ``tcp/127.0.0.1:7447`` only, multicast and gossip scouting off; see that file for router /
client mode on a real network) and serves the key space of :mod:`voxfusion.clients.zenoh_keys` through
the same :class:`~voxfusion.server.manager.SessionManager` calls as the HTTP routes, so one session can
take frames over HTTP and zenoh at once.

Sessions are created over zenoh with the ``voxfusion/@v1/sessions/create`` queryable (``SessionCreate``
JSON payload, the server API key as attachment when the server has one) or over HTTP; either way the
token it returns opens the session's zenoh keys (sent as the attachment of every put and query).

Threads and order (nothing slow ever runs on a zenoh thread):

* ``sessions/*/frames`` (subscriber for ``put``, queryable for ``get``): the callback only checks the
  token (cached per session after the first check; constant-time compare) and appends the bytes to the
  session's bounded FIFO (``ingest_queue_frames``). One worker thread per session takes them in order
  and calls ``manager.submit_frame_bytes`` (decode, validate, durable record, enqueue: the HTTP path).
  When the engine's own queue is full (429) the worker waits and retries (up to ``queue_full_retry_s``),
  which stalls only that session. A ``get`` is answered with ``FrameAccepted`` JSON once recorded; a
  ``put`` is acknowledged on ``sessions/<id>/acks``. Acks published by that worker use congestion control
  ``BLOCK`` (an ack is never silently dropped; a slow ack subscriber stalls only its own session's worker);
  refusals answered straight from a zenoh callback (wrong token, unknown session) use ``DROP`` so that no
  subscriber can stall the callback thread. A client that ``put``s frames must itself put with ``BLOCK``:
  zenoh's default for ``put`` is ``DROP``, which discards frames when the link's queue is full.
* **When a session's FIFO is full** the new frame is refused at once: a ``get`` gets an error reply with
  status 429, a ``put`` is dropped, logged, counted (``zenoh_frames_dropped_total``) and an error ack
  with status 429 is published. Frames already queued keep their order; nothing blocks.
* Bad frames (malformed message, wrong token, unknown or finished session) are logged, counted
  (``zenoh_frames_rejected_total{status}``) and answered with an error; they never stop the bridge.
* Every other query (``render``, ``mesh``, ``voxels``, ``status``, ``trajectory``, ``poses/latest``,
  ``create``) runs on a small thread pool (``query_workers``) and is answered from there; ``finish``
  (which waits for the final mapping) runs on a thread of its own.
* Poses: a listener per session publishes each tracked pose (``PoseOut`` JSON) on ``sessions/<id>/poses``
  from the session's tracking thread (zenoh's default congestion control ``DROP``: a slow subscriber can
  never stall tracking).
* Liveliness: ``voxfusion/@v1/servers/<zenoh id>`` while the bridge runs, ``voxfusion/@v1/sessions/<id>``
  while a session is created or running. A sync thread notices sessions created over HTTP (every
  ``sync_interval_s``) and attaches their pose publisher and token.

Example (what the app's lifespan does)::

    bridge = ZenohBridge(manager, settings.zenoh_config)
    bridge.start()
    ...
    bridge.close()
"""

from __future__ import annotations

import hmac
import json
import logging
import queue
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from voxfusion.clients.zenoh_config import (
    config_authenticates,
    ensure_zenoh_secrets,
    load_zenoh_config,
    non_loopback_endpoints,
    require_zenoh,
)
from voxfusion.clients.zenoh_keys import (
    CREATE_KEY,
    PREFIX,
    parse_session_key,
    server_liveliness_key,
    session_key,
    session_liveliness_key,
)
from voxfusion.core.errors import ConfigError, ValidationError, VoxFusionError
from voxfusion.proto import FrameDecodeError, read_header
from voxfusion.proto.schemas import FrameAccepted, RenderRequest, SessionCreate, SessionCreated, SessionState

from .errors import QueueFullError, ServerError, error_status
from .manager import SessionManager
from .outputs import tum_text

__all__ = ["ZenohBridge", "BridgeOptions"]

log = logging.getLogger("voxfusion.server.zenoh")

_LIVE_STATES = (SessionState.created, SessionState.running)


@dataclass(frozen=True)
class BridgeOptions:
    """Tuning of :class:`ZenohBridge`."""

    ingest_queue_frames: int = 64
    """Frames a session's zenoh FIFO holds before new ones are refused with 429 (see the module docstring)."""
    queue_full_retry_s: float = 60.0
    """How long a session's worker retries a frame the engine's queue refuses (429) before giving up."""
    query_workers: int = 4
    """Threads answering queries (render, mesh, status, finish, create, ...)."""
    sync_interval_s: float = 0.5
    """How often sessions created over HTTP are picked up (pose publisher, liveliness token)."""
    worker_idle_s: float = 30.0
    """A session's ingest thread exits after this long without frames (a new one starts on demand)."""


class _ShuttingDownError(ServerError):
    """The bridge is closing: a frame still queued, or a query arriving now, is refused (503)."""

    status = 503

    def __init__(self) -> None:
        super().__init__("the server is shutting down; retry against a running server", None)


def _error_body(exc: BaseException) -> tuple[int, dict[str, Any]]:
    status = error_status(exc)
    if isinstance(exc, ServerError):
        return status, {"status": status, "detail": exc.detail, "field": exc.field}
    if isinstance(exc, ValidationError):
        return status, {"status": status, "detail": str(exc), "field": exc.field}
    if isinstance(exc, VoxFusionError):
        return status, {"status": status, "detail": str(exc), "field": None}
    return 500, {"status": 500, "detail": f"internal error: {type(exc).__name__}: {exc}", "field": None}


def _attachment_text(att: Any) -> str | None:
    if att is None:
        return None
    try:
        return att.to_bytes().decode("utf-8").strip() or None
    except UnicodeDecodeError:
        return None


class _Ingest:
    """One session's FIFO of frames received over zenoh, and the thread feeding them to the manager."""

    def __init__(self, bridge: ZenohBridge, session_id: str) -> None:
        self.bridge = bridge
        self.session_id = session_id
        self.queue: queue.Queue[tuple[bytes, Any]] = queue.Queue(maxsize=bridge.options.ingest_queue_frames)
        self.verified_token: str | None = None
        self.thread: threading.Thread | None = None


class ZenohBridge:
    """Serves a :class:`SessionManager` over zenoh (module docstring).

    Args:
        manager: the server's session manager (opened).
        config_path: zenoh JSON5 config; ``None``: ``configs/zenoh/server.json5``.
        options: tuning (queue sizes, threads).
        listen: replaces the config's ``listen/endpoints`` (e.g. ``["tcp/127.0.0.1:7448"]``).
        secrets: a folder for the LAN setup (:func:`~voxfusion.clients.zenoh_config.ensure_zenoh_secrets`):
            credentials generated there once, the server config rendered from ``configs/zenoh/server-lan.json5``
            (authentication + access control), and ``client.json5`` for clients. Excludes ``config_path``.
        insecure: allow listening beyond loopback without authentication (a network you trust).
    """

    def __init__(self, manager: SessionManager, config_path: str | Path | None = None, *,
                 options: BridgeOptions | None = None, listen: list[str] | None = None,
                 secrets: str | Path | None = None, insecure: bool = False) -> None:
        self.manager = manager
        self.options = options or BridgeOptions()
        if secrets is not None and config_path is not None:
            raise ConfigError("zenoh_secrets", "give a zenoh config file or a secrets folder, not both")
        self.config_path = config_path
        self.secrets = None if secrets is None else ensure_zenoh_secrets(secrets)
        if self.secrets is not None:
            self.config_path = self.secrets.server_config
            log.info("zenoh: authenticated LAN setup from %s; clients use %s", self.secrets.folder,
                     self.secrets.client_config)
        self._insecure = insecure
        self._listen = listen
        self._z: Any = None
        self.server_id: str | None = None
        self._lock = threading.Lock()
        self._ingest: dict[str, _Ingest] = {}
        self._attached: dict[str, tuple[Any, Any, Any]] = {}  # id -> (pose publisher, listener, token | None)
        self._entities: list[Any] = []
        self._pool: ThreadPoolExecutor | None = None
        self._stop = threading.Event()
        self._sync: threading.Thread | None = None
        self._closed = False

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the zenoh session, declare every key, start the sync thread.

        Raises:
            ConfigError: the config cannot be loaded or zenoh cannot open it (e.g. the port is taken).
        """
        z = require_zenoh()
        cfg = load_zenoh_config(self.config_path, "server", listen=self._listen)
        exposed = non_loopback_endpoints(cfg)
        if exposed and not config_authenticates(cfg) and not self._insecure:
            raise ConfigError("zenoh_listen", f"zenoh would listen on {', '.join(exposed)} without authentication: "
                                              "any peer on that network could read session tokens, poses and ids. "
                                              "Use --zenoh-secrets DIR (credentials + access control; clients use "
                                              "DIR/client.json5), a config of your own with transport/auth, or "
                                              "--zenoh-insecure on a network you trust")
        try:
            self._z = z.open(cfg)  # type: ignore[attr-defined]
        except Exception as e:  # zenoh.ZError: e.g. address already in use
            raise ConfigError("zenoh_config", f"cannot open the zenoh session: {e}") from e
        self.server_id = str(self._z.zid())
        cb = z.handlers.Callback  # type: ignore[attr-defined]
        frames = f"{PREFIX}/sessions/*/frames"
        try:
            self._entities = [
                self._z.declare_subscriber(frames, cb(self._on_frame_put)),
                self._z.declare_queryable(frames, cb(self._on_frame_query)),
                self._z.declare_queryable(CREATE_KEY, cb(self._on_create)),
                self._z.liveliness().declare_token(server_liveliness_key(self.server_id)),
            ]
            for verb in ("render", "mesh", "voxels", "status", "trajectory", "poses/latest", "finish"):
                self._entities.append(self._z.declare_queryable(f"{PREFIX}/sessions/*/{verb}", cb(self._on_query)))
        except Exception as e:
            self._z.close()
            self._z = None
            raise ConfigError("zenoh_config", f"cannot declare the bridge's keys: {e}") from e
        self._pool = ThreadPoolExecutor(max_workers=self.options.query_workers, thread_name_prefix="voxfusion-zq")
        self._stop.clear()
        self._sync = threading.Thread(target=self._sync_loop, name="voxfusion-zenoh-sync", daemon=True)
        self._sync.start()
        self.manager.zenoh_running = True
        log.info("zenoh bridge %s serving %s/** (config %s)", self.server_id, PREFIX,
                 self.config_path or "configs/zenoh/server.json5")

    def close(self) -> None:
        """Stop: queued frames not yet recorded are refused (503), listeners removed, zenoh closed."""
        if self._closed or self._z is None:
            return
        self._closed = True
        self._stop.set()
        if self._sync is not None:
            self._sync.join(timeout=5)
        with self._lock:
            ingests = list(self._ingest.values())
            attached = list(self._attached)
        for ing in ingests:
            if ing.thread is not None:
                ing.thread.join(timeout=10)
        for sid in attached:
            self._detach(sid)
        for ent in self._entities:
            ent.undeclare()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        self._z.close()
        self.manager.zenoh_running = False
        log.info("zenoh bridge %s closed", self.server_id)

    def __enter__(self) -> ZenohBridge:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --------------------------------------------------------------------------- bookkeeping
    def _count(self, name: str, label: str = "") -> None:
        self.manager.counters.add(name, label)

    def _attach(self, session_id: str, live: bool) -> None:
        """Publish the session's poses; hold its liveliness token while it is live (created / running)."""
        with self._lock:
            if self._closed:
                return
            entry = self._attached.get(session_id)
            if entry is None:
                pub = self._z.declare_publisher(session_key(session_id, "poses"), encoding="application/json")

                def listener(pose: Any, _pub: Any = pub) -> None:
                    _pub.put(pose.model_dump_json())

                self.manager.add_pose_listener(session_id, listener)
                entry = (pub, listener, None)
            pub, listener, token = entry
            if live and token is None:
                token = self._z.liveliness().declare_token(session_liveliness_key(session_id))
            elif not live and token is not None:
                token.undeclare()
                token = None
            self._attached[session_id] = (pub, listener, token)

    def _detach(self, session_id: str) -> None:
        """Stop publishing a session that no longer holds an engine (finished, failed, deleted)."""
        with self._lock:
            entry = self._attached.pop(session_id, None)
            ing = self._ingest.get(session_id)
            if ing is not None and (ing.thread is None or not ing.thread.is_alive()) and ing.queue.empty():
                del self._ingest[session_id]
        if entry is None:
            return
        pub, listener, token = entry
        self.manager.remove_pose_listener(session_id, listener)
        if token is not None:
            token.undeclare()
        pub.undeclare()

    def _sync_loop(self) -> None:
        while not self._stop.wait(self.options.sync_interval_s):
            try:
                self.sync_sessions()
            except Exception:  # noqa: BLE001 - keep syncing; the next round may succeed
                log.exception("zenoh bridge: session sync failed")

    def sync_sessions(self) -> None:
        """Attach sessions created over HTTP; drop the liveliness token of sessions that are no longer live
        (finishing) and detach those that hold no engine any more (finished, failed, deleted)."""
        statuses = {s.id: s.state for s in self.manager.open_statuses()}
        with self._lock:
            known = set(self._attached)
        for sid, state in statuses.items():
            live = state in _LIVE_STATES
            with self._lock:
                entry = self._attached.get(sid)
            if entry is None or (entry[2] is not None) != live:
                self._attach(sid, live=live)
        for sid in known - set(statuses):
            self._detach(sid)

    # -------------------------------------------------------------------------------- frames
    def _check_frame_token(self, session_id: str, token: str | None) -> _Ingest:
        with self._lock:
            ing = self._ingest.get(session_id)
        if ing is not None and token is not None and ing.verified_token is not None \
                and hmac.compare_digest(token.encode("utf-8"), ing.verified_token.encode("utf-8")):
            return ing
        self.manager.check_token(session_id, token)  # raises 404 / 401 / 403
        with self._lock:
            ing = self._ingest.setdefault(session_id, _Ingest(self, session_id))
            ing.verified_token = token
        return ing

    def _enqueue(self, key: str, data: bytes, token: str | None, query: Any) -> None:
        """Hand one frame to its session's FIFO (runs on a zenoh callback thread: never blocks)."""
        self._count("zenoh_frames_received_total")
        session_id: str | None = None
        try:
            session_id, _ = parse_session_key(key)
            ing = self._check_frame_token(session_id, token)
            try:
                ing.queue.put_nowait((data, query))
            except queue.Full:
                self._count("zenoh_frames_dropped_total")
                raise QueueFullError(f"session {session_id}: {self.options.ingest_queue_frames} frames are waiting in "
                                "the zenoh ingest queue; slow down") from None
            with self._lock:
                if ing.thread is None or not ing.thread.is_alive():
                    ing.thread = threading.Thread(target=self._ingest_loop, args=(ing,),
                                                  name=f"voxfusion-zin-{session_id[:8]}", daemon=True)
                    ing.thread.start()
        except ValueError as e:  # a key that is not sessions/<id>/frames (wildcard id, ...)
            self._refuse(key, session_id, data, query, ServerError(str(e), "key", None), from_callback=True)
        except Exception as e:  # noqa: BLE001 - every refusal is answered, none stops the bridge
            self._refuse(key, session_id, data, query, e, from_callback=True)

    def _on_frame_put(self, sample: Any) -> None:
        self._enqueue(str(sample.key_expr), sample.payload.to_bytes(), _attachment_text(sample.attachment), None)

    def _on_frame_query(self, query: Any) -> None:
        payload = query.payload
        self._enqueue(str(query.key_expr), payload.to_bytes() if payload is not None else b"",
                      _attachment_text(query.attachment), query)

    def _ingest_loop(self, ing: _Ingest) -> None:
        key = session_key(ing.session_id, "frames")
        idle_since = time.monotonic()
        while True:
            try:
                data, query = ing.queue.get(timeout=0.25)
            except queue.Empty:
                with self._lock:
                    if self._closed or (ing.queue.empty()
                                        and time.monotonic() - idle_since > self.options.worker_idle_s):
                        ing.thread = None
                        return
                continue
            if self._closed:  # shutting down: what is still queued was never acknowledged
                self._refuse(key, ing.session_id, data, query, _ShuttingDownError())
                continue
            self._submit(ing.session_id, data, query)
            idle_since = time.monotonic()

    def _submit(self, session_id: str, data: bytes, query: Any) -> None:
        key = session_key(session_id, "frames")
        deadline = time.monotonic() + self.options.queue_full_retry_s
        wait_s = 0.005
        while True:
            try:
                seq = self.manager.submit_frame_bytes(session_id, data)
                break
            except QueueFullError as e:
                if time.monotonic() >= deadline or self._closed:
                    self._refuse(key, session_id, data, query, e)
                    return
                time.sleep(wait_s)  # stalls only this session's worker
                wait_s = min(0.05, wait_s * 2)
            except Exception as e:  # noqa: BLE001 - a bad frame is answered, the worker goes on
                self._refuse(key, session_id, data, query, e)
                return
        self._count("zenoh_frames_accepted_total")
        body = FrameAccepted(seq=seq, session=session_id).model_dump_json()
        if query is not None:
            self._reply(query, key, body.encode("utf-8"))
        else:
            self._publish_ack(session_id, {"ok": True, "seq": seq, "session": session_id}, block=True)
        self._attach(session_id, live=True)

    def _publish_ack(self, session_id: str, ack: dict[str, Any], *, block: bool) -> None:
        """Publish one ``FrameAck`` on ``sessions/<id>/acks`` (``block``: congestion control BLOCK, else DROP)."""
        z = require_zenoh()
        cc = z.CongestionControl.BLOCK if block else z.CongestionControl.DROP
        self._z.put(session_key(session_id, "acks"), json.dumps(ack), congestion_control=cc)

    def _refuse(self, key: str, session_id: str | None, data: bytes, query: Any, exc: BaseException,
                *, from_callback: bool = False) -> None:
        status, body = _error_body(exc)
        self._count("zenoh_frames_rejected_total", str(status))
        seq = None
        try:
            seq = read_header(data).seq
        except (FrameDecodeError, TypeError):
            pass
        log.warning("zenoh frame on %s refused (%d): %s", key, status, body["detail"])
        if query is not None:
            self._reply_err(query, body)
        elif session_id is not None:
            try:
                self._publish_ack(session_id, {"ok": False, "seq": seq, "session": session_id, **body},
                                  block=not from_callback)
            except Exception:  # noqa: BLE001 - the session is closing
                log.debug("could not publish the refusal ack", exc_info=True)

    # ------------------------------------------------------------------------------- queries
    def _reply(self, query: Any, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        try:
            if attachment is not None:
                query.reply(key, payload, attachment=attachment)
            else:
                query.reply(key, payload)
        except Exception:  # noqa: BLE001 - the querier went away
            log.debug("zenoh reply on %s failed", key, exc_info=True)
        finally:
            query.drop()

    def _reply_err(self, query: Any, body: dict[str, Any]) -> None:
        try:
            query.reply_err(json.dumps(body), encoding="application/json")
        except Exception:  # noqa: BLE001 - the querier went away
            log.debug("zenoh error reply failed", exc_info=True)
        finally:
            query.drop()

    def _run_query(self, query: Any, fn: Any, *, own_thread: bool = False) -> None:
        """Answer ``query`` with ``fn`` on the query pool (``own_thread``: on a thread of its own, for work
        that may take minutes, such as finishing a session, so it never holds a pool thread)."""
        pool = self._pool
        if pool is None or self._closed:
            self._reply_err(query, _error_body(_ShuttingDownError())[1])
            return

        def job() -> None:
            try:
                fn()
            except Exception as e:  # noqa: BLE001 - answered as an error reply
                status, body = _error_body(e)
                if status >= 500:
                    log.exception("zenoh query %s failed", query.key_expr)
                self._count("zenoh_queries_failed_total", str(status))
                self._reply_err(query, body)

        if own_thread:
            threading.Thread(target=job, name="voxfusion-zq-long", daemon=True).start()
            return
        try:
            pool.submit(job)
        except RuntimeError:  # pool shut down between the check and the submit
            self._reply_err(query, _error_body(_ShuttingDownError())[1])

    def _on_create(self, query: Any) -> None:
        def create() -> None:
            if str(query.key_expr) != CREATE_KEY:  # a wildcard query that happens to match: create nothing
                raise ServerError(f"creating a session needs a query on {CREATE_KEY} exactly, got "
                                  f"{query.key_expr}", "key")
            self.manager.check_api_key(_attachment_text(query.attachment))
            raw = query.payload.to_bytes() if query.payload is not None else b""
            try:
                body = SessionCreate.model_validate_json(raw or b"{}")
            except ValueError as e:
                raise ValidationError("body", f"not a SessionCreate JSON object: {e}") from e
            sid, token = self.manager.create_session(body.name, body.config, preset=body.preset, mode=body.mode)
            self._attach(sid, live=True)
            self._count("zenoh_sessions_created_total")
            self._reply(query, CREATE_KEY, SessionCreated(id=sid, token=token).model_dump_json().encode("utf-8"))

        self._run_query(query, create)

    def _on_query(self, query: Any) -> None:
        key = str(query.key_expr)

        def answer() -> None:
            try:
                sid, verb = parse_session_key(key)
            except ValueError as e:
                raise ServerError(f"{e}: ask for one session's key, without wildcards", "key") from None
            self.manager.check_token(sid, _attachment_text(query.attachment))
            fmt = query.parameters.get("format")
            if verb == "status":
                out: bytes = self.manager.status(sid).model_dump_json().encode("utf-8")
            elif verb == "poses/latest":
                out = self.manager.latest_pose(sid).model_dump_json().encode("utf-8")
            elif verb == "trajectory":
                traj = self.manager.trajectory(sid)
                if fmt in (None, "json"):
                    out = traj.model_dump_json().encode("utf-8")
                elif fmt == "tum":
                    out = tum_text(traj.poses).encode("utf-8")
                else:
                    raise ValidationError("format", f"unknown trajectory format {fmt!r}; use json or tum")
            elif verb == "render":
                raw = query.payload.to_bytes() if query.payload is not None else b""
                try:
                    req = RenderRequest.model_validate_json(raw)
                except ValueError as e:
                    raise ValidationError("body", f"not a RenderRequest JSON object: {e}") from e
                rendered = self.manager.render(sid, req)
                self._reply(query, key, rendered.body, json.dumps(rendered.headers).encode("utf-8"))
                return
            elif verb in ("mesh", "voxels"):
                if verb == "mesh":
                    data, version = self.manager.mesh_bytes(sid, fmt or "ply")
                else:
                    data, version = self.manager.voxels_bytes(sid, fmt or "npz")
                meta = {"format": fmt or ("ply" if verb == "mesh" else "npz"), "map_version": version}
                self._reply(query, key, data, json.dumps(meta).encode("utf-8"))
                return
            elif verb == "finish":
                out = self.manager.finish(sid).model_dump_json().encode("utf-8")
                self._detach(sid)
            else:  # not declared; kept for completeness
                raise ServerError(f"unknown key {verb!r}", "key")
            self._reply(query, key, out)

        self._run_query(query, answer, own_thread=key.endswith("/finish"))
