"""The FastAPI application: :func:`create_app` builds it; heavy objects are built in its lifespan.

Run it with ``voxfusion serve`` (or ``uvicorn --factory voxfusion.server.app:create_app``, settings from the
environment). The OpenAPI docs are at ``/docs``.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool
from starlette.routing import Router
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from voxfusion import __version__

from .api import ROUTERS
from .errors import PayloadTooLargeError, install_exception_handlers
from .manager import SessionManager
from .metrics import HttpStats, route_template
from .openapi import document_errors
from .settings import ServerSettings

__all__ = ["create_app", "BodySizeLimit", "start_zenoh_bridge"]

log = logging.getLogger("voxfusion.server")

_DESCRIPTION = """
Dense RGB-D SLAM (Vox-Fusion) as a service. Create a session, stream frames to it, read poses as they
are tracked, render depth at any pose for AR occlusion, download the mesh.

1. `POST /sessions` -> `{id, token}`; send `Authorization: Bearer <token>` on every session route.
2. `POST /sessions/{id}/frames`: one frame per request (the binary frame message of `proto/README.md`, or
   multipart: JSON metadata + 16-bit PNG depth + JPEG colour). 202 once it is durably recorded.
3. `GET /sessions/{id}/poses`, `/poses/latest`, WebSocket `/poses/stream`; `POST /sessions/{id}/render`.
4. `GET /sessions/{id}/mesh?format=ply|glb|obj`, `/voxels?format=npz|ply`; `POST /sessions/{id}/finish`.

Errors are JSON `{"detail", "field"}`: 400 malformed frame, 401/403 token, 404 unknown session,
409 finished/failed session or nothing to serve yet, 413 too large, 415 unknown encoding,
422 invalid field or a frame no camera produces, 429 ingest queue full (Retry-After) or too many
sessions from one client without an API key, 503 too many sessions; 500 answers are JSON too.
"""


class BodySizeLimit:
    """ASGI middleware: refuse request bodies larger than ``max_bytes`` with 413 (by ``Content-Length`` up
    front, or while a chunked body streams in)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await _json_response(send, 400, {"detail": "invalid Content-Length header", "field": "Content-Length"})
                return
            if declared > self.max_bytes:
                await _json_response(send, 413, {"detail": f"request body is {declared} bytes, more than this "
                                                           f"server's limit of {self.max_bytes}", "field": "body"})
                return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise PayloadTooLargeError(f"request body exceeds this server's limit of {self.max_bytes} bytes",
                                          "body")
            return message

        await self.app(scope, limited_receive, send)


async def _json_response(send: Send, status: int, body: dict[str, Any]) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": data})


class _HttpMetrics:
    """ASGI middleware timing HTTP requests and counting WebSocket connections by route template
    (:func:`~voxfusion.server.metrics.route_template`, matched against the routes ``router`` has at the time,
    so routes and mounts added after the app is built count too)."""

    def __init__(self, app: ASGIApp, stats: HttpStats, router: Router) -> None:
        self.app = app
        self.stats = stats
        self.router = router

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            route = route_template(self.router.routes, scope)
            self.stats.websockets.labels(route).inc()
            with self.stats.websockets_open.labels(route).track_inprogress():
                await self.app(scope, receive, send)
            return
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        route = route_template(self.router.routes, scope)  # before the app runs: mounts rewrite the scope's paths
        status = 500
        t0 = time.perf_counter()

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            self.stats.observe(scope.get("method", ""), route, status, time.perf_counter() - t0)


def start_zenoh_bridge(settings: ServerSettings, manager: SessionManager) -> Any:  # noqa: ANN401 - optional module
    """Start ``voxfusion.server.zenoh_bridge.ZenohBridge`` when enabled; ``None`` when off or unavailable
    (a missing module or ``zenoh`` package is a warning, never an error)."""
    if settings.zenoh is False:
        return None
    try:
        from .zenoh_bridge import ZenohBridge
    except ImportError as e:
        level = logging.WARNING if settings.zenoh else logging.INFO
        log.log(level, "zenoh bridge unavailable (%s); serving HTTP only", e)
        return None
    try:
        bridge = ZenohBridge(manager, settings.zenoh_config,
                             listen=list(settings.zenoh_listen) if settings.zenoh_listen else None,
                             secrets=settings.zenoh_secrets, insecure=settings.zenoh_insecure)
        bridge.start()
    except Exception as e:  # noqa: BLE001 - zenoh is optional: HTTP keeps working
        level = logging.WARNING if settings.zenoh else logging.INFO
        log.log(level, "zenoh bridge failed to start (%s: %s); serving HTTP only", type(e).__name__, e)
        return None
    manager.zenoh_running = True
    log.info("zenoh bridge started")
    return bridge


def create_app(settings: ServerSettings | None = None) -> FastAPI:
    """The voxfusion server app. ``settings`` default: :meth:`ServerSettings.from_env`.

    Nothing heavy happens here: the session manager (database, housekeeping thread) and the zenoh bridge
    are built when the app starts (lifespan) and closed when it stops.
    """
    settings = settings if settings is not None else ServerSettings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        manager = SessionManager(settings)
        await run_in_threadpool(manager.open)
        app.state.manager = manager
        bridge = await run_in_threadpool(start_zenoh_bridge, settings, manager)
        log.info("voxfusion server ready: data in %s, device %s, default preset %s", settings.data_dir,
                 manager.device, manager.default_preset)
        try:
            yield
        finally:
            if bridge is not None:
                await run_in_threadpool(bridge.close)
                manager.zenoh_running = False
            await run_in_threadpool(manager.close)

    app = FastAPI(title="voxfusion", version=__version__, description=_DESCRIPTION, lifespan=lifespan)
    app.state.settings = settings
    app.state.http_stats = HttpStats()
    install_exception_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    document_errors(app)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_frame_bytes)
    app.add_middleware(_HttpMetrics, stats=app.state.http_stats, router=app.router)
    return app
