"""What the HTTP and the zenoh client share: session handle, frame encoding, sequence numbers, the
background sender behind ``send_frame_async``, and the decoding of answers.

A transport subclass implements a handful of primitives (``_create``, ``_send_message``, ``_query_json``,
``_query_bytes``, ...); every public verb is written once here, so both clients behave the same.
"""

from __future__ import annotations

import queue
import threading
import time
from abc import ABC, abstractmethod
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from voxfusion.core.config import parse_overrides
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ValidationError
from voxfusion.core.trajectory import Trajectory as CoreTrajectory
from voxfusion.proto import ColorEncoding, ConfidenceEncoding, DepthEncoding, WireIntrinsics, encode_frame, read_header
from voxfusion.proto.api_extra import SessionStatusOut
from voxfusion.proto.schemas import (
    PoseOut,
    RenderFormat,
    RenderIntrinsics,
    RenderRequest,
    SessionCreate,
    SessionCreated,
    SessionMode,
    SessionState,
)

from .errors import ClientError, ServerError, TransportError

__all__ = [
    "SessionHandle",
    "EncodeOptions",
    "BaseClient",
    "MESH_FORMATS",
    "VOXEL_FORMATS",
    "poses_to_trajectory",
    "decode_render",
]

MESH_FORMATS = ("ply", "glb", "obj")
VOXEL_FORMATS = ("npz", "ply")
_DONE_STATES = (SessionState.finished, SessionState.failed)


@dataclass(frozen=True)
class SessionHandle:
    """A session on the server: its id and the bearer token its routes and keys require."""

    id: str
    token: str


@dataclass(frozen=True)
class EncodeOptions:
    """How frames are put on the wire (``proto/README.md`` §3).

    Example::

        EncodeOptions(depth_encoding="png16_mm")            # smallest for iPhone LiDAR depth
        EncodeOptions(color_encoding=None)                  # depth only
    """

    depth_encoding: DepthEncoding = "zstd_u16_mm"
    """``zstd_u16_mm`` (fast, 1 mm steps), ``png16_mm`` (smaller for LiDAR), ``zstd_f16_m``, ``raw_f32_m``."""
    color_encoding: ColorEncoding | None = "jpeg"
    """``jpeg``, ``png``, ``raw_rgb8`` or ``None`` (no colour)."""
    confidence_encoding: ConfidenceEncoding | None = "zstd_u8"
    """``zstd_u8``, ``raw_u8``, ``png8`` or ``None`` (not sent)."""
    jpeg_quality: int = 90
    """1..100."""


def poses_to_trajectory(poses: list[PoseOut]) -> CoreTrajectory:
    """The poses of a session as a :class:`voxfusion.core.trajectory.Trajectory` (for TUM files, evo)."""
    if not poses:
        return CoreTrajectory(np.zeros(0), np.zeros((0, 4, 4)))
    return CoreTrajectory(np.array([p.timestamp_s for p in poses], dtype=np.float64),
                          np.array([p.T_world_cam for p in poses], dtype=np.float64))


