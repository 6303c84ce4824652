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
``color``        JPEG or PNG (RGB), any size with the intrinsics' (and depth's) aspect ratio; optional
``confidence``   8-bit greyscale PNG or raw bytes (one per depth pixel), levels 0/1/2; optional
===============  =====================================================================================

``metadata`` keys: ``seq`` (int >= 0, required), ``timestamp_s`` (seconds, required), ``intrinsics``
(``{fx, fy, cx, cy, width, height}``: pixels, for the stated resolution, required), ``depth_encoding``
(``png16_mm`` | ``raw_f16_m`` | ``raw_f32_m`` | ``zstd_u16_mm`` | ``zstd_f16_m``; default ``png16_mm``
for a PNG part), ``depth_width`` / ``depth_height`` (required unless the depth is a PNG),
``color_width`` / ``color_height`` (optional), ``color_encoding`` (``jpeg`` | ``png``; default from the
bytes), ``confidence_encoding`` (``png8`` | ``raw_u8`` | ``zstd_u8``; default from the bytes),
``confidence_levels`` (``0-2`` default, or ``0-255``),
``device_pose`` (``{"convention": "opencv" | "arkit", "matrix": 16 numbers row-major camera-to-world}``),
``session`` (optional; must be the URL's session).

Sizes are checked against what the upload declares before anything is packed, and a mismatch is refused
with :class:`~voxfusion.core.errors.ValidationError` (422) naming the part, never rescaled to fit:

* ``depth``: the image (PNG header, or the byte count of a raw payload) is exactly ``depth_width`` x
  ``depth_height`` when those are given, and has the aspect ratio of the intrinsics' ``width`` x
  ``height`` (within 1 %);
* ``color``: exactly ``color_width`` x ``color_height`` when given, and the aspect ratio of the intrinsics
  and of the depth;
* ``confidence``: exactly the depth's size (PNG header, raw byte count, zstd content size).

What the binary frame format allows (``proto/README.md`` §2, §3.2, §4) stays allowed, so both bodies take
the same frames: intrinsics may be stated for another resolution of the same aspect ratio (ARKit's
1920x1440 with 256x192 depth; they are scaled exactly, §4), and colour may be larger or smaller than the
depth at the same aspect ratio (640x480 with 256x192 depth); the decoder resizes it to the depth's size
(§3.2). Malformed metadata and corrupt or truncated images stay 400, unknown encodings 415. Only image
headers are read here, never pixels: an image whose header declares more pixels than Pillow's
decompression-bomb limit (about 179 million, e.g. 30000x30000) is 413 naming the part, and one larger than the
server's ``max_image_width`` x ``max_image_height`` is 413 when the packed message is checked
(:func:`check_message_limits`), before anything is decoded.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from typing import Any

import zstandard
from PIL import Image, UnidentifiedImageError

from voxfusion.core.errors import ValidationError
from voxfusion.proto import DEPTH_ENCODINGS, FrameDecodeError, FrameEncodingError, FrameHeader, read_header
from voxfusion.proto.codecs import DEPTH_UNITS
from voxfusion.proto.container import Payloads, pack_message
from voxfusion.proto.frame_codec import ASPECT_TOLERANCE, DecodeLimits

from .errors import PayloadTooLargeError

__all__ = ["UploadPart", "MULTIPART_DEPTH_ENCODINGS", "check_message_limits", "message_from_multipart"]

MULTIPART_DEPTH_ENCODINGS = ("png16_mm", "raw_f16_m", "raw_f32_m", "zstd_u16_mm", "zstd_f16_m")
"""Depth encodings a multipart ``depth`` part may use (``raw_f16_m`` is wrapped into ``zstd_f16_m``)."""
_METADATA_KEYS = {"seq", "timestamp_s", "intrinsics", "depth_encoding", "depth_width", "depth_height",
                  "color_encoding", "color_width", "color_height", "confidence_encoding", "confidence_levels",
                  "device_pose", "session"}
_BYTES_PER_PIXEL = {"raw_f16_m": 2, "raw_f32_m": 4, "zstd_u16_mm": 2, "zstd_f16_m": 2, "raw_u8": 1, "zstd_u8": 1}
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
    """Width and height in pixels that an image's header states (the pixel data is not decoded).

    Raises:
        PayloadTooLargeError: the header states more pixels than Pillow's decompression-bomb limit
            (``2 * Image.MAX_IMAGE_PIXELS``, about 179 million), far beyond any server's image limit (413).
        FrameDecodeError: not a readable image: truncated, corrupt or unknown header (400).
    """
    try:
        with Image.open(io.BytesIO(data)) as im:
            return int(im.size[0]), int(im.size[1])
    except Image.DecompressionBombError as e:
        raise PayloadTooLargeError(f"the {kind} header declares an image too large to accept ({e})", field) from e
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise FrameDecodeError(field, f"not a readable {kind} image ({e})") from e
    except Exception as e:  # noqa: BLE001 - Pillow raises many types for corrupt headers; all mean the same here
        raise FrameDecodeError(field, f"not a readable {kind} image ({type(e).__name__}: {e})") from e


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


def _declared_size(meta: dict[str, Any], part: str) -> tuple[int, int] | None:
    """``(<part>_width, <part>_height)`` from the metadata, ``None`` when neither is given."""
    if meta.get(f"{part}_width") is None and meta.get(f"{part}_height") is None:
        return None
    return _int_key(meta, f"{part}_width", part), _int_key(meta, f"{part}_height", part)


def _intrinsics_size(meta: dict[str, Any]) -> tuple[int, int] | None:
    """The resolution the intrinsics are stated for; ``None`` when it is malformed (the decoder says so, 400)."""
    intr = meta.get("intrinsics")
    if not isinstance(intr, dict):
        return None
    w, h = intr.get("width"), intr.get("height")
    if any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in (w, h)):
        return None
    return w, h


