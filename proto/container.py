"""The byte container of the VoxFusion frame format (version 1): prelude, JSON header, payloads, CRC.

This module knows bytes, not images: it packs a header dict and three payload byte strings into one
message and checks a message's framing (magic, version, flags, lengths, CRC, JSON) on the way back.
What the header and payloads *mean* is :mod:`.frame_codec`'s and :mod:`.codecs`' business. The full
byte-level specification is ``proto/README.md``.

Layout (all integers little-endian)::

    offset  size        type    field
    0       4           bytes   magic  b"VXFR"
    4       2           u16     version (1)
    6       2           u16     flags (0; reserved)
    8       4           u32     header_len      (bytes of JSON)
    12      4           u32     color_len       (0 = no colour payload)
    16      4           u32     depth_len       (> 0)
    20      4           u32     confidence_len  (0 = no confidence payload)
    24      header_len          header: one JSON object, UTF-8
    ...     color_len           colour payload
    ...     depth_len           depth payload
    ...     confidence_len      confidence payload
    end-4   4           u32     CRC-32 (ISO-HDLC, as zlib.crc32) of every byte before it

Example::

    data = pack_message({"seq": 0}, Payloads(color=b"", depth=b"...", confidence=b""))
    header, payloads = unpack_message(data)
"""

from __future__ import annotations

import json
import struct
import zlib
from typing import Any, NamedTuple

from voxfusion.core.errors import ValidationError

__all__ = [
    "MAGIC",
    "WIRE_VERSION",
    "MEDIA_TYPE",
    "PRELUDE_SIZE",
    "CRC_SIZE",
    "MAX_HEADER_BYTES",
    "ERROR_FIELDS",
    "FrameDecodeError",
    "FrameValueError",
    "Payloads",
    "pack_message",
    "unpack_message",
]

MAGIC = b"VXFR"
"""First four bytes of every message (ASCII ``VXFR``: VoxFusion fRame)."""
WIRE_VERSION = 1
"""The container version this module writes and the only one it reads."""
MEDIA_TYPE = "application/vnd.voxfusion.frame"
"""HTTP ``Content-Type`` (and zenoh encoding string) of a message."""

_PRELUDE = struct.Struct("<4sHHIIII")
PRELUDE_SIZE = _PRELUDE.size  # 24
"""Bytes before the JSON header."""
CRC_SIZE = 4
"""Bytes of the CRC-32 trailer."""
MAX_HEADER_BYTES = 64 * 1024
"""Default upper bound on ``header_len`` (a real header is ~400 bytes)."""
_U32_MAX = 2**32 - 1

ERROR_FIELDS = ("magic", "version", "flags", "length", "crc", "header", "intrinsics", "depth", "color",
                "confidence", "device_pose")
"""Every value :attr:`FrameDecodeError.field` can take."""


class FrameDecodeError(ValidationError):
    """A message is malformed; ``field`` names the part that is wrong.

    ``field`` is one of ``"magic"``, ``"version"``, ``"flags"``, ``"length"`` (truncated, trailing bytes,
    lengths that do not add up), ``"crc"``, ``"header"`` (JSON, or a scalar key such as ``seq``,
    ``timestamp_s``, ``session``), ``"intrinsics"``, ``"depth"``, ``"color"``, ``"confidence"``,
    ``"device_pose"``; ``problem`` says what is wrong in words. It is a :class:`ValidationError` (so a
    ``VoxFusionError`` and a ``ValueError``): the server maps it to HTTP 400 with the field.
    """


class FrameEncodingError(FrameDecodeError):
    """A payload names an encoding (or confidence levels) this build does not know; the server answers HTTP 415
    with the field (``depth``, ``color``, ``confidence``)."""


class FrameValueError(FrameDecodeError):
    """A well-formed message whose values no camera produces (a field of view outside 2-170 degrees, a
    device pose more than 100 km from its origin: :mod:`voxfusion.core.frame_checks`); the server answers
    HTTP 422 with the field. Checked at the door so one such frame never reaches a session's engine."""


class Payloads(NamedTuple):
    """The three payloads of a message, in wire order; ``b""`` means absent (depth is never absent)."""

    color: bytes
    depth: bytes
    confidence: bytes