def decode_render(body: bytes, meta: dict[str, str], fmt: RenderFormat, width: int, height: int) -> np.ndarray:
    """A render answer as ``[height, width]`` float32 depth in metres, 0 = no surface.

    The answer is ``depth | mask | color`` back to back; ``meta`` (HTTP headers / zenoh reply attachment)
    gives the parts' lengths (``X-Depth-Bytes``, ...; see ``server/outputs.py``).

    Raises:
        ClientError: the body does not hold a ``width`` x ``height`` image of ``fmt``.
    """
    meta = {k.lower(): v for k, v in meta.items()}
    try:
        n_depth = int(meta.get("x-depth-bytes", len(body)))
    except ValueError as e:
        raise ClientError(f"render answer: bad X-Depth-Bytes {meta.get('x-depth-bytes')!r}") from e
    body = body[:n_depth]
    if fmt == "f16":
        if len(body) != 2 * width * height:
            raise ClientError(f"render answer has {len(body)} bytes, expected {2 * width * height} "
                              f"(f16, {width}x{height})")
        depth = np.frombuffer(body, dtype="<f2").reshape(height, width).astype(np.float32)
    else:
        img = cv2.imdecode(np.frombuffer(body, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.dtype != np.uint16 or img.shape != (height, width):
            raise ClientError(f"render answer is not a {width}x{height} 16-bit PNG")
        depth = img.astype(np.float32) / 1000.0
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def _session_create(name: str | None, overrides: dict[str, Any] | list[str] | None, preset: str | None,
                    mode: SessionMode | str | None) -> SessionCreate:
    config = parse_overrides(overrides) if isinstance(overrides, (list, tuple)) else overrides
    body: dict[str, Any] = {"name": name, "preset": preset, "config": config or None}
    if mode is not None:
        body["mode"] = SessionMode(mode)
    return SessionCreate(**body)


class _Sender:
    """One background thread sending queued messages in order (``send_frame_async`` of the HTTP client)."""

    def __init__(self, send: Any, max_in_flight: int) -> None:
        self._send = send
        self._queue: queue.Queue[tuple[bytes, int, Future[int]] | None] = queue.Queue(maxsize=max_in_flight)
        self._thread = threading.Thread(target=self._run, name="voxfusion-sender", daemon=True)
        self._thread.start()

    def submit(self, data: bytes, seq: int) -> Future[int]:
        fut: Future[int] = Future()
        self._queue.put((data, seq, fut))  # blocks while max_in_flight messages wait: backpressure
        return fut

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                data, seq, fut = item
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(self._send(data, seq))
                    except BaseException as e:  # noqa: BLE001 - handed to the caller through the future
                        fut.set_exception(e)
            finally:
                self._queue.task_done()

    def join(self) -> None:
        self._queue.join()

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=30)


class BaseClient(ABC):
    """The client API, independent of the transport (:class:`~voxfusion.clients.Client` over HTTP,
    :class:`~voxfusion.clients.ZenohClient` over zenoh).

    Frames get consecutive sequence numbers (``seq``) from 0 unless given; ``send_frame`` returns once the
    server has durably recorded the frame (HTTP 202 / zenoh ack), ``send_frame_async`` returns a
    :class:`concurrent.futures.Future` of the ``seq`` at once (at most ``max_in_flight`` frames wait;
    more block the caller: backpressure). Frames keep their order on both transports. In asyncio code,
    ``await asyncio.wrap_future(client.send_frame_async(frame))``.
    """

    def __init__(self, *, token: str | None = None, session_id: str | None = None,
                 encode: EncodeOptions | None = None, max_in_flight: int = 8) -> None:
        if max_in_flight < 1:
            raise ValidationError("max_in_flight", f"must be >= 1, got {max_in_flight}")
        self.encode_options = encode or EncodeOptions()
        self.max_in_flight = int(max_in_flight)
        self._handle: SessionHandle | None = None
        self._seq = 0
        self._seq_lock = threading.Lock()
        if session_id is not None:
            if token is None:
                raise ValidationError("token", "attaching to an existing session needs its token")
            self.attach(session_id, token)

    # ------------------------------------------------------------------------------------ sessions
    @property
    def session(self) -> SessionHandle:
        """The current session (from :meth:`create_session` or :meth:`attach`)."""
        if self._handle is None:
            raise ClientError("no session: call create_session() or attach() first")
        return self._handle

    @property
    def session_id(self) -> str:
        return self.session.id

    def attach(self, session_id: str, token: str, *, next_seq: int = 0) -> SessionHandle:
        """Use an existing session; frames continue at ``next_seq``."""
        self._handle = SessionHandle(str(session_id), str(token))
        self._seq = int(next_seq)
        return self._handle

    def create_session(self, name: str | None = None, overrides: dict[str, Any] | list[str] | None = None, *,
                       preset: str | None = None, mode: SessionMode | str | None = None) -> SessionHandle:
        """Create a session and make it the current one.

        Args:
            name: human-readable label.
            overrides: engine configuration overrides, nested (``{"tracking": {"iters": 10}}``) or
                ``["tracking.iters=10", ...]``.
            preset: configuration preset name on the server (``iphone``, ``tum``, ...), ``None``: its default.
            mode: ``realtime`` (default on the server: may skip frames to keep up) or ``offline`` (every
                frame tracked and mapped, in order: the same frames give the same poses every time).

        Raises:
            ServerError: refused (403 wrong API key, 422 unknown config key, 503 too many sessions).
        """
        created = self._create(_session_create(name, overrides, preset, mode))
        return self.attach(created.id, created.token)

    # -------------------------------------------------------------------------------------- frames
    def _take_seq(self, seq: int | None) -> int:
        with self._seq_lock:
            if seq is None:
                seq = self._seq
            self._seq = max(self._seq, int(seq) + 1)
            return int(seq)

    def encode(self, frame: RGBDFrame, *, seq: int | None = None, color: np.ndarray | None = None,
               intrinsics: WireIntrinsics | None = None, device_pose: np.ndarray | None = None,
               device_pose_convention: str = "opencv") -> tuple[int, bytes]:
        """``(seq, message)``: ``frame`` as one wire message for the current session.

        ``color`` (any size with the depth's aspect ratio), ``intrinsics`` (for their own resolution) and
        ``device_pose`` (``[4, 4]`` camera-to-world in ``device_pose_convention``) replace the frame's.
        """
        o = self.encode_options
        seq = self._take_seq(seq)
        data = encode_frame(frame, seq=seq, session=self.session.id, depth_encoding=o.depth_encoding,
                            color_encoding=o.color_encoding, confidence_encoding=o.confidence_encoding,
                            jpeg_quality=o.jpeg_quality, color=color, intrinsics=intrinsics,
                            device_pose=device_pose, device_pose_convention=device_pose_convention)  # type: ignore[arg-type]
        return seq, data

    def send_frame(self, frame: RGBDFrame, **kwargs: Any) -> int:
        """Send one frame (keyword arguments as :meth:`encode`); returns its ``seq`` once it is recorded.

        Raises:
            ServerError: refused (400 malformed, 403 token, 409 finished session, 429 queue full, ...).
            TransportError: no answer.
        """
        seq, data = self.encode(frame, **kwargs)
        return self._send_message(data, seq)

    def send_bytes(self, data: bytes) -> int:
        """Send an already encoded frame message (its header's ``seq`` is used); returns that ``seq``."""
        seq = read_header(data).seq
        self._take_seq(seq)
        return self._send_message(bytes(data), seq)

    def send_frame_async(self, frame: RGBDFrame, **kwargs: Any) -> Future[int]:
        """Encode now, send in the background; the future gives the ``seq`` or the :class:`ServerError`."""
        seq, data = self.encode(frame, **kwargs)
        return self._send_message_async(data, seq)

    def send_bytes_async(self, data: bytes) -> Future[int]:
        """:meth:`send_bytes` in the background."""
        seq = read_header(data).seq
        self._take_seq(seq)
        return self._send_message_async(bytes(data), seq)

    @abstractmethod
    def flush(self) -> None:
        """Wait until every frame sent with ``send_*_async`` has been answered."""

    # ------------------------------------------------------------------------------------ answers
    def server_device(self) -> str | None:
        """The torch device the server runs sessions on (``cpu``, ``cuda``) where the transport reports it
        (HTTP: ``/healthz``); ``None`` where it does not (zenoh)."""
        return None

    def status(self) -> SessionStatusOut:
        """Progress counters and state of the current session."""
        return SessionStatusOut.model_validate_json(self._query_bytes("status"))

    def latest_pose(self) -> PoseOut | None:
        """The newest tracked pose, or ``None`` before the first one."""
        try:
            return PoseOut.model_validate_json(self._query_bytes("poses/latest"))
        except ServerError as e:
            if e.status == 409:  # the server's NotReady: nothing tracked yet
                return None
            raise

    def trajectory(self) -> list[PoseOut]:
        """Every estimated pose of the session, in ``seq`` order (OpenCV camera-to-world)."""
        from voxfusion.proto.schemas import Trajectory

        return list(Trajectory.model_validate_json(self._query_bytes("trajectory", {"format": "json"})).poses)

    def render_depth(self, T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int, *,
                     convention: str = "opencv", format: RenderFormat = "f16") -> np.ndarray:
        """Depth of the current map seen from a camera, e.g. for AR occlusion.

        Args:
            T_world_cam: ``[4, 4]`` camera-to-world in ``convention`` (``opencv`` or ``arkit``), metres.
            K: ``[3, 3]`` intrinsics for ``width`` x ``height`` pixels.
            format: ``f16`` (raw half floats) or ``png16`` (millimetres) on the wire.

        Returns:
            ``[height, width]`` float32 depth in metres, 0 where the map has no surface.
        """
        K = np.asarray(K, dtype=np.float64)
        req = RenderRequest(T_world_cam=np.asarray(T_world_cam, dtype=np.float64).tolist(),
                            convention=convention,  # type: ignore[arg-type]
                            width=int(width), height=int(height), format=format,
                            intrinsics=RenderIntrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]),
                                                        cx=float(K[0, 2]), cy=float(K[1, 2])))
        body, meta = self._render(req)
        return decode_render(body, meta, format, int(width), int(height))

    def download_mesh(self, path: str | Path | None = None, *, format: str | None = None) -> bytes:
        """The mesh of the current map (``ply``, ``glb`` or ``obj``; default from ``path``'s suffix, else
        ``ply``); written to ``path`` when given. Returns the file's bytes."""
        fmt = _pick_format(path, format, MESH_FORMATS, "ply")
        return _save(self._query_bytes("mesh", {"format": fmt}), path)

    def download_voxels(self, path: str | Path | None = None, *, format: str | None = None) -> bytes:
        """The sparse voxel map (``npz`` or ``ply``), written to ``path`` when given; returns the bytes."""
        fmt = _pick_format(path, format, VOXEL_FORMATS, "npz")
        return _save(self._query_bytes("voxels", {"format": fmt}), path)

    def finish(self, timeout_s: float = 600.0) -> SessionStatusOut:
        """Stop taking frames, process what is queued, run the final mapping; returns the final status."""
        self.flush()
        return self._finish(timeout_s)

    def wait_until_done(self, timeout_s: float = 600.0) -> SessionStatusOut:
        """Poll :meth:`status` until the session is finished or failed."""
        deadline = time.monotonic() + timeout_s
        st = self.status()
        while st.state not in _DONE_STATES:
            if time.monotonic() > deadline:
                raise TransportError(f"session {self.session.id} still {st.state.value} after {timeout_s} s")
            time.sleep(0.05)
            st = self.status()
        return st

    @property
    @abstractmethod
    def mesh_url(self) -> str:
        """Where the current session's mesh is fetched: an HTTP URL, or the zenoh key."""

    # -------------------------------------------------------------------------- transport primitives
    @abstractmethod
    def _create(self, body: SessionCreate) -> SessionCreated: ...

    @abstractmethod
    def _send_message(self, data: bytes, seq: int) -> int: ...

    @abstractmethod
    def _send_message_async(self, data: bytes, seq: int) -> Future[int]: ...

    @abstractmethod
    def _query_bytes(self, verb: str, params: dict[str, str] | None = None) -> bytes:
        """The body of a session's ``verb`` (``status``, ``poses/latest``, ``trajectory``, ``mesh``,
        ``voxels``); raises :class:`ServerError` / :class:`TransportError`."""

    @abstractmethod
    def _render(self, req: RenderRequest) -> tuple[bytes, dict[str, str]]:
        """The render answer's body and its part lengths (``X-Depth-Bytes``, ...)."""

    @abstractmethod
    def _finish(self, timeout_s: float) -> SessionStatusOut: ...

    @abstractmethod
    def close(self) -> None:
        """Release connections and threads (frames still queued by ``send_frame_async`` are sent first)."""

    def __enter__(self) -> BaseClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _pick_format(path: str | Path | None, fmt: str | None, choices: tuple[str, ...], default: str) -> str:
    if fmt is None and path is not None and Path(path).suffix.lower().lstrip(".") in choices:
        fmt = Path(path).suffix.lower().lstrip(".")
    fmt = (fmt or default).lower()
    if fmt not in choices:
        raise ValidationError("format", f"must be one of {', '.join(choices)}, got {fmt!r}")
    return fmt


def _save(data: bytes, path: str | Path | None) -> bytes:
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".part")
        tmp.write_bytes(data)
        tmp.replace(path)
    return data