def _same_aspect(w1: int, h1: int, w2: int, h2: int) -> bool:
    """The binary format's rule (``proto/README.md`` §5): width/height ratios within 1 %."""
    return abs(w1 / h1 - w2 / h2) <= ASPECT_TOLERANCE * (w2 / h2)


def _check_byte_count(data: bytes, enc: str, w: int, h: int, field: str) -> None:
    """A raw payload holds exactly ``w*h`` pixels; a zstd one too when its frame states its content size."""
    n = _BYTES_PER_PIXEL.get(enc)
    if n is None:
        return
    size = len(data)
    if enc.startswith("zstd_"):
        try:
            size = zstandard.frame_content_size(data)
        except zstandard.ZstdError:
            return  # not a zstd frame: the decoder refuses it (400)
        if size < 0:
            return  # size not in the frame header: the decoder checks the decompressed size
    if size != n * w * h:
        what = "decompresses to" if enc.startswith("zstd_") else "is"
        raise ValidationError(field, f"{enc} payload {what} {size} bytes, but {w}x{h} pixels need {n * w * h}")


def _depth_payload(meta: dict[str, Any], depth: UploadPart) -> tuple[bytes, dict[str, Any]]:
    sniffed = _sniff(depth.data)
    enc = meta.get("depth_encoding") or ("png16_mm" if sniffed == "png" or depth.content_type == "image/png"
                                         else None)
    if enc is None:
        raise FrameDecodeError("depth", "metadata 'depth_encoding' is required for a non-PNG depth part "
                                        f"(one of {', '.join(MULTIPART_DEPTH_ENCODINGS)})")
    if enc not in MULTIPART_DEPTH_ENCODINGS:
        raise FrameEncodingError("depth", f"unknown encoding {enc!r}; expected one of "
                                        f"{', '.join(MULTIPART_DEPTH_ENCODINGS)}")
    if enc == "png16_mm":
        w, h = _image_size(depth.data, "depth", "PNG")
        declared = _declared_size(meta, "depth")
        if declared is not None and declared != (w, h):
            raise ValidationError("depth", f"the PNG is {w}x{h} but the metadata declares depth_width x depth_height "
                                           f"{declared[0]}x{declared[1]}")
    else:
        w, h = _int_key(meta, "depth_width", "depth"), _int_key(meta, "depth_height", "depth")
        _check_byte_count(depth.data, enc, w, h, "depth")
    payload = depth.data
    if enc == "raw_f16_m":
        payload = zstandard.ZstdCompressor(level=1).compress(payload)
        enc = "zstd_f16_m"
    if enc not in DEPTH_ENCODINGS:  # pragma: no cover - every multipart encoding maps onto a wire one
        raise FrameEncodingError("depth", f"unknown encoding {enc!r}")
    return payload, {"encoding": enc, "units": DEPTH_UNITS[enc], "width": w, "height": h}