def pack_message(header: dict[str, Any], payloads: Payloads) -> bytes:
    """Serialise ``header`` (a JSON-ready dict) and ``payloads`` into one version-1 message.

    The header is written as compact JSON (ASCII, so also valid UTF-8); non-finite floats are refused.
    Raises :class:`ValidationError` (field ``"header"`` or ``"length"``) for what cannot be framed.
    """
    try:
        header_bytes = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as e:
        raise ValidationError("header", f"cannot be written as JSON ({e})") from e
    parts = (header_bytes, payloads.color, payloads.depth, payloads.confidence)
    for name, part in zip(("header", "color", "depth", "confidence"), parts, strict=True):
        if len(part) > _U32_MAX:
            raise ValidationError("length", f"{name} is {len(part)} bytes, more than a u32 can state")
    prelude = _PRELUDE.pack(MAGIC, WIRE_VERSION, 0, len(header_bytes), len(payloads.color), len(payloads.depth),
                            len(payloads.confidence))
    body = b"".join((prelude, *parts))
    return body + struct.pack("<I", zlib.crc32(body))


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} is not allowed")


def unpack_message(data: bytes | bytearray | memoryview,
                   max_header_bytes: int = MAX_HEADER_BYTES) -> tuple[dict[str, Any], Payloads]:
    """Check a message's framing and split it into ``(header dict, payloads)``.

    Checks, in order: magic, version, flags, that the stated lengths add up to ``len(data)`` exactly,
    the CRC-32, and that the header is a UTF-8 JSON object (no ``NaN``/``Infinity``) of at most
    ``max_header_bytes``. The header's *content* is not checked here.

    Raises:
        FrameDecodeError: for any malformed message (never another exception for bytes input).
        TypeError: ``data`` is not bytes-like.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"data must be bytes-like, got {type(data).__name__}")
    data = bytes(data)
    n = len(data)
    if data[:4] != MAGIC[: min(n, 4)]:
        raise FrameDecodeError("magic", f"expected {MAGIC!r}, got {data[:4]!r}: not a VoxFusion frame")
    if n < PRELUDE_SIZE + CRC_SIZE:
        raise FrameDecodeError("length", f"message is {n} bytes, shorter than the "
                                         f"{PRELUDE_SIZE + CRC_SIZE}-byte prelude and CRC")
    _, version, flags, header_len, color_len, depth_len, conf_len = _PRELUDE.unpack_from(data)
    if version != WIRE_VERSION:
        raise FrameDecodeError("version", f"unsupported version {version}; this decoder reads {WIRE_VERSION}")
    if flags != 0:
        raise FrameDecodeError("flags", f"unknown flags 0x{flags:04x}; version {WIRE_VERSION} defines none")
    expected = PRELUDE_SIZE + header_len + color_len + depth_len + conf_len + CRC_SIZE
    if expected != n:
        raise FrameDecodeError("length", f"lengths in the prelude add up to {expected} bytes, message has {n} "
                                         f"(header {header_len}, color {color_len}, depth {depth_len}, "
                                         f"confidence {conf_len})")
    (crc_stated,) = struct.unpack_from("<I", data, n - CRC_SIZE)
    crc_actual = zlib.crc32(memoryview(data)[: n - CRC_SIZE])
    if crc_stated != crc_actual:
        raise FrameDecodeError("crc", f"CRC-32 mismatch (stated 0x{crc_stated:08x}, computed 0x{crc_actual:08x}): "
                                      "the message is corrupt")
    if header_len > max_header_bytes:
        raise FrameDecodeError("header", f"header is {header_len} bytes, more than the {max_header_bytes} allowed")
    if depth_len == 0:
        raise FrameDecodeError("depth", "depth payload is empty; every frame carries depth")
    o = PRELUDE_SIZE
    try:
        header = json.loads(data[o : o + header_len].decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise FrameDecodeError("header", f"not valid UTF-8 JSON ({e})") from e
    if not isinstance(header, dict):
        raise FrameDecodeError("header", f"must be a JSON object, got {type(header).__name__}")
    o += header_len
    color = data[o : o + color_len]
    o += color_len
    depth = data[o : o + depth_len]
    o += depth_len
    confidence = data[o : o + conf_len]
    return header, Payloads(color=color, depth=depth, confidence=confidence)
