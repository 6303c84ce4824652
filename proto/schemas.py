"""Pydantic v2 models of the server's JSON API (requests and responses).

Frames themselves travel in the binary container (:mod:`voxfusion.proto.frame_codec`,
``proto/README.md``); everything else the server takes or answers is JSON described here. Conventions
are the project's: poses are 4x4 camera-to-world matrices, row-major nested lists ``[[r00, r01, r02, tx],
...]``, OpenCV camera axes (x right, y down, z forward), metres; times are seconds (``_s``) or
milliseconds (``_ms``) as the name says.

Every model refuses unknown keys (``extra="forbid"``: a typo is an error, not silently ignored) and
non-finite numbers (``NaN``/``Infinity``); pydantic's errors name the offending field (``loc``), which
the server returns as :class:`ErrorOut`.

Example::

    req = RenderRequest.model_validate_json(body)
    T = req.T_world_cam_cv()     # [4, 4] float64, OpenCV axes, whatever convention was sent
    K = req.K()                  # [3, 3] float64 for req.width x req.height
"""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from voxfusion.core.geometry import check_rigid, make_intrinsics, opengl_to_opencv

__all__ = [
    "MAX_RENDER_SIZE",
    "SessionMode",
    "SessionState",
    "SessionCreate",
    "SessionCreated",
    "SessionStatus",
    "SessionList",
    "FrameAccepted",
    "PoseOut",
    "Trajectory",
    "RenderFormat",
    "RenderIntrinsics",
    "RenderRequest",
    "ErrorOut",
]

MAX_RENDER_SIZE = 2048
"""Largest ``width`` / ``height`` of a render request, in pixels."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


def _matrix_4x4(value: Any) -> list[list[float]]:
    """Accept a 4x4 nested list or 16 numbers (row-major); return a 4x4 nested list of a rigid pose."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError("must be a 4x4 matrix (nested lists) or 16 numbers in row-major order") from e
    if arr.shape == (16,):
        arr = arr.reshape(4, 4)
    if arr.shape != (4, 4):
        raise ValueError(f"must be a 4x4 matrix or 16 numbers in row-major order, got shape {arr.shape}")
    # check_rigid raises ValidationError (a ValueError): pydantic reports it under this field's name.
    return check_rigid(arr, "T_world_cam").tolist()


class SessionMode(StrEnum):
    """How a session processes frames."""

    realtime = "realtime"
    """Keep up with the sender: tracking always takes the newest frame, older queued frames may be
    dropped (counted in ``frames_dropped``); every frame is still recorded on disk."""
    offline = "offline"
    """Process every frame in order, however long it takes (recorded captures, evaluation)."""


class SessionState(StrEnum):
    """Life cycle: ``created -> running -> finishing -> finished``, or ``failed`` from any state."""

    created = "created"
    """Exists; no frame received yet."""
    running = "running"
    """Receiving and processing frames."""
    finishing = "finishing"
    """No new frames accepted; the queue drains and final mapping / mesh extraction run."""
    finished = "finished"
    """Done; poses, mesh and map stay available."""
    failed = "failed"
    """Stopped by an error (``last_error`` says which)."""


class SessionCreate(_Model):
    """``POST /sessions`` body."""

    name: str | None = Field(None, min_length=1, max_length=128)
    """Human-readable label (not unique, not an id)."""
    preset: str | None = Field(None, pattern=r"^[a-z0-9][a-z0-9_-]{0,63}(\+[a-z0-9][a-z0-9_-]{0,63}){0,3}$")
    """Named configuration preset (``configs/<preset>.yaml``, e.g. ``iphone``, ``tum``), or names composed with
    ``+``, kind first (``tum+cpu``: TUM at CPU sizes); ``None``: the server's default. Names only, never a path."""
    config: dict[str, Any] | None = None
    """Overrides of the engine configuration as a nested object, e.g. ``{"mapping": {"iters": 10},
    "voxel_size_m": 0.1}``; keys are checked by the server (an unknown key is an error naming it)."""
    mode: SessionMode = SessionMode.realtime
    """``realtime`` (may drop frames to keep up) or ``offline`` (every frame tracked and mapped, in order,
    before the next: reproducible, as ``voxfusion run``)."""


class SessionCreated(_Model):
    """``POST /sessions`` answer."""

    id: str
    """Session id: use in URLs and in the frame header's ``session``."""
    token: str
    """Bearer token for this session's endpoints (``Authorization: Bearer <token>``)."""