def message_from_multipart(metadata: bytes | str, depth: UploadPart, color: UploadPart | None = None,
                           confidence: UploadPart | None = None) -> bytes:
    """Pack a multipart upload (module docstring) into one frame message; images are not re-encoded.

    Raises:
        FrameDecodeError: bad metadata or a part that cannot be what it claims (``field`` names it); the
            message is fully checked later by :func:`decode_frame`.
        ValidationError: an image does not match the sizes the upload declares (module docstring; 422,
            ``field`` is ``depth``, ``color`` or ``confidence``).
        PayloadTooLargeError: an image header declares a decompression bomb (413, ``field`` names the part).
    """
    meta = _parse_metadata(metadata)
    for key in ("seq", "timestamp_s", "intrinsics"):
        if key not in meta:
            raise FrameDecodeError("intrinsics" if key == "intrinsics" else "header",
                                   f"metadata key {key!r} is required")
    header: dict[str, Any] = {"session": meta.get("session"), "seq": meta["seq"], "timestamp_s": meta["timestamp_s"],
                              "intrinsics": meta["intrinsics"]}
    depth_bytes, header["depth"] = _depth_payload(meta, depth)
    intr = _intrinsics_size(meta)
    dw, dh = header["depth"]["width"], header["depth"]["height"]
    if intr is not None and not _same_aspect(dw, dh, *intr):
        raise ValidationError("depth", f"{dw}x{dh} does not have the aspect ratio of the {intr[0]}x{intr[1]} the "
                                       "intrinsics are stated for; images are not rescaled to fit")

    color_bytes = b""
    header["color"] = None
    if color is not None and color.data:
        enc = meta.get("color_encoding") or _sniff(color.data)
        if enc is None:
            raise FrameDecodeError("color", "colour part is neither JPEG nor PNG; set metadata 'color_encoding'")
        if enc not in ("jpeg", "png"):
            raise FrameEncodingError("color", f"unknown encoding {enc!r}; expected one of jpeg, png")
        cw, ch = _image_size(color.data, "color", enc.upper())
        declared = _declared_size(meta, "color")
        if declared is not None and declared != (cw, ch):
            raise ValidationError("color", f"the {enc.upper()} is {cw}x{ch} but the metadata declares color_width x "
                                           f"color_height {declared[0]}x{declared[1]}")
        if not _same_aspect(cw, ch, dw, dh) or (intr is not None and not _same_aspect(cw, ch, *intr)):
            shown = f", intrinsics {intr[0]}x{intr[1]}" if intr is not None else ""
            raise ValidationError("color", f"{cw}x{ch} does not have the aspect ratio of the declared sizes (depth "
                                           f"{dw}x{dh}{shown}); colour is only resized between sizes of the same "
                                           "aspect ratio")
        color_bytes = color.data
        header["color"] = {"encoding": enc, "width": cw, "height": ch}

    conf_bytes = b""
    header["confidence"] = None
    if confidence is not None and confidence.data:
        enc = meta.get("confidence_encoding") or ("png8" if _sniff(confidence.data) == "png" else "raw_u8")
        if enc == "png8" and _sniff(confidence.data) == "png":
            qw, qh = _image_size(confidence.data, "confidence", "PNG")
            if (qw, qh) != (dw, dh):
                raise ValidationError("confidence", f"the PNG is {qw}x{qh}; confidence must be the depth's {dw}x{dh}")
        else:
            _check_byte_count(confidence.data, enc, dw, dh, "confidence")
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
