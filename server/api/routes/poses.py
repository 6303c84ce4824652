"""Poses: the whole trajectory (JSON or TUM text), the latest pose, and a WebSocket stream.

WebSocket ``/sessions/{id}/poses/stream`` (token as ``?token=`` or ``Authorization: Bearer``): one text
message per tracked frame, the :class:`~voxfusion.proto.schemas.PoseOut` JSON (tracked pose, OpenCV
axes), as tracking produces them; when the session is finished or failed a last message
``{"event": "end", "state": ..., "last_error": ...}`` is sent and the socket closed (code 1000).
Refusals close the socket with 4401 (no token), 4403 (wrong token) or 4404 (unknown session).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Annotated, Literal

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import PlainTextResponse, Response
from starlette.concurrency import run_in_threadpool

from voxfusion.proto.schemas import ErrorOut, PoseOut, SessionState, Trajectory

from ...auth import bearer_token
from ...errors import ServerError
from ...manager import SessionManager
from ...outputs import tum_text
from ..deps import ManagerDep, SessionIdDep

__all__ = ["router"]

router = APIRouter(tags=["poses"], responses={401: {"model": ErrorOut}, 403: {"model": ErrorOut},
                                              404: {"model": ErrorOut}})

_QUEUE_SIZE = 1024


@router.get("/sessions/{session_id}/poses", response_model=Trajectory,
            responses={200: {"content": {"text/plain": {}}, "description": "JSON, or TUM text with format=tum"}})
def get_poses(session_id: SessionIdDep, manager: ManagerDep,
              format: Annotated[Literal["json", "tum"], Query(description="json or tum")] = "json") -> Response:
    """Every estimated pose (camera-to-world, OpenCV axes, metres; keyframe refinements applied), in
    tracking order: JSON, or a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``)."""
    traj = manager.trajectory(session_id)
    if format == "tum":
        return PlainTextResponse(tum_text(traj.poses), headers={
            "Content-Disposition": f'attachment; filename="voxfusion-{session_id[:8]}-trajectory.txt"'})
    return Response(traj.model_dump_json(), media_type="application/json")


@router.get("/sessions/{session_id}/poses/latest", response_model=PoseOut, responses={409: {"model": ErrorOut}})
def get_latest_pose(session_id: SessionIdDep, manager: ManagerDep) -> PoseOut:
    """The newest tracked pose (409 before the first frame is tracked)."""
    return manager.latest_pose(session_id)


def _put_latest(queue: asyncio.Queue, pose: PoseOut) -> None:
    if queue.full():  # a slow client loses the oldest poses, never the newest
        with contextlib.suppress(asyncio.QueueEmpty):
            queue.get_nowait()
    queue.put_nowait(pose)


@router.websocket("/sessions/{session_id}/poses/stream")
async def stream_poses(websocket: WebSocket, session_id: str) -> None:
    """Poses as they are tracked (see the module docstring)."""
    manager: SessionManager = websocket.app.state.manager
    token = websocket.query_params.get("token") or bearer_token(websocket.headers.get("authorization"))
    await websocket.accept()
    try:
        await run_in_threadpool(manager.check_token, session_id, token)
    except ServerError as e:
        await websocket.close(code=4000 + e.status, reason=e.detail[:120])
        return
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[PoseOut] = asyncio.Queue(maxsize=_QUEUE_SIZE)

    def listener(pose: PoseOut) -> None:
        loop.call_soon_threadsafe(_put_latest, queue, pose)

    disconnected = asyncio.Event()

    async def read_until_closed() -> None:
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            while True:
                await websocket.receive_text()
        disconnected.set()

    try:
        manager.add_pose_listener(session_id, listener)
    except ServerError as e:  # deleted meanwhile
        await websocket.close(code=4000 + e.status, reason=e.detail[:120])
        return
    reader = asyncio.create_task(read_until_closed())
    try:
        while not disconnected.is_set():
            try:
                pose = await asyncio.wait_for(queue.get(), timeout=0.5)
            except TimeoutError:
                try:
                    st = await run_in_threadpool(manager.status, session_id)
                except ServerError:
                    await websocket.close(code=4404, reason="session deleted")
                    return
                if st.state in (SessionState.finished, SessionState.failed) and queue.empty():
                    await websocket.send_text(json.dumps({"event": "end", "state": st.state.value,
                                                          "last_error": st.last_error}))
                    await websocket.close(code=1000)
                    return
                continue
            await websocket.send_text(pose.model_dump_json())
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        manager.remove_pose_listener(session_id, listener)
        reader.cancel()
