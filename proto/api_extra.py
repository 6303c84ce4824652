"""API models the server needs beside :mod:`.schemas` (kept apart so that module stays the wire helper's).

Same conventions as :mod:`.schemas`: unknown keys refused, finite numbers only, frozen.
"""

from __future__ import annotations

from pydantic import Field

from .schemas import SessionStatus, _Model

__all__ = ["SessionStatusOut", "SessionListOut", "HealthOut", "LatestFrameOut"]


class SessionStatusOut(SessionStatus):
    """``GET /sessions/{id}`` answer: :class:`~.schemas.SessionStatus` plus recovery information."""

    resume_required: bool = False
    """The server restarted while this session was open: every acknowledged frame is in its recording,
    and ``POST /sessions/{id}/resume`` (or its next frame) replays the recording through a new engine.
    Until then mesh / voxels / poses come from its last periodic checkpoint (if any)."""
    replay_pending: int = Field(0, ge=0)
    """Recorded frames still to be replayed (resume in progress)."""
    frames_queued: int = Field(0, ge=0)
    """Frames accepted but not yet handed to tracking (the bounded ingest queue)."""
    frames_lost: int = Field(0, ge=0)
    """Tracked frames whose tracking failed (their pose is the motion model's guess; they are not fused)."""
    frames_retried: int = Field(0, ge=0)
    """Frames after a gap that were tracked again from other start poses (their first start looked wrong), and the
    session's second frame where tracking it again from turned starts changed its pose (``tracking.
    first_motion_max_deg``)."""
    frames_relocalised: int = Field(0, ge=0)
    """Of those, the frames placed from a keyframe's pose (a camera back at a place it mapped)."""
    frames_limited: int = Field(0, ge=0)
    """Tracked frames whose tracking state was ``limited`` (their cost jumped; not lost, still fused)."""
    worker_pid: int | None = None
    """Process id of the session's engine worker on the server (``None``: none, or engines on threads)."""
    worker_node: str | None = None
    """Where the engine runs: the Ray node id with ``--ray-address``, else this server's host name."""
    worker_restarts: int = Field(0, ge=0)
    """How often the session's worker process died (killed, crashed) and was restarted, replaying the
    recording, since the session was opened."""


class SessionListOut(_Model):
    """``GET /sessions`` answer."""

    sessions: list[SessionStatusOut]


class HealthOut(_Model):
    """``GET /healthz`` answer."""

    status: str = "ok"
    version: str
    """voxfusion version."""
    device: str
    """Torch device sessions run on (``cpu``, ``cuda``)."""
    sessions_open: int = Field(ge=0)
    """Sessions holding an engine (created, running, finishing)."""
    sessions_total: int = Field(ge=0)
    """Sessions known to the server (every state)."""
    max_sessions: int = Field(ge=1)
    zenoh: bool = False
    """The zenoh bridge is running."""


class LatestFrameOut(_Model):
    """``GET /sessions/{id}/frames/latest`` answer: the newest frame the session received (the live viewer
    draws the current camera's frustum from it)."""

    seq: int
    """The frame's wire ``seq``."""
    timestamp_s: float
    """Capture time (device clock), seconds."""
    width: int = Field(ge=1)
    """Depth image width, pixels (the intrinsics are for this resolution)."""
    height: int = Field(ge=1)
    fx: float
    fy: float
    cx: float
    cy: float
    has_colour: bool
    """``/frames/latest/colour.jpg`` has an image."""
    valid_depth_fraction: float = Field(ge=0, le=1)
    """Share of depth pixels that are valid (> 0)."""
    median_depth_m: float | None = None
    """Median of the valid depths, metres (``None`` when none is valid)."""