class SessionStatus(_Model):
    """``GET /sessions/{id}`` answer: progress counters and health of one session."""

    id: str
    name: str | None = None
    mode: SessionMode = SessionMode.realtime
    state: SessionState
    created_at: datetime
    """Creation time (server wall clock, UTC, ISO 8601)."""
    frames_received: int = Field(0, ge=0)
    """Frames accepted and recorded."""
    frames_tracked: int = Field(0, ge=0)
    """Frames with an estimated pose."""
    frames_mapped: int = Field(0, ge=0)
    """Frames whose data has been fused into the map (keyframes and mapping-window frames)."""
    frames_dropped: int = Field(0, ge=0)
    """Frames recorded but skipped by tracking to keep up (``realtime`` mode only)."""
    keyframes: int = Field(0, ge=0)
    voxels: int = Field(0, ge=0)
    """Allocated voxels in the sparse map."""
    fps: float = Field(0.0, ge=0.0)
    """Frames tracked per second over the last few seconds."""
    latency_ms: float | None = Field(None, ge=0.0)
    """Median time from a frame's arrival to its pose over recent frames; ``None`` before the first pose."""
    last_error: str | None = None
    map_version: int = Field(0, ge=0)
    """Increments each time mapping publishes a new map snapshot (renders and meshes name the version)."""


class SessionList(_Model):
    """``GET /sessions`` answer."""

    sessions: list[SessionStatus]


class FrameAccepted(_Model):
    """Answer to a posted frame: it is recorded durably (on disk) before this is sent.

    A frame whose ``seq`` the session already recorded is a duplicate (a retry, or a sender reusing a
    number): it is acknowledged with ``duplicate: true, action: "ignored"`` and neither recorded nor
    tracked again; the copy recorded first stands, even when the bytes differ, so a retry can never add
    or change a frame of the recording.
    """

    seq: int = Field(ge=0)
    """The frame header's ``seq``."""
    session: str
    """Session id the frame was filed under."""
    duplicate: bool | None = None
    """``True`` when a frame with this ``seq`` was already recorded for the session. ``None``: not
    reported (answers of the zenoh bridge, which acknowledges a duplicate like a new frame)."""
    action: Literal["recorded", "ignored"] | None = None
    """What happened to this frame: ``recorded`` (appended to the recording, queued for tracking) or
    ``ignored`` (a duplicate: the recording is unchanged). ``None`` exactly when ``duplicate`` is."""


class PoseOut(_Model):
    """The estimated pose of one frame."""

    seq: int = Field(ge=0)
    """The frame header's ``seq`` (the frame's index in the session)."""
    timestamp_s: float
    """The frame's ``timestamp_s`` (device clock)."""
    T_world_cam: list[list[float]]
    """4x4 camera-to-world, row-major nested lists, OpenCV camera axes, metres (also accepts 16 numbers)."""
    convention: Literal["opencv"] = "opencv"
    """Always ``opencv``; ARKit/OpenGL clients convert with ``T_gl = T_cv @ diag(1, -1, -1, 1)``."""
    tracking_loss: float | None = None
    """Final tracking loss (lower is better; comparable within one session), ``None`` if not tracked."""
    lost: bool = False
    """Tracking failed for this frame (the pose is the motion-model prediction)."""
    tracking_state: Literal["normal", "limited", "lost"] = "normal"
    """``lost`` as ``lost``; ``limited``: tracked, but its cost jumped to more than ``tracking.limited_cost_factor``
    (3) times the median of the frames before it (``cost_ratio``), so the pose may be wrong: a start beyond the
    tracker's reach (fast motion, dropped frames), or a view turning into space the map has not seen. The frame is
    still fused. ARKit's ``ARCamera.TrackingState`` has the same three; an AR app may hold its anchors while it is
    not ``normal``."""
    cost_ratio: float | None = Field(None, ge=0)
    """The frame's tracking cost over the median cost of the tracked frames before it (about 1 while tracking goes
    well); None for the first frames, frames not tracked and lost ones."""
    is_keyframe: bool = False

    @model_validator(mode="before")
    @classmethod
    def _state_agrees_with_lost(cls, v: Any) -> Any:
        """Poses saved before ``tracking_state`` existed (a finished session's ``poses.json``) have only ``lost``:
        the state follows it. Sent together, the two must agree."""
        if not isinstance(v, dict) or "lost" not in v:
            return v
        lost = v["lost"]
        if not isinstance(lost, bool):
            return v  # the field's own validation names it
        state = v.get("tracking_state")
        if state is None:
            return {**v, "tracking_state": "lost" if lost else "normal"}
        if (state == "lost") != lost:
            raise ValueError(f"tracking_state {state!r} contradicts lost={lost} (a lost frame's state is 'lost', "
                             "and only a lost frame's)")
        return v

    @field_validator("T_world_cam", mode="before")
    @classmethod
    def _rigid(cls, v: Any) -> list[list[float]]:
        return _matrix_4x4(v)


