"""The HTTP client of the VoxFusion server (httpx).

Example::

    from voxfusion.clients import Client

    with Client("http://127.0.0.1:8000", api_key=None) as client:
        session = client.create_session("desk", ["tracking.iters=10"], mode="offline")
        for frame in capture.frames():
            client.send_frame_async(frame)          # pipelined, in order, backpressure at max_in_flight
        print(client.viewer_url)                     # the live viewer page in a browser
        client.finish()
        client.download_mesh("out/mesh.ply")
        poses = client.trajectory()

Every error answer becomes a :class:`~voxfusion.clients.ServerError` with the server's status, detail
and offending field; a server that cannot be reached raises :class:`~voxfusion.clients.TransportError`.
"""

from __future__ import annotations

import time
from concurrent.futures import Future
from typing import Any
from urllib.parse import quote

import httpx

from voxfusion.proto import MEDIA_TYPE
from voxfusion.proto.api_extra import SessionStatusOut
from voxfusion.proto.schemas import (
    FrameAccepted,
    RenderRequest,
    SessionCreate,
    SessionCreated,
)

from .base import BaseClient, EncodeOptions, _Sender
from .errors import ClientError, ServerError, TransportError, server_error_from_body

__all__ = ["Client", "viewer_url"]

_QUERY_PATHS = {
    "status": "",
    "poses/latest": "/poses/latest",
    "trajectory": "/poses",
    "mesh": "/mesh",
    "voxels": "/voxels",
}


def viewer_url(server_url: str, session_id: str, token: str) -> str:
    """The live viewer page of a session: ``<server>/sessions/<id>/view?token=<token>`` (the one place this
    link is made; ``scripts/demo.sh`` prints it through here too).

    The token is part of the link (as for the pose WebSocket's ``?token=``): whoever has the link can watch
    the session, so share it like the token itself.

    Example::

        viewer_url("http://127.0.0.1:8000/", "3f2a...", "tok")
        # -> "http://127.0.0.1:8000/sessions/3f2a.../view?token=tok"
    """
    return f"{server_url.rstrip('/')}/sessions/{quote(session_id, safe='')}/view?token={quote(token, safe='')}"


class Client(BaseClient):
    """VoxFusion over HTTP.

    Args:
        url: server base URL, e.g. ``http://127.0.0.1:8000``.
        token: the session token (with ``session_id``, to use an existing session).
        api_key: the server API key, when the server requires one to create sessions.
        session_id: an existing session to attach to.
        encode: how frames are encoded.
        max_in_flight: frames ``send_frame_async`` queues before the caller blocks.
        retry_queue_full_s: how long ``send_frame`` keeps retrying a frame the server answers 429 (queue
            full) to, honouring ``Retry-After`` (capped at 0.5 s per wait); 0 = raise at once.
        timeout_s: per-request timeout.
    """

    def __init__(self, url: str = "http://127.0.0.1:8000", *, token: str | None = None,
                 api_key: str | None = None, session_id: str | None = None, encode: EncodeOptions | None = None,
                 max_in_flight: int = 8, retry_queue_full_s: float = 60.0, timeout_s: float = 60.0) -> None:
        self.url = url.rstrip("/")
        self.api_key = api_key
        self.retry_queue_full_s = float(retry_queue_full_s)
        self._http = httpx.Client(base_url=self.url, timeout=timeout_s)
        self._sender: _Sender | None = None
        super().__init__(token=token, session_id=session_id, encode=encode, max_in_flight=max_in_flight)

    # ----------------------------------------------------------------------------------- plumbing
    @property
    def session_url(self) -> str:
        """``<url>/sessions/<id>``."""
        return f"{self.url}/sessions/{self.session.id}"

    @property
    def mesh_url(self) -> str:
        """The URL a plain ``curl -H 'Authorization: Bearer <token>'`` downloads the mesh from."""
        return f"{self.session_url}/mesh"

    @property
    def viewer_url(self) -> str:
        """The current session's live viewer page (:func:`viewer_url`; it carries the session token)."""
        return viewer_url(self.url, self.session.id, self.session.token)

    def server_device(self) -> str:
        """The torch device the server runs sessions on (``cpu``, ``cuda``, ...), from ``GET /healthz``.

        Raises:
            ClientError: the answer names no device (not a VoxFusion server?).
        """
        try:
            device = self._request("GET", "/healthz").json().get("device")
        except (ValueError, AttributeError):
            device = None
        if not isinstance(device, str) or not device:
            raise ClientError(f"{self.url}/healthz names no device: is this a VoxFusion server?")
        return device

    def _auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.session.token}"}

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            resp = self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as e:
            raise TransportError(f"{method} {self.url}{path}: no answer in time ({e})") from e
        except httpx.HTTPError as e:
            raise TransportError(f"{method} {self.url}{path}: {e}") from e
        if resp.status_code >= 400:
            err = server_error_from_body(resp.status_code, resp.content)
            err.retry_after_s = _retry_after(resp)
            raise err
        return resp

    # ------------------------------------------------------------------------------- primitives
    def _create(self, body: SessionCreate) -> SessionCreated:
        headers = {"X-API-Key": self.api_key} if self.api_key else {}
        resp = self._request("POST", "/sessions", content=body.model_dump_json(exclude_none=True),
                             headers={"Content-Type": "application/json", **headers})
        return SessionCreated.model_validate_json(resp.content)

    def _send_message(self, data: bytes, seq: int) -> int:
        path = f"/sessions/{self.session.id}/frames"
        headers = {**self._auth(), "Content-Type": MEDIA_TYPE}
        deadline = time.monotonic() + self.retry_queue_full_s
        while True:
            try:
                resp = self._request("POST", path, content=data, headers=headers)
                break
            except ServerError as e:
                if e.status != 429 or time.monotonic() >= deadline:
                    raise
                time.sleep(min(0.5, e.retry_after_s or 0.1))
        return FrameAccepted.model_validate_json(resp.content).seq

    def _send_message_async(self, data: bytes, seq: int) -> Future[int]:
        if self._sender is None:
            self._sender = _Sender(self._send_message, self.max_in_flight)
        return self._sender.submit(data, seq)

    def flush(self) -> None:
        if self._sender is not None:
            self._sender.join()

    def _query_bytes(self, verb: str, params: dict[str, str] | None = None) -> bytes:
        path = f"/sessions/{self.session.id}{_QUERY_PATHS[verb]}"
        return self._request("GET", path, params=params or None, headers=self._auth()).content

    def _render(self, req: RenderRequest) -> tuple[bytes, dict[str, str]]:
        resp = self._request("POST", f"/sessions/{self.session.id}/render", content=req.model_dump_json(),
                             headers={**self._auth(), "Content-Type": "application/json"})
        return resp.content, dict(resp.headers)

    def _finish(self, timeout_s: float) -> SessionStatusOut:
        self._request("POST", f"/sessions/{self.session.id}/finish", headers=self._auth(),
                      timeout=timeout_s + 5.0)
        return self.wait_until_done(timeout_s)

    def trajectory_tum(self) -> str:
        """The session's poses as TUM text (``timestamp tx ty tz qx qy qz qw``)."""
        return self._query_bytes("trajectory", {"format": "tum"}).decode("utf-8")

    def close(self) -> None:
        if self._sender is not None:
            self._sender.join()
            self._sender.close()
            self._sender = None
        self._http.close()


def _retry_after(resp: httpx.Response) -> float | None:
    value = resp.headers.get("Retry-After")
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None
