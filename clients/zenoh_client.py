"""The zenoh client of the VoxFusion server: the same verbs as the HTTP :class:`~voxfusion.clients.Client`.

Frames go out as zenoh queries on ``voxfusion/@v1/sessions/<id>/frames`` carrying the frame message as
payload and the session token as attachment; the server answers each once the frame is durably recorded
(the zenoh equivalent of HTTP's 202). Queries from one client reach the server in order, so frames keep
their order, and ``send_frame_async`` keeps up to ``max_in_flight`` of them outstanding at once. (The
server also takes plain ``put``s on that key, answering on ``.../acks``: see ``clients/zenoh_keys.py``.)
Poses can also be followed as they are tracked with :meth:`ZenohClient.subscribe_poses`.

Example::

    from voxfusion.clients import ZenohClient

    with ZenohClient() as client:                  # configs/zenoh/client.json5: tcp/127.0.0.1:7447
        client.create_session("desk", {"tracking": {"iters": 10}})
        sub = client.subscribe_poses(lambda pose: print(pose.seq, pose.T_world_cam[0][3]))
        for frame in capture.frames():
            client.send_frame_async(frame)
        client.finish()
        client.download_mesh("mesh.ply")
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any

from voxfusion.proto.api_extra import SessionStatusOut
from voxfusion.proto.schemas import FrameAccepted, PoseOut, RenderRequest, SessionCreate, SessionCreated

from .base import BaseClient, EncodeOptions
from .errors import ServerError, TransportError, server_error_from_body
from .zenoh_config import load_zenoh_config, require_zenoh
from .zenoh_keys import CREATE_KEY, SERVERS_LIVELINESS, SESSIONS_LIVELINESS, session_key

__all__ = ["ZenohClient", "ZenohReply"]

zenoh: Any = require_zenoh()


class ZenohReply:
    """The successful reply of a query: ``payload`` bytes and the attachment (``None`` if absent)."""

    __slots__ = ("payload", "attachment")

    def __init__(self, payload: bytes, attachment: bytes | None) -> None:
        self.payload = payload
        self.attachment = attachment


class _Collect:
    """Gathers the replies of one query; resolves ``future`` when zenoh closes the query."""

    def __init__(self, what: str, future: Future[ZenohReply]) -> None:
        self.what = what
        self.future = future
        self.ok: ZenohReply | None = None
        self.error: ServerError | None = None

    def on_reply(self, reply: Any) -> None:
        sample = reply.ok
        if sample is not None:
            if self.ok is None:
                att = sample.attachment
                self.ok = ZenohReply(sample.payload.to_bytes(), att.to_bytes() if att is not None else None)
        elif self.error is None:
            self.error = server_error_from_body(500, reply.err.payload.to_bytes())

    def on_done(self) -> None:
        if self.future.done():
            return
        if self.ok is not None:  # several servers: one knows the session, the others answer 404
            self.future.set_result(self.ok)
        elif self.error is not None:
            self.future.set_exception(self.error)
        else:
            self.future.set_exception(TransportError(f"no VoxFusion server answered {self.what} in time"))


class ZenohClient(BaseClient):
    """VoxFusion over zenoh.

    Args:
        config: zenoh JSON5 config file, or a ``zenoh.Config``; ``None``: ``configs/zenoh/client.json5``.
        connect: replaces the config's ``connect/endpoints`` (e.g. ``["tcp/192.168.1.20:7447"]``).
        token, session_id: attach to an existing session (created over HTTP or zenoh).
        api_key: the server API key, when the server requires one to create sessions.
        encode: how frames are encoded.
        max_in_flight: frames ``send_frame_async`` keeps outstanding before the caller blocks.
        timeout_s: how long a query (frame, render, mesh, ...) waits for its answer.
        wait_for_server_s: how long the constructor waits for a server's liveliness token.

    Raises:
        TransportError: no VoxFusion server is reachable.
    """

    def __init__(self, config: str | Path | Any | None = None, *, connect: list[str] | None = None,
                 token: str | None = None, api_key: str | None = None, session_id: str | None = None,
                 encode: EncodeOptions | None = None, max_in_flight: int = 8, timeout_s: float = 60.0,
                 wait_for_server_s: float = 10.0) -> None:
        if config is None or isinstance(config, (str, Path)):
            config = load_zenoh_config(config, "client", connect=connect)
        elif connect is not None:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        try:
            self._z = zenoh.open(config)
        except zenoh.ZError as e:
            raise TransportError(f"cannot open the zenoh session: {e}. Is the server running and listening there? "
                                 "A server started with --zenoh-secrets DIR accepts only clients with its "
                                 "credentials: use its DIR/client.json5 as the config") from e
        self.api_key = api_key
        self.timeout_s = float(timeout_s)
        self._window: threading.Semaphore | None = None
        self._pending: set[Future[int]] = set()
        self._pending_lock = threading.Lock()
        self._pose_subs: list[Any] = []
        try:
            self.wait_for_server(wait_for_server_s)
            super().__init__(token=token, session_id=session_id, encode=encode, max_in_flight=max_in_flight)
        except BaseException:
            self._z.close()
            raise
        self._window = threading.Semaphore(self.max_in_flight)

    # ------------------------------------------------------------------------------- discovery
    def servers(self, timeout_s: float = 1.0) -> list[str]:
        """Zenoh ids of the VoxFusion servers whose liveliness tokens are visible now."""
        keys = [str(r.ok.key_expr) for r in self._z.liveliness().get(SERVERS_LIVELINESS, timeout=timeout_s)
                if r.ok is not None]
        return sorted(k.rsplit("/", 1)[-1] for k in keys)

    def live_sessions(self, timeout_s: float = 1.0) -> list[str]:
        """Ids of the sessions that are live (created or running) on the reachable servers."""
        keys = [str(r.ok.key_expr) for r in self._z.liveliness().get(SESSIONS_LIVELINESS, timeout=timeout_s)
                if r.ok is not None]
        return sorted(k.rsplit("/", 1)[-1] for k in keys)

    def wait_for_server(self, timeout_s: float = 10.0) -> list[str]:
        """Wait until at least one server is visible; returns their ids.

        Raises:
            TransportError: none within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            found = self.servers(timeout_s=min(1.0, max(0.1, deadline - time.monotonic())))
            if found:
                return found
            if time.monotonic() >= deadline:
                raise TransportError(f"no VoxFusion server visible over zenoh after {timeout_s} s "
                                     f"(liveliness {SERVERS_LIVELINESS}); is `voxfusion serve` running with "
                                     f"zenoh, and does the config connect to it?")
            time.sleep(0.05)

    @property
    def mesh_url(self) -> str:
        """The zenoh key of the current session's mesh (query it with ``?format=ply|glb|obj``)."""
        return session_key(self.session.id, "mesh")

    # ---------------------------------------------------------------------------------- queries
    def _get_async(self, key: str, *, params: dict[str, str] | None = None, payload: bytes | None = None,
                   attachment: bytes | None = None, timeout_s: float | None = None) -> Future[ZenohReply]:
        selector = key if not params else key + "?" + ";".join(f"{k}={v}" for k, v in params.items())
        fut: Future[ZenohReply] = Future()
        collect = _Collect(selector, fut)
        kwargs: dict[str, Any] = {"timeout": timeout_s or self.timeout_s,
                                  "congestion_control": zenoh.CongestionControl.BLOCK}
        if payload is not None:
            kwargs["payload"] = payload
        if attachment is not None:
            kwargs["attachment"] = attachment
        try:
            # indirect=False: the two tiny callbacks run on zenoh's thread; the default (a Python thread per
            # handler, i.e. per query) costs ~1 ms a frame
            self._z.get(selector, zenoh.handlers.Callback(collect.on_reply, collect.on_done, indirect=False),
                        **kwargs)
        except zenoh.ZError as e:
            raise TransportError(f"zenoh query {selector}: {e}") from e
        return fut

    def _get(self, key: str, **kwargs: Any) -> ZenohReply:
        timeout_s = kwargs.get("timeout_s") or self.timeout_s
        try:
            return self._get_async(key, **kwargs).result(timeout=timeout_s + 5.0)
        except FutureTimeout as e:
            raise TransportError(f"no answer to {key} within {timeout_s} s") from e

    def _token(self) -> bytes:
        return self.session.token.encode("utf-8")

    # ------------------------------------------------------------------------------- primitives
    def _create(self, body: SessionCreate) -> SessionCreated:
        reply = self._get(CREATE_KEY, payload=body.model_dump_json(exclude_none=True).encode("utf-8"),
                          attachment=self.api_key.encode("utf-8") if self.api_key else None)
        return SessionCreated.model_validate_json(reply.payload)

    def _send_message_async(self, data: bytes, seq: int) -> Future[int]:
        if self._window is None:
            raise TransportError("the client is not connected")
        self._window.acquire()  # at most max_in_flight outstanding frames: backpressure on the caller
        out: Future[int] = Future()
        with self._pending_lock:
            self._pending.add(out)

        def done(reply_future: Future[ZenohReply]) -> None:
            self._window.release()  # type: ignore[union-attr]
            with self._pending_lock:
                self._pending.discard(out)
            try:
                out.set_result(FrameAccepted.model_validate_json(reply_future.result().payload).seq)
            except BaseException as e:  # noqa: BLE001 - handed to the caller through the future
                out.set_exception(e)

        try:
            fut = self._get_async(session_key(self.session.id, "frames"), payload=data, attachment=self._token())
        except BaseException:
            self._window.release()
            with self._pending_lock:
                self._pending.discard(out)
            raise
        fut.add_done_callback(done)
        return out

    def _send_message(self, data: bytes, seq: int) -> int:
        fut = self._send_message_async(data, seq)
        try:
            return fut.result(timeout=self.timeout_s + 5.0)
        except FutureTimeout as e:
            raise TransportError(f"frame {seq}: no answer within {self.timeout_s} s") from e

    def flush(self) -> None:
        while True:
            with self._pending_lock:
                pending = list(self._pending)
            if not pending:
                return
            for fut in pending:
                try:
                    fut.result(timeout=self.timeout_s + 5.0)
                except Exception:  # noqa: BLE001 - the caller sees it through its own future
                    pass

    def _query_bytes(self, verb: str, params: dict[str, str] | None = None) -> bytes:
        return self._get(session_key(self.session.id, verb), params=params, attachment=self._token()).payload

    def _render(self, req: RenderRequest) -> tuple[bytes, dict[str, str]]:
        reply = self._get(session_key(self.session.id, "render"), payload=req.model_dump_json().encode("utf-8"),
                          attachment=self._token())
        meta = json.loads(reply.attachment) if reply.attachment else {}
        return reply.payload, {str(k): str(v) for k, v in meta.items()}

    def _finish(self, timeout_s: float) -> SessionStatusOut:
        self._get(session_key(self.session.id, "finish"), attachment=self._token(), timeout_s=timeout_s)
        return self.wait_until_done(timeout_s)

    def trajectory_tum(self) -> str:
        """The session's poses as TUM text (``timestamp tx ty tz qx qy qz qw``)."""
        return self._query_bytes("trajectory", {"format": "tum"}).decode("utf-8")

    # ------------------------------------------------------------------------------------ poses
    def subscribe_poses(self, callback: Callable[[PoseOut], None]) -> Any:
        """Call ``callback(pose)`` for every pose the server tracks in the current session from now on.

        Returns once the server knows the subscription (a status query after the declaration: zenoh
        sends declarations ahead of data on a link, so the server has it when it answers). The callback
        runs on a zenoh callback thread: keep it short. Returns the zenoh subscriber (``.undeclare()``
        stops it; :meth:`close` undeclares all).
        """

        def on_sample(sample: Any) -> None:
            callback(PoseOut.model_validate_json(sample.payload.to_bytes()))

        sub = self._z.declare_subscriber(session_key(self.session.id, "poses"), zenoh.handlers.Callback(on_sample))
        self._pose_subs.append(sub)
        self.status()
        return sub

    def close(self) -> None:
        try:
            self.flush()
        finally:
            for sub in self._pose_subs:
                sub.undeclare()
            self._pose_subs.clear()
            self._z.close()
