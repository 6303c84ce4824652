"""Frame uploads: size checks of a frame message, and multipart uploads turned into a frame message.

Every frame the server accepts, whatever it arrived as, becomes one frame message
(``proto/README.md``): that is what is recorded and replayed, and what :func:`decode_frame` checks. A
multipart upload is repacked into a message *without re-encoding* its images (a 16-bit PNG stays the
``png16_mm`` payload, a JPEG the ``jpeg`` payload); raw float16 depth is wrapped losslessly in zstd
(``zstd_f16_m``).

Multipart form (``POST /sessions/{id}/frames``, ``Content-Type: multipart/form-data``):

===============  =====================================================================================
part             content
===============  =====================================================================================
``metadata``     JSON object (below), required
``depth``        16-bit greyscale PNG (millimetres), or raw little-endian float16 / float32 metres, or a
                 zstd payload of the frame format; required
``color``        JPEG or PNG (RGB), any size with the depth's aspect ratio; optional
``confidence``   8-bit greyscale PNG or raw bytes (one per depth pixel), levels 0/1/2; optional
===============  =====================================================================================

``metadata`` keys: ``seq`` (int >= 0, required), ``timestamp_s`` (seconds, required), ``intrinsics``
(``{fx, fy, cx, cy, width, height}``: pixels, for the stated resolution, required), ``depth_encoding``
(``png16_mm`` | ``raw_f16_m`` | ``raw_f32_m`` | ``zstd_u16_mm`` | ``zstd_f16_m``; default ``png16_mm``
for a PNG part), ``depth_width`` / ``depth_height`` (required unless the depth is a PNG),
``color_encoding`` (``jpeg`` | ``png``; default from the bytes), ``confidence_encoding`` (``png8`` |
``raw_u8`` | ``zstd_u8``; default from the bytes), ``confidence_levels`` (``0-2`` default, or ``0-255``),
``device_pose`` (``{"convention": "opencv" | "arkit", "matrix": 16 numbers row-major camera-to-world}``),
``session`` (optional; must be the URL's session).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from typing import Any

import zstandard
from PIL import Image, UnidentifiedImageError

from voxfusion.proto import DEPTH_ENCODINGS, FrameDecodeError, FrameHeader, read_header
from voxfusion.proto.codecs import DEPTH_UNITS
from voxfusion.proto.container import Payloads, pack_message
from voxfusion.proto.frame_codec import DecodeLimits

from .errors import PayloadTooLargeError

__all__ = ["UploadPart", "MULTIPART_DEPTH_ENCODINGS", "check_message_limits", "message_from_multipart"]

MULTIPART_DEPTH_ENCODINGS = ("png16_mm", "raw_f16_m", "raw_f32_m", "zstd_u16_mm", "zstd_f16_m")
"""Depth encodings a multipart ``depth`` part may use (``raw_f16_m`` is wrapped into ``zstd_f16_m``)."""
_METADATA_KEYS = {"seq", "timestamp_s", "intrinsics", "depth_encoding", "depth_width", "depth_height",
                  "color_encoding", "confidence_encoding", "confidence_levels", "device_pose", "session"}
_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG = b"\xff\xd8\xff"
_UNLIMITED = DecodeLimits(max_width=1 << 16, max_height=1 << 16)


@dataclass(frozen=True)
class UploadPart:
    """One uploaded file part: its bytes and the ``Content-Type`` the client gave it (may be empty)."""

    data: bytes
    content_type: str = ""


def check_message_limits(data: bytes, max_width: int, max_height: int) -> FrameHeader:
    """Check a message's framing and header, then its image sizes against the server's limits.

    Raises:
        FrameDecodeError: malformed message (400 / 415).
        PayloadTooLargeError: an image is larger than ``max_width`` x ``max_height`` (413).
    """
    hdr = read_header(data, limits=_UNLIMITED)
    for name, w, h in (("depth", hdr.depth_width, hdr.depth_height), ("color", hdr.color_width, hdr.color_height)):
        if w > max_width or h > max_height:
            raise PayloadTooLargeError(f"{name} image is {w}x{h}, larger than this server's limit of "
                                  f"{max_width}x{max_height} pixels", name)
    return hdr


def _reject_constant(name: str) -> Any:
    raise ValueError(f"non-finite number {name} is not allowed")


def _image_size(data: bytes, field: str, kind: str) -> tuple[int, int]:
    try:
        with Image.open(io.BytesIO(data)) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise FrameDecodeError(field, f"not a readable {kind} image ({e})") from e


def _sniff(data: bytes) -> str | None:
    if data.startswith(_PNG):
        return "png"
    if data.startswith(_JPEG):
        return "jpeg"
    return None


def _int_key(meta: dict[str, Any], key: str, field: str) -> int:
    v = meta.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise FrameDecodeError(field, f"metadata {key!r} must be a positive integer, got {v!r}")
    return v


def _parse_metadata(raw: bytes | str) -> dict[str, Any]:
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else raw
        meta = json.loads(text, parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError) as e:
        raise FrameDecodeError("header", f"metadata is not valid UTF-8 JSON ({e})") from e
    if not isinstance(meta, dict):
        raise FrameDecodeError("header", f"metadata must be a JSON object, got {type(meta).__name__}")
    unknown = sorted(set(meta) - _METADATA_KEYS)
    if unknown:
        raise FrameDecodeError("header", f"unknown metadata key {unknown[0]!r}; known: {sorted(_METADATA_KEYS)}")
    return meta


def _depth_payload(meta: dict[str, Any], depth: UploadPart) -> tuple[bytes, dict[str, Any]]:
    sniffed = _sniff(depth.data)
    enc = meta.get("depth_encoding") or ("png16_mm" if sniffed == "png" or depth.content_type == "image/png"
                                         else None)
    if enc is None:
        raise FrameDecodeError("depth", "metadata 'depth_encoding' is required for a non-PNG depth part "
                                        f"(one of {', '.join(MULTIPART_DEPTH_ENCODINGS)})")
    if enc not in MULTIPART_DEPTH_ENCODINGS:
        raise FrameDecodeError("depth", f"unknown encoding {enc!r}; expected one of "
                                        f"{', '.join(MULTIPART_DEPTH_ENCODINGS)}")
    if enc == "png16_mm":
        w, h = _image_size(depth.data, "depth", "PNG")
    else:
        w, h = _int_key(meta, "depth_width", "depth"), _int_key(meta, "depth_height", "depth")
    payload = depth.data
    if enc == "raw_f16_m":
        if len(payload) != 2 * w * h:
            raise FrameDecodeError("depth", f"raw float16 depth of {w}x{h} must be {2 * w * h} bytes, "
                                            f"got {len(payload)}")
        payload = zstandard.ZstdCompressor(level=1).compress(payload)
        enc = "zstd_f16_m"
    if enc not in DEPTH_ENCODINGS:  # pragma: no cover - every multipart encoding maps onto a wire one
        raise FrameDecodeError("depth", f"unknown encoding {enc!r}")
    return payload, {"encoding": enc, "units": DEPTH_UNITS[enc], "width": w, "height": h}


def message_from_multipart(metadata: bytes | str, depth: UploadPart, color: UploadPart | None = None,
                           confidence: UploadPart | None = None) -> bytes:
    """Pack a multipart upload (module docstring) into one frame message; images are not re-encoded.

    Raises:
        FrameDecodeError: bad metadata or a part that cannot be what it claims (``field`` names it); the
            message is fully checked later by :func:`decode_frame`.
    """
    meta = _parse_metadata(metadata)
    for key in ("seq", "timestamp_s", "intrinsics"):
        if key not in meta:
            raise FrameDecodeError("intrinsics" if key == "intrinsics" else "header",
                                   f"metadata key {key!r} is required")
    header: dict[str, Any] = {"session": meta.get("session"), "seq": meta["seq"], "timestamp_s": meta["timestamp_s"],
                              "intrinsics": meta["intrinsics"]}
    depth_bytes, header["depth"] = _depth_payload(meta, depth)

    color_bytes = b""
    header["color"] = None
    if color is not None and color.data:
        enc = meta.get("color_encoding") or _sniff(color.data)
        if enc is None:
            raise FrameDecodeError("color", "colour part is neither JPEG nor PNG; set metadata 'color_encoding'")
        if enc not in ("jpeg", "png"):
            raise FrameDecodeError("color", f"unknown encoding {enc!r}; expected one of jpeg, png")
        cw, ch = _image_size(color.data, "color", enc.upper())
        color_bytes = color.data
        header["color"] = {"encoding": enc, "width": cw, "height": ch}

    conf_bytes = b""
    header["confidence"] = None
    if confidence is not None and confidence.data:
        enc = meta.get("confidence_encoding") or ("png8" if _sniff(confidence.data) == "png" else "raw_u8")
        conf_bytes = confidence.data
        header["confidence"] = {"encoding": enc, "levels": meta.get("confidence_levels", "0-2")}

    pose = meta.get("device_pose")
    if pose is not None:
        if not isinstance(pose, dict):
            raise FrameDecodeError("device_pose", "metadata 'device_pose' must be an object {convention, matrix}")
        matrix = pose.get("matrix")
        if isinstance(matrix, list) and len(matrix) == 4 and all(isinstance(r, list) for r in matrix):
            matrix = [v for row in matrix for v in row]
        pose = {"convention": pose.get("convention", "opencv"), "layout": pose.get("layout", "row-major-c2w"),
                "matrix": matrix}
    header["device_pose"] = pose
    try:
        return pack_message(header, Payloads(color=color_bytes, depth=depth_bytes, confidence=conf_bytes))
    except ValueError as e:  # e.g. a value JSON cannot hold
        raise FrameDecodeError("header", str(e)) from e
