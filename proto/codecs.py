"""Payload codecs of the frame format: depth, colour and confidence images to bytes and back.

Every decoder is told the width and height the header declares and checks the payload against them
*before* allocating the full image (PNG/JPEG sizes are read from the image header; zstd output is
bounded by the declared size), so a hostile message cannot make the decoder allocate more than
``width * height`` pixels. Every decoder raises :class:`FrameDecodeError` with the payload's name as
``field`` for anything it cannot decode; encoders raise :class:`ValidationError` for bad arguments.

Encodings (byte-level details in ``proto/README.md``):

=================  ==================================================================================
depth
``png16_mm``       16-bit greyscale PNG, uint16 millimetres, 0 = invalid
``zstd_u16_mm``    one zstd frame of ``H*W`` uint16 LE millimetres, row-major, 0 = invalid
``zstd_f16_m``     one zstd frame of ``H*W`` IEEE-754 binary16 LE metres; <= 0 / NaN / inf = invalid
``raw_f32_m``      ``H*W`` IEEE-754 binary32 LE metres, uncompressed; <= 0 / NaN / inf = invalid
colour
``jpeg``           baseline or progressive JPEG, 3 channels (greyscale is accepted and expanded)
``png``            8-bit RGB PNG (grey / RGBA / 16-bit are accepted and converted to 8-bit RGB)
``raw_rgb8``       ``H*W*3`` bytes, row-major, R G B per pixel
confidence
``raw_u8``         ``H*W`` bytes, row-major
``zstd_u8``        one zstd frame of ``H*W`` bytes
``png8``           8-bit greyscale PNG
=================  ==================================================================================

Confidence levels: ``"0-2"`` (0 low, 1 medium, 2 high: ARKit, Stray) or ``"0-255"`` (0/127/255, Polycam
style; any byte ``v`` maps to ``round(v / 127.5)``, i.e. 0-63 -> 0, 64-191 -> 1, 192-255 -> 2).
"""

from __future__ import annotations

import io
import numbers
from typing import Literal, get_args

import cv2
import numpy as np
import zstandard
from PIL import Image

from voxfusion.core.errors import ShapeError, ValidationError

from .container import FrameDecodeError, FrameEncodingError

__all__ = [
    "DepthEncoding",
    "ColorEncoding",
    "ConfidenceEncoding",
    "ConfidenceLevels",
    "DEPTH_ENCODINGS",
    "DEPTH_UNITS",
    "COLOR_ENCODINGS",
    "CONFIDENCE_ENCODINGS",
    "CONFIDENCE_LEVELS",
    "MAX_DEPTH_MM_M",
    "encode_depth",
    "decode_depth",
    "encode_color",
    "decode_color",
    "encode_confidence",
    "decode_confidence",
]

DepthEncoding = Literal["png16_mm", "zstd_u16_mm", "zstd_f16_m", "raw_f32_m"]
ColorEncoding = Literal["jpeg", "png", "raw_rgb8"]
ConfidenceEncoding = Literal["raw_u8", "zstd_u8", "png8"]
ConfidenceLevels = Literal["0-2", "0-255"]

DEPTH_ENCODINGS: tuple[str, ...] = get_args(DepthEncoding)
DEPTH_UNITS: dict[str, str] = {"png16_mm": "mm", "zstd_u16_mm": "mm", "zstd_f16_m": "m", "raw_f32_m": "m"}
"""The ``units`` each depth encoding states in the header."""
COLOR_ENCODINGS: tuple[str, ...] = get_args(ColorEncoding)
CONFIDENCE_ENCODINGS: tuple[str, ...] = get_args(ConfidenceEncoding)
CONFIDENCE_LEVELS: tuple[str, ...] = get_args(ConfidenceLevels)

MAX_DEPTH_MM_M = 65.535
"""Largest depth (metres) the millimetre encodings hold; farther depth is sent as 0 (invalid)."""
_F16_MAX = 65504.0
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8\xff"
_CONF_255_LUT = np.zeros(256, dtype=np.uint8)
_CONF_255_LUT[64:192] = 1
_CONF_255_LUT[192:] = 2