class Trajectory(_Model):
    """``GET /sessions/{id}/poses`` answer (zenoh: ``sessions/<id>/trajectory``): every estimated pose, in ``seq``
    order.

    (Not :class:`voxfusion.core.trajectory.Trajectory`; import this one as ``schemas.Trajectory``.)
    """

    session: str
    poses: list[PoseOut]
    frames_received: int | None = Field(None, ge=0)
    """Frames the session has received (its status' ``frames_received``) when the poses were read: fewer poses than
    this are frames still queued or being tracked (a new session's engine is starting, its first frame mapped),
    or frames the tracker dropped (status ``frames_dropped``), not lost data. None from a server that predates it."""


RenderFormat = Literal["f16", "png16"]
"""Render answer body: ``f16`` = ``height * width`` IEEE-754 binary16 little-endian depth in metres,
row-major, 0 = no surface; ``png16`` = 16-bit greyscale PNG, millimetres, 0 = no surface."""


class RenderIntrinsics(_Model):
    """Pinhole intrinsics of the requested image, in pixels (for ``width`` x ``height``)."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float


class RenderRequest(_Model):
    """``POST /sessions/{id}/render``: render the map's depth (and colour) from a client's viewpoint.

    The typical use is AR occlusion: an ARKit client sends its camera pose (``convention="arkit"``) and
    intrinsics scaled to the size it wants back.
    """

    T_world_cam: list[list[float]]
    """4x4 camera-to-world (nested lists) or 16 numbers row-major, in ``convention``'s camera axes, metres."""
    convention: Literal["opencv", "arkit"] = "opencv"
    """``opencv`` (x right, y down, z forward) or ``arkit`` (OpenGL: x right, y up, camera looks along -z).
    ARKit's ``simd_float4x4`` is column-major: send it transposed (row by row)."""
    width: int = Field(ge=1, le=MAX_RENDER_SIZE)
    """Output width in pixels."""
    height: int = Field(ge=1, le=MAX_RENDER_SIZE)
    """Output height in pixels."""
    intrinsics: RenderIntrinsics
    """For ``width`` x ``height``; the principal point must lie inside that image."""
    format: RenderFormat = "f16"
    with_color: bool = False
    """Also render colour (the server returns it beside the depth; see the server's API docs)."""

    @field_validator("T_world_cam", mode="before")
    @classmethod
    def _rigid(cls, v: Any) -> list[list[float]]:
        return _matrix_4x4(v)

    @field_validator("intrinsics", mode="after")
    @classmethod
    def _principal_point_inside(cls, v: RenderIntrinsics, info: ValidationInfo) -> RenderIntrinsics:
        w, h = info.data.get("width"), info.data.get("height")
        if w is not None and h is not None and not (0 <= v.cx <= w and 0 <= v.cy <= h):
            raise ValueError(f"principal point ({v.cx}, {v.cy}) lies outside the {w}x{h} image")
        return v

    def T_world_cam_cv(self) -> np.ndarray:
        """``[4, 4]`` float64 camera-to-world in OpenCV axes (ARKit poses converted)."""
        T = np.asarray(self.T_world_cam, dtype=np.float64)
        return opengl_to_opencv(T) if self.convention == "arkit" else T

    def K(self) -> np.ndarray:
        """``[3, 3]`` float64 intrinsics for ``width`` x ``height``."""
        i = self.intrinsics
        return make_intrinsics(i.fx, i.fy, i.cx, i.cy)


class ErrorOut(_Model):
    """Body of every error answer (4xx / 5xx)."""

    detail: str
    """What went wrong, in words."""
    field: str | None = None
    """The offending input: a JSON field (``"T_world_cam"``, ``"config.mapping.iters"``) or a frame
    container part (:data:`voxfusion.proto.ERROR_FIELDS`: ``"depth"``, ``"crc"``, ...); ``None`` when the
    error is not about one input."""
