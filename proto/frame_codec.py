"""RGB-D frames to wire messages and back: the one entry point the server and the clients use.

:func:`encode_frame` turns an :class:`RGBDFrame` into one version-1 message (layout in
:mod:`.container`, payload encodings in :mod:`.codecs`, full specification in ``proto/README.md``);
:func:`decode_frame` checks every byte of a message and returns the frame, or raises
:class:`FrameDecodeError` naming the part that is wrong. :func:`read_header` checks the framing and the
header only (cheap: no image is decoded), e.g. to route or log a message before decoding it.

Decoding normalises what the wire allows to vary:

* depth becomes float32 metres (0 = invalid) whatever its encoding;
* colour sent at another resolution than depth (same aspect ratio within 1 %) is resized to the depth
  resolution with ``cv2.INTER_AREA``;
* intrinsics are stated for a resolution of their own (ARKit: the 1920x1440 colour image) and are scaled
  to the depth resolution with :func:`scale_intrinsics`;
* an ``arkit`` (OpenGL axes) device pose is converted to OpenCV axes; it lands in
  ``RGBDFrame.T_world_cam_device``;
* confidence levels 0/127/255 become 0/1/2.

Example::

    data = encode_frame(frame, seq=7, session="desk", depth_encoding="zstd_u16_mm")
    decoded = decode_frame(data)
    decoded.frame.depth_m, decoded.seq, decoded.session
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.frame_checks import intrinsics_problem, pose_problem
from voxfusion.core.geometry import check_rigid, make_intrinsics, opencv_to_opengl, opengl_to_opencv, scale_intrinsics

from .codecs import (
    COLOR_ENCODINGS,
    CONFIDENCE_ENCODINGS,
    CONFIDENCE_LEVELS,
    DEPTH_ENCODINGS,
    DEPTH_UNITS,
    ColorEncoding,
    ConfidenceEncoding,
    DepthEncoding,
    decode_color,
    decode_confidence,
    decode_depth,
    encode_color,
    encode_confidence,
    encode_depth,
)
from .container import (
    MAX_HEADER_BYTES,
    FrameDecodeError,
    FrameEncodingError,
    FrameValueError,
    Payloads,
    pack_message,
    unpack_message,
)

__all__ = [
    "PoseConvention",
    "POSE_CONVENTIONS",
    "POSE_LAYOUT",
    "ASPECT_TOLERANCE",
    "WireIntrinsics",
    "DecodeLimits",
    "FrameHeader",
    "DecodedFrame",
    "encode_frame",
    "decode_frame",
    "read_header",
]

PoseConvention = Literal["opencv", "arkit"]
POSE_CONVENTIONS: tuple[str, ...] = ("opencv", "arkit")
POSE_LAYOUT = "row-major-c2w"
"""The only pose layout of version 1: 16 numbers, row by row, of the 4x4 camera-to-world matrix."""
ASPECT_TOLERANCE = 0.01
"""Largest relative difference of width/height ratios between colour (or intrinsics) and depth."""
MAX_SESSION_CHARS = 256
MAX_SEQ = 2**63 - 1
MAX_INTRINSICS_SIZE = 65535


@dataclass(frozen=True)
class WireIntrinsics:
    """Pinhole intrinsics in pixels and the image resolution they refer to (header key ``intrinsics``).

    Attributes:
        fx, fy: focal lengths in pixels (> 0).
        cx, cy: principal point in pixels (pixel centres at integer coordinates).
        width, height: the resolution these numbers are for (may differ from the depth's).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> WireIntrinsics:
        """From a ``[3, 3]`` ``K`` for a ``width`` x ``height`` image."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ShapeError("intrinsics", K.shape, "(3, 3)")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` float64 for ``width`` x ``height``."""
        return make_intrinsics(self.fx, self.fy, self.cx, self.cy)

    def to_json(self) -> dict[str, float | int]:
        """The header's ``intrinsics`` object (plain floats and ints, whatever types were given)."""
        return {"fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "width": int(self.width), "height": int(self.height)}


@dataclass(frozen=True)
class DecodeLimits:
    """What :func:`decode_frame` accepts; larger messages are refused before any image is decoded.

    Attributes:
        max_width, max_height: largest depth / colour / confidence image in pixels.
        max_header_bytes: largest JSON header.
    """

    max_width: int = 4096
    max_height: int = 4096
    max_header_bytes: int = MAX_HEADER_BYTES


@dataclass(frozen=True, eq=False)
class FrameHeader:
    """A checked header (everything but the pixels).

    Attributes:
        seq: sender's sequence number (>= 0).
        session: session id or ``None``.
        timestamp_s: capture time in seconds (device clock).
        intrinsics: as sent (for their own resolution; not yet scaled to depth).
        depth_encoding, depth_width, depth_height: depth payload.
        color_encoding, color_width, color_height: colour payload (``None`` / 0 without colour).
        confidence_encoding, confidence_levels: confidence payload (``None`` without confidence).
        device_pose: ``[4, 4]`` float64 camera-to-world, already converted to OpenCV axes, or ``None``.
        device_pose_convention: the convention it was sent in, or ``None``.
        raw: the header JSON object as received.
    """

    seq: int
    session: str | None
    timestamp_s: float
    intrinsics: WireIntrinsics
    depth_encoding: str
    depth_width: int
    depth_height: int
    color_encoding: str | None
    color_width: int
    color_height: int
    confidence_encoding: str | None
    confidence_levels: str | None
    device_pose: np.ndarray | None
    device_pose_convention: str | None
    raw: dict[str, Any]


@dataclass(frozen=True, eq=False)
class DecodedFrame:
    """A decoded message.

    Attributes:
        frame: the frame (depth float32 metres, colour RGB at the depth resolution, ``K`` for the depth
            resolution, ``T_world_cam_device`` in OpenCV axes, ``index`` = ``seq``).
        seq: sender's sequence number.
        session: session id from the header, or ``None``.
        header: the header JSON object as received.
    """

    frame: RGBDFrame
    seq: int
    session: str | None
    header: dict[str, Any]


# ------------------------------------------------------------------------------------------ encode


def _aspect_close(w1: int, h1: int, w2: int, h2: int) -> bool:
    a1, a2 = w1 / h1, w2 / h2
    return abs(a1 - a2) <= ASPECT_TOLERANCE * a2


def encode_frame(frame: RGBDFrame, *, seq: int, session: str | None = None,
                 depth_encoding: DepthEncoding = "zstd_u16_mm", color_encoding: ColorEncoding | None = "jpeg",
                 confidence_encoding: ConfidenceEncoding | None = "zstd_u8", jpeg_quality: int = 90,
                 device_pose: np.ndarray | None = None, device_pose_convention: PoseConvention = "opencv",
                 color: np.ndarray | None = None, intrinsics: WireIntrinsics | None = None,
                 zstd_level: int = 3) -> bytes:
    """Encode ``frame`` as one version-1 message.

    Args:
        frame: the frame; its depth, colour (unless ``color`` is given), confidence, ``K`` (unless
            ``intrinsics`` is given), ``timestamp_s`` and ``T_world_cam_device`` are sent.
            ``T_world_cam`` (the reference pose) and ``meta`` are not.
        seq: sequence number (0 <= seq < 2**63), echoed back by the server.
        session: session id, or ``None``.
        depth_encoding: one of ``png16_mm``, ``zstd_u16_mm`` (1 mm steps, <= 65.535 m), ``zstd_f16_m``,
            ``raw_f32_m``.
        color_encoding: ``jpeg``, ``png``, ``raw_rgb8``, or ``None`` to send no colour.
        confidence_encoding: ``raw_u8``, ``zstd_u8``, ``png8``, or ``None`` to send no confidence.
        jpeg_quality: 1..100.
        device_pose: ``[4, 4]`` camera-to-world in ``device_pose_convention`` to send instead of
            ``frame.T_world_cam_device`` (which is OpenCV and is sent as ``opencv`` when this is ``None``).
        device_pose_convention: ``opencv`` or ``arkit`` (OpenGL camera axes): the convention the pose is
            written in. ``device_pose`` is taken to be in it; the frame's (OpenCV) pose is converted to it.
        color: ``[Hc, Wc, 3]`` uint8 RGB to send instead of ``frame.color``, at any resolution with the
            depth's aspect ratio (e.g. 640x480 colour for 256x192 depth).
        intrinsics: intrinsics to send instead of ``frame.K`` (which is for the depth resolution),
            e.g. ARKit's K for 1920x1440.
        zstd_level: zstd compression level for the zstd encodings.

    Raises:
        ValidationError: an argument is invalid (field names it).
    """
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or not 0 <= int(seq) <= MAX_SEQ:
        raise ValidationError("seq", f"must be an integer in [0, 2**63), got {seq!r}")
    if session is not None and not (isinstance(session, str) and 1 <= len(session) <= MAX_SESSION_CHARS):
        raise ValidationError("session", f"must be None or a string of 1..{MAX_SESSION_CHARS} characters")
    h, w = frame.depth_m.shape
    header: dict[str, Any] = {"session": session, "seq": int(seq), "timestamp_s": float(frame.timestamp_s)}
    intr = intrinsics if intrinsics is not None else WireIntrinsics.from_K(frame.K, w, h)
    _check_intrinsics(intr, w, h, ValidationError)
    header["intrinsics"] = intr.to_json()

    depth_bytes = encode_depth(frame.depth_m, depth_encoding, zstd_level=zstd_level)
    header["depth"] = {"encoding": depth_encoding, "units": DEPTH_UNITS[depth_encoding], "width": w, "height": h}

    color_img = color if color is not None else frame.color
    color_bytes = b""
    header["color"] = None
    if color_encoding is not None and color_img is not None:
        color_bytes = encode_color(color_img, color_encoding, jpeg_quality=jpeg_quality)  # checks [H, W, 3] uint8
        ch, cw = np.asarray(color_img).shape[:2]
        if ch < 1 or cw < 1 or not _aspect_close(cw, ch, w, h):
            raise ValidationError("color", f"{cw}x{ch} does not have the depth's aspect ratio ({w}x{h})")
        header["color"] = {"encoding": color_encoding, "width": cw, "height": ch}

    conf_bytes = b""
    header["confidence"] = None
    if confidence_encoding is not None and frame.confidence is not None:
        conf_bytes = encode_confidence(frame.confidence, confidence_encoding, zstd_level=zstd_level)
        header["confidence"] = {"encoding": confidence_encoding, "levels": "0-2"}

    header["device_pose"] = None
    if device_pose is not None or frame.T_world_cam_device is not None:
        if device_pose_convention not in POSE_CONVENTIONS:
            raise ValidationError("device_pose_convention", f"must be 'opencv' or 'arkit', got "
                                                            f"{device_pose_convention!r}")
        if device_pose is None:
            T = np.asarray(frame.T_world_cam_device, dtype=np.float64)
            if device_pose_convention == "arkit":
                T = opencv_to_opengl(T)
        else:
            T = check_rigid(device_pose, "device_pose")
        header["device_pose"] = {"convention": device_pose_convention, "layout": POSE_LAYOUT,
                                 "matrix": [float(v) for v in T.reshape(-1)]}
    return pack_message(header, Payloads(color=color_bytes, depth=depth_bytes, confidence=conf_bytes))


# ------------------------------------------------------------------------------------------ decode


def _key(obj: dict[str, Any], key: str, field: str, required: bool = True) -> Any:
    if key not in obj:
        if required:
            raise FrameDecodeError(field, f"missing key {key!r}")
        return None
    return obj[key]


def _obj(obj: dict[str, Any], key: str, field: str, required: bool) -> dict[str, Any] | None:
    v = _key(obj, key, field, required)
    if v is None and not required:
        return None
    if not isinstance(v, dict):
        raise FrameDecodeError(field, f"{key!r} must be a JSON object{'' if required else ' or null'}, "
                                      f"got {type(v).__name__}")
    return v


def _num(obj: dict[str, Any], key: str, field: str) -> float:
    v = _key(obj, key, field)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise FrameDecodeError(field, f"{key!r} must be a number, got {type(v).__name__}")
    try:
        f = float(v)
    except OverflowError as e:  # an integer literal beyond the float range
        raise FrameDecodeError(field, f"{key!r} is out of range") from e
    if not math.isfinite(f):
        raise FrameDecodeError(field, f"{key!r} must be finite, got {f}")
    return f


def _int(obj: dict[str, Any], key: str, field: str, lo: int, hi: int) -> int:
    v = _key(obj, key, field)
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise FrameDecodeError(field, f"{key!r} must be an integer in [{lo}, {hi}], got {v!r}")
    return v


def _choice(obj: dict[str, Any], key: str, field: str, choices: tuple[str, ...],
            unknown: type[FrameDecodeError] = FrameDecodeError) -> str:
    """``obj[key]`` if it is one of ``choices``; else ``unknown`` (:class:`FrameEncodingError` for encodings
    and levels: HTTP 415) naming ``field``."""
    v = _key(obj, key, field)
    if v not in choices:
        raise unknown(field, f"unknown {key} {v!r}; expected one of {', '.join(choices)}")
    return v


def _check_intrinsics(intr: WireIntrinsics, w: int, h: int, error: type[ValidationError],
                      implausible: type[ValidationError] | None = None) -> None:
    """fx, fy > 0 and finite; principal point inside the image; same aspect ratio as the depth (``error``);
    a field of view a camera can have (``implausible``, default ``error``)."""
    values = (intr.fx, intr.fy, intr.cx, intr.cy)
    if not all(math.isfinite(v) for v in values):
        raise error("intrinsics", f"must be finite, got fx={intr.fx}, fy={intr.fy}, cx={intr.cx}, cy={intr.cy}")
    if intr.fx <= 0 or intr.fy <= 0:
        raise error("intrinsics", f"focal lengths must be > 0, got fx={intr.fx}, fy={intr.fy}")
    if not (1 <= intr.width <= MAX_INTRINSICS_SIZE and 1 <= intr.height <= MAX_INTRINSICS_SIZE):
        raise error("intrinsics", f"resolution {intr.width}x{intr.height} is out of range")
    if not (0 <= intr.cx <= intr.width and 0 <= intr.cy <= intr.height):
        raise error("intrinsics", f"principal point ({intr.cx}, {intr.cy}) lies outside the "
                                  f"{intr.width}x{intr.height} image they refer to")
    if not _aspect_close(intr.width, intr.height, w, h):
        raise error("intrinsics", f"stated for {intr.width}x{intr.height}, which does not have the depth's "
                                  f"aspect ratio ({w}x{h}); intrinsics of a cropped image cannot be scaled")
    problem = intrinsics_problem(intr.fx, intr.fy, intr.width, intr.height)
    if problem is not None:
        raise (implausible or error)("intrinsics", problem)


def _parse_header(raw: dict[str, Any], limits: DecodeLimits) -> FrameHeader:
    seq = _int(raw, "seq", "header", 0, MAX_SEQ)
    session = raw.get("session")
    if session is not None and not (isinstance(session, str) and 1 <= len(session) <= MAX_SESSION_CHARS):
        raise FrameDecodeError("header", f"'session' must be null or a string of 1..{MAX_SESSION_CHARS} characters")
    timestamp_s = _num(raw, "timestamp_s", "header")

    dep = _obj(raw, "depth", "depth", required=True)
    depth_encoding = _choice(dep, "encoding", "depth", DEPTH_ENCODINGS, FrameEncodingError)
    units = _key(dep, "units", "depth")
    if units != DEPTH_UNITS[depth_encoding]:
        raise FrameDecodeError("depth", f"units {units!r} do not match encoding {depth_encoding!r} "
                                        f"(which is in {DEPTH_UNITS[depth_encoding]!r})")
    w = _int(dep, "width", "depth", 1, limits.max_width)
    h = _int(dep, "height", "depth", 1, limits.max_height)

    ik = _obj(raw, "intrinsics", "intrinsics", required=True)
    intr = WireIntrinsics(*(_num(ik, k, "intrinsics") for k in ("fx", "fy", "cx", "cy")),
                          _int(ik, "width", "intrinsics", 1, MAX_INTRINSICS_SIZE),
                          _int(ik, "height", "intrinsics", 1, MAX_INTRINSICS_SIZE))
    _check_intrinsics(intr, w, h, FrameDecodeError, FrameValueError)

    col = _obj(raw, "color", "color", required=False)
    color_encoding, cw, ch = None, 0, 0
    if col is not None:
        color_encoding = _choice(col, "encoding", "color", COLOR_ENCODINGS, FrameEncodingError)
        cw = _int(col, "width", "color", 1, limits.max_width)
        ch = _int(col, "height", "color", 1, limits.max_height)
        if not _aspect_close(cw, ch, w, h):
            raise FrameDecodeError("color", f"{cw}x{ch} does not have the depth's aspect ratio ({w}x{h})")

    con = _obj(raw, "confidence", "confidence", required=False)
    conf_encoding = conf_levels = None
    if con is not None:
        conf_encoding = _choice(con, "encoding", "confidence", CONFIDENCE_ENCODINGS, FrameEncodingError)
        conf_levels = _choice(con, "levels", "confidence", CONFIDENCE_LEVELS, FrameEncodingError)

    pose = _obj(raw, "device_pose", "device_pose", required=False)
    T = convention = None
    if pose is not None:
        convention = _choice(pose, "convention", "device_pose", POSE_CONVENTIONS)
        _choice(pose, "layout", "device_pose", (POSE_LAYOUT,))
        m = _key(pose, "matrix", "device_pose")
        if not isinstance(m, list) or len(m) != 16:
            raise FrameDecodeError("device_pose", "'matrix' must be a list of 16 numbers (row-major 4x4)")
        T = np.array([_num({"matrix": v}, "matrix", "device_pose") for v in m], dtype=np.float64).reshape(4, 4)
        try:
            T = check_rigid(T, "device_pose")
        except ValidationError as e:
            raise FrameDecodeError("device_pose", e.problem) from e
        problem = pose_problem(T)
        if problem is not None:
            raise FrameValueError("device_pose", problem)
        if convention == "arkit":
            T = opengl_to_opencv(T)
    return FrameHeader(seq=seq, session=session, timestamp_s=timestamp_s, intrinsics=intr,
                       depth_encoding=depth_encoding, depth_width=w, depth_height=h, color_encoding=color_encoding,
                       color_width=cw, color_height=ch, confidence_encoding=conf_encoding,
                       confidence_levels=conf_levels, device_pose=T, device_pose_convention=convention, raw=raw)


def _split(data: bytes | bytearray | memoryview, limits: DecodeLimits) -> tuple[FrameHeader, Payloads]:
    raw, payloads = unpack_message(data, limits.max_header_bytes)
    hdr = _parse_header(raw, limits)
    if (hdr.color_encoding is None) != (len(payloads.color) == 0):
        raise FrameDecodeError("color", f"header color is {'null' if hdr.color_encoding is None else 'set'} but "
                                        f"the colour payload is {len(payloads.color)} bytes")
    if (hdr.confidence_encoding is None) != (len(payloads.confidence) == 0):
        raise FrameDecodeError("confidence", f"header confidence is "
                                             f"{'null' if hdr.confidence_encoding is None else 'set'} but the "
                                             f"confidence payload is {len(payloads.confidence)} bytes")
    return hdr, payloads


def read_header(data: bytes | bytearray | memoryview, *, limits: DecodeLimits | None = None) -> FrameHeader:
    """Check a message's framing, CRC and header, without decoding any image.

    Raises:
        FrameDecodeError: the message is malformed (``field`` names the part).
    """
    return _split(data, limits or DecodeLimits())[0]


_FRAME_FIELDS = {"depth_m": "depth", "K": "intrinsics", "color": "color", "confidence": "confidence",
                 "T_world_cam_device": "device_pose"}


def decode_frame(data: bytes | bytearray | memoryview, *, limits: DecodeLimits | None = None) -> DecodedFrame:
    """Decode one message into an :class:`RGBDFrame` (see the module docstring for what is normalised).

    Args:
        data: the message bytes.
        limits: size limits (default :class:`DecodeLimits`: 4096x4096 images, 64 KiB header).

    Raises:
        FrameDecodeError: for every malformed message: truncated, wrong magic, unknown version or flags,
            bad CRC, bad JSON, a missing or invalid key, unknown encoding, payload of the wrong size,
            corrupt PNG/JPEG/zstd, sizes that disagree, bad intrinsics, non-rigid pose, oversize images.
        TypeError: ``data`` is not bytes-like.
    """
    hdr, payloads = _split(data, limits or DecodeLimits())
    w, h = hdr.depth_width, hdr.depth_height
    depth_m = decode_depth(payloads.depth, hdr.depth_encoding, w, h)
    color = None
    if hdr.color_encoding is not None:
        color = decode_color(payloads.color, hdr.color_encoding, hdr.color_width, hdr.color_height)
        if (hdr.color_width, hdr.color_height) != (w, h):
            color = cv2.resize(color, (w, h), interpolation=cv2.INTER_AREA)
    confidence = None
    if hdr.confidence_encoding is not None:
        confidence = decode_confidence(payloads.confidence, hdr.confidence_encoding, hdr.confidence_levels or "",
                                       w, h)
    intr = hdr.intrinsics
    K = scale_intrinsics(intr.K, (intr.width, intr.height), (w, h))
    try:
        frame = RGBDFrame(depth_m=depth_m, K=K, timestamp_s=hdr.timestamp_s, color=color, confidence=confidence,
                          T_world_cam_device=hdr.device_pose, index=hdr.seq)
    except ValidationError as e:  # the checks above should make this unreachable; keep the contract anyway
        raise FrameDecodeError(_FRAME_FIELDS.get(e.field, "header"), e.problem) from e
    return DecodedFrame(frame=frame, seq=hdr.seq, session=hdr.session, header=hdr.raw)