# ----------------------------------------------------------------------------------------- helpers


def _check_choice(value: str, choices: tuple[str, ...], field: str) -> None:
    if value not in choices:
        raise ValidationError(field, f"unknown encoding {value!r}; expected one of {', '.join(choices)}")


def _zstd_compress(raw: bytes, level: int) -> bytes:
    if not -7 <= level <= 22:
        raise ValidationError("zstd_level", f"must be in [-7, 22], got {level}")
    return zstandard.ZstdCompressor(level=level, write_content_size=True).compress(raw)


def _zstd_decompress(payload: bytes, n_bytes: int, field: str) -> bytes:
    """Decompress one zstd frame that must hold exactly ``n_bytes``; never allocates more."""
    try:
        stated = zstandard.frame_content_size(payload)
    except zstandard.ZstdError as e:
        raise FrameDecodeError(field, f"not a zstd frame ({e})") from e
    if stated not in (-1, n_bytes):
        raise FrameDecodeError(field, f"zstd frame holds {stated} bytes, the declared size needs {n_bytes}")
    try:
        raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=n_bytes, allow_extra_data=False)
    except zstandard.ZstdError as e:
        raise FrameDecodeError(field, f"corrupt zstd data ({e})") from e
    if len(raw) != n_bytes:
        raise FrameDecodeError(field, f"zstd data decompressed to {len(raw)} bytes, expected {n_bytes}")
    return raw


def _png_encode(img: np.ndarray, level: int) -> bytes:
    if not 0 <= level <= 9:
        raise ValidationError("png_compression", f"must be in [0, 9], got {level}")
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level])
    if not ok:  # pragma: no cover - OpenCV cannot fail on a valid uint8/uint16 array
        raise ValidationError("png", "OpenCV could not encode the image")
    return buf.tobytes()


def _imdecode(payload: bytes, kind: Literal["PNG", "JPEG"], width: int, height: int, flags: int,
              field: str) -> np.ndarray:
    """Decode a PNG/JPEG after checking its signature and that its stated size is ``width`` x ``height``."""
    signature = _PNG_SIGNATURE if kind == "PNG" else _JPEG_SIGNATURE
    if not payload.startswith(signature):
        raise FrameDecodeError(field, f"payload is not a {kind} (bad signature {payload[:8]!r})")
    try:  # reads the image header only: the pixel data is not touched
        with Image.open(io.BytesIO(payload), formats=[kind]) as im:
            size = im.size
    except Exception as e:  # Pillow raises many types for corrupt headers; all mean the same here
        raise FrameDecodeError(field, f"corrupt {kind} header ({type(e).__name__}: {e})") from e
    if size != (width, height):
        raise FrameDecodeError(field, f"{kind} is {size[0]}x{size[1]}, the header declares {width}x{height}")
    try:
        img = cv2.imdecode(np.frombuffer(payload, dtype=np.uint8), flags)
    except cv2.error as e:
        raise FrameDecodeError(field, f"corrupt {kind} ({e})") from e
    if img is None:
        raise FrameDecodeError(field, f"corrupt {kind} (OpenCV could not decode it)")
    if img.shape[:2] != (height, width):
        raise FrameDecodeError(field, f"{kind} decoded to {img.shape[1]}x{img.shape[0]}, "
                                      f"the header declares {width}x{height}")
    return img


def _raw(payload: bytes, n_bytes: int, field: str) -> bytes:
    if len(payload) != n_bytes:
        raise FrameDecodeError(field, f"raw payload is {len(payload)} bytes, the declared size needs {n_bytes}")
    return payload


# ------------------------------------------------------------------------------------------- depth


