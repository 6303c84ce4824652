"""Frame ingest: ``POST /sessions/{id}/frames``.

Body, either

* one frame message (``proto/README.md``) with ``Content-Type: application/vnd.voxfusion.frame`` or
  ``application/octet-stream``; or
* ``multipart/form-data`` with parts ``metadata`` (JSON), ``depth``, optional ``color`` and
  ``confidence`` (see :mod:`voxfusion.server.ingest`).

Answer 202 ``{"seq", "session", "duplicate": false, "action": "recorded"}`` once the frame is durably in
the session's recording (fdatasync). A frame whose ``seq`` is already recorded (by either body kind) is
acknowledged with ``{"duplicate": true, "action": "ignored"}`` and ``X-Duplicate: true``: it is neither
recorded nor tracked again, the first copy stands (even when the bytes differ), so retries are safe.

A multipart upload whose images do not match the sizes it declares (``intrinsics`` width and height,
``depth_width`` / ``depth_height``, ``color_width`` / ``color_height``) is refused with 422 naming the part
(``depth``, ``color``, ``confidence``); see :mod:`voxfusion.server.ingest`.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile

from voxfusion.proto import MEDIA_TYPE, FrameDecodeError
from voxfusion.proto.schemas import ErrorOut, FrameAccepted

from ...errors import UnsupportedMediaTypeError
from ...ingest import UploadPart, message_from_multipart
from ..deps import ManagerDep, SessionIdDep

__all__ = ["router", "FRAME_CONTENT_TYPES"]

FRAME_CONTENT_TYPES = (MEDIA_TYPE, "application/octet-stream", "multipart/form-data")

router = APIRouter(tags=["frames"])

_OPENAPI_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
            "multipart/form-data": {"schema": {
                "type": "object", "required": ["metadata", "depth"],
                "properties": {
                    "metadata": {"type": "string", "description": "JSON: seq, timestamp_s, intrinsics "
                                 "{fx, fy, cx, cy, width, height}, depth_encoding, depth_width, depth_height, "
                                 "color_width, color_height, device_pose {convention, matrix}, ..."},
                    "depth": {"type": "string", "format": "binary",
                              "description": "16-bit PNG (mm) or raw float16 / float32 metres, with the "
                                             "intrinsics' aspect ratio"},
                    "color": {"type": "string", "format": "binary",
                              "description": "JPEG or PNG with the intrinsics' aspect ratio (resized to the depth's "
                                             "size, as in the binary format)"},
                    "confidence": {"type": "string", "format": "binary",
                                   "description": "PNG8 or raw u8 at the depth's size"},
                }}},
        },
    }
}


async def _part(form: object, name: str) -> UploadPart | None:
    value = form.get(name)  # type: ignore[attr-defined]
    if value is None:
        return None
    if isinstance(value, UploadFile):
        return UploadPart(await value.read(), (value.content_type or "").split(";")[0].strip().lower())
    return UploadPart(str(value).encode("utf-8"), "")


@router.post("/sessions/{session_id}/frames", status_code=status.HTTP_202_ACCEPTED, response_model=FrameAccepted,
             openapi_extra=_OPENAPI_BODY,
             responses={400: {"model": ErrorOut}, 409: {"model": ErrorOut}, 413: {"model": ErrorOut},
                        415: {"model": ErrorOut}, 422: {"model": ErrorOut}, 429: {"model": ErrorOut},
                        503: {"model": ErrorOut}})
async def post_frame(session_id: SessionIdDep, manager: ManagerDep, request: Request,
                     response: Response) -> FrameAccepted:
    """Record one frame durably and queue it for tracking; 202 with its ``seq`` once it is on disk."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype in (MEDIA_TYPE, "application/octet-stream"):
        data = await request.body()
    elif ctype == "multipart/form-data":
        limit = request.app.state.settings.max_frame_bytes
        async with request.form(max_files=4, max_fields=4, max_part_size=limit) as form:
            metadata = await _part(form, "metadata")
            depth = await _part(form, "depth")
            if metadata is None or depth is None:
                raise FrameDecodeError("metadata" if metadata is None else "depth",
                                       "multipart frames need a 'metadata' part and a 'depth' part")
            color = await _part(form, "color")
            confidence = await _part(form, "confidence")
        data = await run_in_threadpool(message_from_multipart, metadata.data, depth, color, confidence)
    else:
        raise UnsupportedMediaTypeError(f"Content-Type {ctype or '(none)'!r} is not a frame; send one of "
                                   f"{', '.join(FRAME_CONTENT_TYPES)}", "Content-Type")
    seq, duplicate = await run_in_threadpool(manager.submit_frame, session_id, data)
    if duplicate:
        response.headers["X-Duplicate"] = "true"
    return FrameAccepted(seq=seq, session=session_id, duplicate=duplicate,
                         action="ignored" if duplicate else "recorded")
