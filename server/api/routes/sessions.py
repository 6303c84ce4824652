"""Sessions: create, list, status, finish, resume, delete."""

from __future__ import annotations

import logging
import threading
from typing import Annotated

from fastapi import APIRouter, Body, Query, Response, status

from voxfusion.proto.api_extra import SessionListOut, SessionStatusOut
from voxfusion.proto.schemas import ErrorOut, SessionCreate, SessionCreated, SessionState

from ..deps import AnonymousClientDep, ApiKeyDep, ManagerDep, SessionIdDep

__all__ = ["router"]

log = logging.getLogger("voxfusion.server")

router = APIRouter(tags=["sessions"], responses={401: {"model": ErrorOut}, 403: {"model": ErrorOut},
                                                 404: {"model": ErrorOut}})


@router.post("/sessions", status_code=status.HTTP_201_CREATED, response_model=SessionCreated,
             responses={422: {"model": ErrorOut}, 429: {"model": ErrorOut}, 503: {"model": ErrorOut}})
def create_session(manager: ManagerDep, _: ApiKeyDep, client: AnonymousClientDep,
                   body: Annotated[SessionCreate | None, Body()] = None) -> SessionCreated:
    """Create a session (engine preset, config overrides, realtime/offline mode); returns its id and its
    bearer token (shown only here). Requires the server API key when one is configured; without one, a
    client beyond loopback may hold ``--max-sessions-per-client`` open sessions (more: 429)."""
    body = body or SessionCreate()
    sid, token = manager.create_session(body.name, body.config, preset=body.preset, mode=body.mode, client=client)
    return SessionCreated(id=sid, token=token)


@router.get("/sessions", response_model=SessionListOut)
def list_sessions(manager: ManagerDep, _: ApiKeyDep) -> SessionListOut:
    """Every session the server knows (also those of earlier runs), with its state and counters."""
    return SessionListOut(sessions=manager.list_sessions())


@router.get("/sessions/{session_id}", response_model=SessionStatusOut)
def get_session(session_id: SessionIdDep, manager: ManagerDep) -> SessionStatusOut:
    """State (created, running, finishing, finished, failed), frame counters, keyframes, voxels, fps,
    latency and the last error of one session."""
    return manager.status(session_id)


@router.post("/sessions/{session_id}/finish", response_model=SessionStatusOut,
             responses={202: {"model": SessionStatusOut}, 409: {"model": ErrorOut}})
def finish_session(session_id: SessionIdDep, manager: ManagerDep, response: Response,
                   wait: Annotated[bool, Query(description="Block until finished (else answer 202 at once).")]
                   = True) -> SessionStatusOut:
    """Stop taking frames, process what is queued, run the final mapping, and save the final
    checkpoint, mesh and trajectory. Idempotent."""
    if wait:
        return manager.finish(session_id)

    def run() -> None:
        try:
            manager.finish(session_id)
        except Exception:  # noqa: BLE001 - the session's state and last_error tell the client
            log.exception("finishing session %s failed", session_id)

    current = manager.status(session_id)
    if current.state != SessionState.finished:
        threading.Thread(target=run, name=f"voxfusion-finish-{session_id[:8]}", daemon=True).start()
        response.status_code = status.HTTP_202_ACCEPTED
    return manager.status(session_id)


@router.post("/sessions/{session_id}/resume", status_code=status.HTTP_202_ACCEPTED, response_model=SessionStatusOut,
             responses={409: {"model": ErrorOut}, 429: {"model": ErrorOut}, 503: {"model": ErrorOut}})
def resume_session(session_id: SessionIdDep, manager: ManagerDep) -> SessionStatusOut:
    """Replay the recording of a session that was open when the server stopped, that was closed for
    idleness (``--session-idle-timeout-s``) or that failed, through a new engine; the session then takes
    frames again. No-op for a running session."""
    return manager.resume(session_id)


@router.delete("/sessions/{session_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_session(session_id: SessionIdDep, manager: ManagerDep) -> Response:
    """Stop the session and delete its metadata, recording and outputs."""
    manager.delete(session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
