"""The server's domain errors and their HTTP answers, in one place.

Routes and the :class:`~voxfusion.server.manager.SessionManager` raise domain errors (these, and the
engine's :class:`~voxfusion.core.errors.ValidationError` family); :func:`install_exception_handlers`
maps every one of them to a status and an :class:`~voxfusion.proto.schemas.ErrorOut` body
``{"detail": ..., "field": ...}``:

===========================================  ======  ==========================================
error                                        status  when
===========================================  ======  ==========================================
``FrameEncodingError``                       415     a frame names an encoding we do not know
``FrameValueError``                          422     well-formed frame no camera produces (intrinsics,
                                                     device pose out of reach: ``core.frame_checks``)
``FrameDecodeError`` (anything else)         400     malformed frame message or upload
``UnsupportedMediaTypeError``                415     a ``Content-Type`` the route does not take
``ValidationError`` / ``ConfigError``        422     bad JSON field, unknown config key
FastAPI ``RequestValidationError``           422     request body / query does not match its model
``UnauthorizedError``                        401     no token / API key
``ForbiddenError``                           403     wrong token / API key
``SessionNotFoundError``                     404     unknown (or malformed) session id
``NotReadyError`` / ``MapNotReadyError``     409     nothing to serve yet (no map, no pose)
``SessionConflictError``                     409     the session is finished, finishing or failed
``PayloadTooLargeError``                     413     body or image larger than the server's limits
``QueueFullError``                           429     per-session ingest queue full (``Retry-After``)
``TooManyClientSessionsError``               429     one address holds ``max_sessions_per_client``
                                                    open sessions created without an API key
``TooManySessionsError``                     503     ``max_sessions`` open (``Retry-After``)
``WorkerUnavailableError``                   503     the session's worker is restarting or busy
                                                    (``Retry-After``)
anything else                                500     a bug: JSON ``{"detail", "field": null}`` too
===========================================  ======  ==========================================
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from voxfusion.core.errors import CaptureError, MapNotReadyError, ValidationError, VoxFusionError
from voxfusion.proto import FrameDecodeError, FrameEncodingError, FrameValueError

__all__ = [
    "ServerError",
    "UnauthorizedError",
    "ForbiddenError",
    "SessionNotFoundError",
    "SessionConflictError",
    "NotReadyError",
    "PayloadTooLargeError",
    "UnsupportedMediaTypeError",
    "QueueFullError",
    "TooManySessionsError",
    "TooManyClientSessionsError",
    "WorkerUnavailableError",
    "install_exception_handlers",
    "error_status",
]

log = logging.getLogger("voxfusion.server")


class ServerError(VoxFusionError):
    """A request the server refuses; ``status`` is its HTTP status, ``field`` the offending input."""

    status = 400

    def __init__(self, detail: str, field: str | None = None, headers: dict[str, str] | None = None) -> None:
        self.detail = detail
        self.field = field
        self.headers = headers or {}
        super().__init__(detail)


class UnauthorizedError(ServerError):
    """No credentials were sent (401)."""

    status = 401

    def __init__(self, detail: str, field: str | None = "Authorization") -> None:
        super().__init__(detail, field, {"WWW-Authenticate": "Bearer"})


class ForbiddenError(ServerError):
    """The credentials sent are wrong (403)."""

    status = 403


class SessionNotFoundError(ServerError):
    """No session has this id (404)."""

    status = 404

    def __init__(self, session_id: str) -> None:
        shown = session_id if len(session_id) <= 64 else session_id[:64] + "..."
        super().__init__(f"no session {shown!r}", "session_id")


class SessionConflictError(ServerError):
    """The session's state does not allow this (finished, finishing or failed) (409)."""

    status = 409


class NotReadyError(ServerError):
    """Nothing to serve yet: no frame mapped / tracked (409)."""

    status = 409


class PayloadTooLargeError(ServerError):
    """Body or image exceeds the server's limits (413)."""

    status = 413


class UnsupportedMediaTypeError(ServerError):
    """Content type or encoding the route does not take (415)."""

    status = 415


class QueueFullError(ServerError):
    """The session's ingest queue is full; retry after ``retry_after_s`` (429)."""

    status = 429

    def __init__(self, detail: str, retry_after_s: int = 1) -> None:
        super().__init__(detail, None, {"Retry-After": str(max(1, int(retry_after_s)))})