def encode_depth(depth_m: np.ndarray, encoding: DepthEncoding = "zstd_u16_mm", *, zstd_level: int = 3,
                 png_compression: int = 1) -> bytes:
    """Encode ``[H, W]`` depth in metres (0 = invalid) as a depth payload.

    Non-finite and negative depth is sent as invalid. The millimetre encodings round to the nearest mm
    and send depth beyond :data:`MAX_DEPTH_MM_M` as 0; ``zstd_f16_m`` keeps ~11 significant bits
    (relative error <= 4.9e-4) and sends depth beyond 65504 m as 0; ``raw_f32_m`` is exact.
    """
    _check_choice(encoding, DEPTH_ENCODINGS, "depth_encoding")
    d = np.asarray(depth_m)
    if d.ndim != 2 or d.size == 0:
        raise ShapeError("depth_m", d.shape, "[H, W] with H, W >= 1")
    d = d.astype(np.float32, copy=False)
    valid = np.isfinite(d) & (d > 0)
    if encoding in ("png16_mm", "zstd_u16_mm"):
        mm = np.where(valid, np.rint(d * np.float32(1000.0)), np.float32(0.0))
        mm[mm > 65535] = 0
        u16 = mm.astype("<u2")
        if encoding == "png16_mm":
            return _png_encode(u16.astype(np.uint16, copy=False), png_compression)
        return _zstd_compress(u16.tobytes(), zstd_level)
    if encoding == "zstd_f16_m":
        f16 = np.where(valid & (d <= _F16_MAX), d, np.float32(0.0)).astype("<f2")
        return _zstd_compress(f16.tobytes(), zstd_level)
    return np.where(valid, d, np.float32(0.0)).astype("<f4").tobytes()


def decode_depth(payload: bytes, encoding: str, width: int, height: int) -> np.ndarray:
    """Decode a depth payload declared as ``width`` x ``height`` to ``[H, W]`` float32 metres, 0 = invalid."""
    n = width * height
    if encoding == "png16_mm":
        img = _imdecode(payload, "PNG", width, height, cv2.IMREAD_UNCHANGED, "depth")
        if img.ndim != 2 or img.dtype != np.uint16:
            raise FrameDecodeError("depth", f"png16_mm must be a single-channel 16-bit PNG, got {img.dtype} "
                                            f"with shape {img.shape}")
        return img.astype(np.float32) / np.float32(1000.0)
    if encoding == "zstd_u16_mm":
        raw = _zstd_decompress(payload, 2 * n, "depth")
        return (np.frombuffer(raw, dtype="<u2").astype(np.float32) / np.float32(1000.0)).reshape(height, width)
    if encoding == "zstd_f16_m":
        d = np.frombuffer(_zstd_decompress(payload, 2 * n, "depth"), dtype="<f2").astype(np.float32)
    elif encoding == "raw_f32_m":
        d = np.frombuffer(_raw(payload, 4 * n, "depth"), dtype="<f4").astype(np.float32)
    else:
        raise FrameEncodingError("depth",
                                 f"unknown encoding {encoding!r}; expected one of {', '.join(DEPTH_ENCODINGS)}")
    with np.errstate(invalid="ignore"):
        d[~(d > 0) | ~np.isfinite(d)] = 0.0
    return d.reshape(height, width)


# ------------------------------------------------------------------------------------------ colour


def encode_color(color: np.ndarray, encoding: ColorEncoding = "jpeg", *, jpeg_quality: int = 90,
                 png_compression: int = 1) -> bytes:
    """Encode ``[H, W, 3]`` uint8 RGB as a colour payload (``jpeg_quality`` in [1, 100])."""
    _check_choice(encoding, COLOR_ENCODINGS, "color_encoding")
    c = np.asarray(color)
    if c.ndim != 3 or c.shape[2] != 3 or c.size == 0:
        raise ShapeError("color", c.shape, "[H, W, 3] with H, W >= 1")
    if c.dtype != np.uint8:
        raise ValidationError("color", f"dtype must be uint8, got {c.dtype}")
    if encoding == "raw_rgb8":
        return np.ascontiguousarray(c).tobytes()
    bgr = cv2.cvtColor(np.ascontiguousarray(c), cv2.COLOR_RGB2BGR)
    if encoding == "png":
        return _png_encode(bgr, png_compression)
    if isinstance(jpeg_quality, bool) or not (isinstance(jpeg_quality, numbers.Integral) and 1 <= jpeg_quality <= 100):
        raise ValidationError("jpeg_quality", f"must be an integer in [1, 100], got {jpeg_quality!r}")
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:  # pragma: no cover - OpenCV cannot fail on a valid uint8 array
        raise ValidationError("color", "OpenCV could not encode the JPEG")
    return buf.tobytes()


