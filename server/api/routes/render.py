"""``POST /sessions/{id}/render``: depth rendered from the map at a client's pose (AR occlusion).

Body: :class:`~voxfusion.proto.schemas.RenderRequest` JSON (pose + convention, intrinsics for
``width`` x ``height``, ``format`` ``f16`` or ``png16``, ``with_color``). Answer: one binary body
``depth | mask | color`` with the part lengths in headers (layout: :mod:`voxfusion.server.outputs`).
"""

from __future__ import annotations

from fastapi import APIRouter, Response

from voxfusion.proto.schemas import ErrorOut, RenderRequest

from ..deps import ManagerDep, SessionIdDep

__all__ = ["router"]

router = APIRouter(tags=["render"])


@router.post("/sessions/{session_id}/render", response_class=Response,
             responses={200: {"content": {"application/octet-stream": {}},
                              "description": "depth | mask | color; part lengths in X-Depth-Bytes, X-Mask-Bytes, "
                                             "X-Color-Bytes; X-Width, X-Height, X-Depth-Format, X-Depth-Units, "
                                             "X-Map-Version"},
                        401: {"model": ErrorOut}, 403: {"model": ErrorOut}, 404: {"model": ErrorOut},
                        409: {"model": ErrorOut}, 422: {"model": ErrorOut}})
def render_depth(session_id: SessionIdDep, manager: ManagerDep, body: RenderRequest) -> Response:
    """Render depth (metres as float16, or millimetres as 16-bit PNG), a validity mask and optionally
    colour from the session's newest map at the requested camera pose."""
    out = manager.render(session_id, body)
    return Response(out.body, media_type="application/octet-stream", headers=out.headers)