class TooManySessionsError(ServerError):
    """The server holds ``max_sessions`` open sessions (503)."""

    status = 503

    def __init__(self, detail: str, retry_after_s: int = 30) -> None:
        super().__init__(detail, None, {"Retry-After": str(max(1, int(retry_after_s)))})


class WorkerUnavailableError(ServerError):
    """The session's worker cannot answer now: it is restarting after a crash, or busy past the time limit
    (503, ``Retry-After``)."""

    status = 503

    def __init__(self, detail: str, retry_after_s: int = 2) -> None:
        super().__init__(detail, None, {"Retry-After": str(max(1, int(retry_after_s)))})


class TooManyClientSessionsError(ServerError):
    """One client address holds ``max_sessions_per_client`` open sessions created without an API key (429).

    Not retryable as such: the client must finish or delete one of its sessions (idle ones are closed after
    ``session_idle_timeout_s``), or create sessions with the server's API key.
    """

    status = 429


def error_status(exc: BaseException) -> int:
    """The HTTP status the server answers ``exc`` with (see the module table); 500 for anything else."""
    if isinstance(exc, ServerError):
        return exc.status
    if isinstance(exc, MapNotReadyError):
        return 409
    if isinstance(exc, FrameValueError):
        return 422
    if isinstance(exc, FrameEncodingError):
        return 415
    if isinstance(exc, FrameDecodeError):
        return 400
    if isinstance(exc, ValidationError):
        return 422
    if isinstance(exc, CaptureError):
        return 500
    return 500


def _body(detail: str, field: str | None) -> dict:
    return {"detail": detail, "field": field}


def _pydantic_field(loc: tuple) -> str | None:
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header")]
    return ".".join(parts) or None


def request_error_detail(error: dict) -> tuple[str, str | None]:
    """``(detail, field)`` of one pydantic request error (``RequestValidationError.errors()[i]``): the field's
    dotted path and its message, without pydantic's "Value error, " prefix or the field named twice; a body that is
    not JSON at all is said so (its location is a character offset, not a field)."""
    loc, msg = tuple(error.get("loc", ())), str(error.get("msg", "invalid request"))
    if error.get("type") == "json_invalid":
        at = f" at character {loc[-1]}" if loc and isinstance(loc[-1], int) else ""
        return f"the request body is not valid JSON{at}: {error.get('ctx', {}).get('error', msg)}", None
    field = _pydantic_field(loc)
    msg = msg.removeprefix("Value error, ")
    if field:
        msg = msg.removeprefix(f"{field}: ")
    return (f"{field}: {msg}" if field else msg), field


def install_exception_handlers(app: FastAPI) -> None:
    """Register the handlers that turn domain errors into ``ErrorOut`` JSON answers."""

    @app.exception_handler(ServerError)
    async def _server_error(_: Request, exc: ServerError) -> JSONResponse:
        return JSONResponse(_body(exc.detail, exc.field), status_code=exc.status, headers=exc.headers)

    @app.exception_handler(ValidationError)
    async def _validation_error(_: Request, exc: ValidationError) -> JSONResponse:
        return JSONResponse(_body(str(exc), exc.field), status_code=error_status(exc))

    @app.exception_handler(RequestValidationError)
    async def _request_validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        first = errors[0] if errors else {"loc": (), "msg": "invalid request"}
        detail, field = request_error_detail(first)
        return JSONResponse(_body(detail, field), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        return JSONResponse(_body(str(exc.detail), None), status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(MapNotReadyError)
    async def _map_not_ready(_: Request, exc: MapNotReadyError) -> JSONResponse:
        return JSONResponse(_body(str(exc), None), status_code=409)

    @app.exception_handler(VoxFusionError)
    async def _voxfusion_error(_: Request, exc: VoxFusionError) -> JSONResponse:
        log.exception("internal error: %s", exc)
        return JSONResponse(_body(f"internal error: {exc}", None), status_code=500)

    @app.exception_handler(Exception)
    async def _unexpected_error(_: Request, exc: Exception) -> JSONResponse:
        # Starlette answers with this, then re-raises ``exc`` so that the server logs its traceback; the
        # message is not echoed (it may hold paths or other internals).
        return JSONResponse(_body(f"internal error ({type(exc).__name__}); see the server log", None),
                            status_code=500)