def decode_color(payload: bytes, encoding: str, width: int, height: int) -> np.ndarray:
    """Decode a colour payload declared as ``width`` x ``height`` to ``[H, W, 3]`` uint8 RGB."""
    if encoding == "raw_rgb8":
        raw = _raw(payload, width * height * 3, "color")
        return np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3).copy()
    if encoding not in ("jpeg", "png"):
        raise FrameEncodingError("color",
                                 f"unknown encoding {encoding!r}; expected one of {', '.join(COLOR_ENCODINGS)}")
    kind: Literal["PNG", "JPEG"] = "JPEG" if encoding == "jpeg" else "PNG"
    bgr = _imdecode(payload, kind, width, height, cv2.IMREAD_COLOR, "color")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


# -------------------------------------------------------------------------------------- confidence


def encode_confidence(confidence: np.ndarray, encoding: ConfidenceEncoding = "zstd_u8", *, zstd_level: int = 3,
                      png_compression: int = 1) -> bytes:
    """Encode ``[H, W]`` uint8 confidence in {0, 1, 2} as a payload with levels ``"0-2"``."""
    _check_choice(encoding, CONFIDENCE_ENCODINGS, "confidence_encoding")
    c = np.asarray(confidence)
    if c.ndim != 2 or c.size == 0:
        raise ShapeError("confidence", c.shape, "[H, W] with H, W >= 1")
    if c.dtype != np.uint8:
        raise ValidationError("confidence", f"dtype must be uint8, got {c.dtype}")
    if c.size and int(c.max()) > 2:
        raise ValidationError("confidence", f"values must be 0, 1 or 2, got a maximum of {int(c.max())}")
    c = np.ascontiguousarray(c)
    if encoding == "raw_u8":
        return c.tobytes()
    if encoding == "zstd_u8":
        return _zstd_compress(c.tobytes(), zstd_level)
    return _png_encode(c, png_compression)


def decode_confidence(payload: bytes, encoding: str, levels: str, width: int, height: int) -> np.ndarray:
    """Decode a confidence payload (``width`` x ``height``, the depth's size) to ``[H, W]`` uint8 in {0, 1, 2}."""
    if levels not in CONFIDENCE_LEVELS:
        raise FrameEncodingError("confidence", f"unknown levels {levels!r}; expected one of "
                                             f"{', '.join(CONFIDENCE_LEVELS)}")
    n = width * height
    if encoding == "raw_u8":
        c = np.frombuffer(_raw(payload, n, "confidence"), dtype=np.uint8).reshape(height, width)
    elif encoding == "zstd_u8":
        c = np.frombuffer(_zstd_decompress(payload, n, "confidence"), dtype=np.uint8).reshape(height, width)
    elif encoding == "png8":
        c = _imdecode(payload, "PNG", width, height, cv2.IMREAD_UNCHANGED, "confidence")
        if c.ndim != 2 or c.dtype != np.uint8:
            raise FrameDecodeError("confidence", f"png8 must be a single-channel 8-bit PNG, got {c.dtype} "
                                                 f"with shape {c.shape}")
    else:
        raise FrameEncodingError("confidence", f"unknown encoding {encoding!r}; expected one of "
                                             f"{', '.join(CONFIDENCE_ENCODINGS)}")
    if levels == "0-255":
        return _CONF_255_LUT[c]
    if c.size and int(c.max()) > 2:
        raise FrameDecodeError("confidence", f"levels '0-2' allow values 0, 1, 2; got a maximum of {int(c.max())}")
    return c.copy()
