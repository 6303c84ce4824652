"""The live web viewer: ``GET /sessions/{id}/view?token=...`` and what only it needs.

The page (three.js, bundled by vite from ``server/viewer/``; see ``docs/viewer.md``) is served from the
pre-built ``server/viewer/dist/``: no CDN, it works on a LAN without internet. It reads the session with
the public API (status, poses and their WebSocket, ``/mesh``, ``/mesh/frame``) plus the newest received
frame from the routes here.

The token travels in the page's link (like the pose WebSocket's ``?token=``); the page is only served when
it is right, is never cached, sends no ``Referer`` and removes the token from the address bar once loaded.
"""

from __future__ import annotations

import re
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, Response
from starlette.concurrency import run_in_threadpool

from voxfusion.proto.api_extra import LatestFrameOut
from voxfusion.proto.schemas import ErrorOut

from ...errors import NotReadyError
from ...live_frame import colour_jpeg, depth_preview_png
from ...viewer_assets import VIEWER_DIST
from ..deps import ManagerDep, SessionIdDep

__all__ = ["router"]

_ASSET_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_MEDIA_TYPES = {".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml", ".png": "image/png",
                ".woff2": "font/woff2", ".map": "application/json"}
_PAGE_HEADERS = {
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
                               "style-src 'self' 'unsafe-inline'; base-uri 'none'; frame-ancestors 'none'",
}
_ERRORS = {401: {"model": ErrorOut}, 403: {"model": ErrorOut}, 404: {"model": ErrorOut}, 409: {"model": ErrorOut}}

router = APIRouter(tags=["viewer"], responses=_ERRORS)


@router.get("/sessions/{session_id}/view", response_class=HTMLResponse,
            responses={200: {"content": {"text/html": {}}}, 503: {"model": ErrorOut}})
def view_session(session_id: str, manager: ManagerDep,
                 token: Annotated[str | None, Query(description="The session's token (the page's link carries "
                                                                 "it, like the pose WebSocket's).")] = None
                 ) -> Response:
    """The live viewer page of a session: the mesh growing, the trajectory, the current camera, the
    newest depth / colour frame and the session's counters; finished sessions from their checkpoint."""
    manager.check_token(session_id, token)
    index = VIEWER_DIST / "index.html"
    if not index.is_file():
        raise HTTPException(503, "the web viewer is not built into this installation: run `make viewer` (needs "
                                 "Node.js) and restart the server")
    return HTMLResponse(index.read_text(encoding="utf-8"), headers=_PAGE_HEADERS)


@router.get("/viewer/assets/{name}", include_in_schema=False)
def viewer_asset(name: str) -> Response:
    """A file of the built viewer (content-hashed names: cached for a year)."""
    path = VIEWER_DIST / "assets" / name
    if not _ASSET_NAME.match(name) or path.suffix not in _MEDIA_TYPES or not path.is_file():
        raise HTTPException(404, f"no viewer asset {name!r}")
    return FileResponse(path, media_type=_MEDIA_TYPES[path.suffix],
                        headers={"Cache-Control": "public, max-age=31536000, immutable",
                                 "X-Content-Type-Options": "nosniff"})


@router.get("/sessions/{session_id}/frames/latest", response_model=LatestFrameOut)
async def latest_frame_info(session_id: SessionIdDep, manager: ManagerDep) -> LatestFrameOut:
    """The newest frame the session received: ``seq``, time, depth resolution and intrinsics (for the
    viewer's camera frustum), how much of its depth is valid. 409 before the first frame."""
    latest = await run_in_threadpool(manager.latest_frame, session_id)
    return LatestFrameOut(**latest.info())


def _image(request: Request, seq: int, data: bytes, media_type: str) -> Response:
    etag = f'"f{seq}-{len(data)}"'
    headers = {"ETag": etag, "Cache-Control": "no-cache", "X-Frame-Seq": str(seq)}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    return Response(data, media_type=media_type, headers=headers)


@router.get("/sessions/{session_id}/frames/latest/depth.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
async def latest_depth_preview(session_id: SessionIdDep, manager: ManagerDep, request: Request) -> Response:
    """The newest frame's depth, colour-mapped for people (turbo, 0-6 m, invalid black): a preview, not
    data (the recording and ``/render`` have metric depth)."""
    latest = await run_in_threadpool(manager.latest_frame, session_id)
    data = await run_in_threadpool(depth_preview_png, latest.frame.depth_m)
    return _image(request, latest.seq, data, "image/png")


@router.get("/sessions/{session_id}/frames/latest/colour.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}}})
async def latest_colour(session_id: SessionIdDep, manager: ManagerDep, request: Request) -> Response:
    """The newest frame's colour image at the depth resolution (409 when that frame has no colour)."""
    latest = await run_in_threadpool(manager.latest_frame, session_id)
    if latest.frame.color is None:
        raise NotReadyError(f"frame {latest.seq} of session {session_id} has no colour image", "colour")
    data = await run_in_threadpool(colour_jpeg, latest.frame.color)
    return _image(request, latest.seq, data, "image/jpeg")
