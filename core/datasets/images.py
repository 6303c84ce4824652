"""Image and depth loading shared by the capture readers.

Every function here names the file in the error it raises (:class:`CaptureError` for a missing or
unreadable file, :class:`CaptureFormatError` for a file that decodes but has the wrong kind of content),
so a reader never has to check ``cv2.imread``'s ``None`` itself.

Conventions: colour is returned as ``[H, W, 3]`` uint8 **RGB** (OpenCV decodes BGR; converted here),
depth as ``[H, W]`` float32 metres with 0 = invalid, confidence as ``[H, W]`` uint8 in {0, 1, 2}.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from ..errors import CaptureError, CaptureFormatError, ValidationError
from ..geometry import check_intrinsics, make_intrinsics

__all__ = [
    "require_file",
    "image_size",
    "read_color",
    "decode_color",
    "read_depth_png",
    "depth_from_uint16",
    "read_depth_npy",
    "read_confidence",
    "check_confidence",
    "resize_color",
    "read_text_matrix",
    "read_intrinsics_txt",
    "validate_intrinsics",
]


def require_file(path: str | Path, what: str = "file") -> Path:
    """Return ``path`` as a :class:`Path`, or raise :class:`CaptureError` if it is not an existing file."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(path, f"{what} not found")
    return path


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, read from its header only (no pixel decoding)."""
    path = require_file(path, "image")
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise CaptureError(path, f"unreadable or corrupt image ({e})") from e


def _imread(path: Path, flags: int) -> np.ndarray:
    require_file(path, "image")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise CaptureError(path, "unreadable or corrupt image (OpenCV could not decode it)")
    return img


def _to_rgb(img: np.ndarray, source: str | Path) -> np.ndarray:
    """Convert an OpenCV-decoded image (gray, BGR or BGRA; 8-bit) to ``[H, W, 3]`` uint8 RGB."""
    if img.dtype != np.uint8:
        raise CaptureFormatError(source, f"colour image must be 8-bit, got {img.dtype}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    raise CaptureFormatError(source, f"colour image has {img.shape[2]} channels, expected 3")


def read_color(path: str | Path) -> np.ndarray:
    """Read a colour image (PNG/JPEG/...) as ``[H, W, 3]`` uint8 RGB."""
    path = Path(path)
    return _to_rgb(_imread(path, cv2.IMREAD_UNCHANGED), path)


def decode_color(data: bytes, source: str | Path) -> np.ndarray:
    """Decode an encoded colour image held in memory (e.g. a JPEG inside a zip) to ``[H, W, 3]`` RGB.

    ``source`` names where the bytes came from, for the error message.
    """
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CaptureError(source, "unreadable or corrupt image (OpenCV could not decode it)")
    return _to_rgb(img, source)


def depth_from_uint16(raw: np.ndarray, scale: float, source: str | Path,
                      invalid_values: tuple[int, ...] = ()) -> np.ndarray:
    """Convert a ``[H, W]`` uint16 depth image to float32 metres (``raw / scale``), 0 = invalid.

    Args:
        raw: ``[H, W]`` uint16 raw depth.
        scale: raw units per metre (1000 for millimetres, 5000 for TUM, 6553.5 for Replica).
        source: file the image came from, for error messages.
        invalid_values: raw values that also mean "no measurement" (e.g. 65535 in 7-Scenes).
    """
    if raw.ndim != 2:
        raise CaptureFormatError(source, f"depth image must be single-channel, got shape {raw.shape}")
    if raw.dtype != np.uint16:
        raise CaptureFormatError(source, f"depth image must be 16-bit (uint16), got {raw.dtype}")
    depth_m = raw.astype(np.float32) / np.float32(scale)
    for v in invalid_values:
        depth_m[raw == v] = 0.0
    return depth_m


def read_depth_png(path: str | Path, scale: float, invalid_values: tuple[int, ...] = ()) -> np.ndarray:
    """Read a 16-bit depth PNG as ``[H, W]`` float32 metres (``value / scale``), 0 = invalid.

    Raises :class:`CaptureFormatError` if the PNG is not single-channel uint16 (an 8-bit PNG has lost
    the depth precision and is refused rather than guessed at).
    """
    path = Path(path)
    return depth_from_uint16(_imread(path, cv2.IMREAD_UNCHANGED), scale, path, invalid_values)


def read_depth_npy(path: str | Path, scale: float = 1000.0) -> np.ndarray:
    """Read a ``.npy`` depth map: uint16 is raw units (``value / scale``), floats are already metres.

    Non-finite and negative values become 0 (invalid).
    """
    path = require_file(path, "depth file")
    try:
        raw = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise CaptureError(path, f"unreadable or corrupt .npy depth ({e})") from e
    if raw.dtype == np.uint16:
        return depth_from_uint16(raw, scale, path)
    if raw.ndim != 2 or raw.dtype.kind != "f":
        raise CaptureFormatError(
            path, f"depth array must be [H, W] uint16 or float, got {raw.dtype} {raw.shape}"
        )
    depth_m = raw.astype(np.float32)
    depth_m[~np.isfinite(depth_m) | (depth_m < 0)] = 0.0
    return depth_m


def check_confidence(conf: np.ndarray, source: str | Path) -> np.ndarray:
    """Validate a ``[H, W]`` confidence map with values in {0, 1, 2}; returns it as uint8."""
    if conf.ndim != 2:
        raise CaptureFormatError(source, f"confidence must be single-channel, got shape {conf.shape}")
    if conf.dtype != np.uint8:
        raise CaptureFormatError(source, f"confidence must be uint8, got {conf.dtype}")
    if conf.size and int(conf.max()) > 2:
        raise CaptureFormatError(
            source, f"confidence values must be 0/1/2 (low/medium/high), found {int(conf.max())}"
        )
    return conf


def read_confidence(path: str | Path) -> np.ndarray:
    """Read an 8-bit confidence PNG (values 0/1/2) as ``[H, W]`` uint8."""
    path = Path(path)
    return check_confidence(_imread(path, cv2.IMREAD_UNCHANGED), path)


def resize_color(color: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize ``[H, W, 3]`` uint8 colour to ``width`` x ``height`` (area averaging); no-op if equal."""
    if color.shape[1] == width and color.shape[0] == height:
        return color
    return cv2.resize(color, (width, height), interpolation=cv2.INTER_AREA)


def read_text_matrix(path: str | Path, what: str = "matrix") -> np.ndarray:
    """Read a whitespace- or comma-separated numeric text file as a float64 2D array."""
    path = require_file(path, what)
    rows: list[list[float]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append([float(v) for v in line.replace(",", " ").split()])
        except ValueError as e:
            raise CaptureFormatError(path, f"line {lineno}: not a number ({e})") from e
    if not rows:
        raise CaptureFormatError(path, f"empty {what}")
    if len({len(r) for r in rows}) != 1:
        raise CaptureFormatError(path, f"{what} rows have different lengths")
    return np.asarray(rows, dtype=np.float64)


def read_intrinsics_txt(path: str | Path) -> np.ndarray:
    """Read intrinsics from a text file: either one line ``fx fy cx cy`` or a 3x3 matrix (3 rows).

    A 4x4 matrix (ScanNet's ``intrinsic_depth.txt``) is accepted too; its top-left 3x3 is used.
    Returns a float64 ``[3, 3]`` K (not yet checked against an image size; see
    :func:`validate_intrinsics`).
    """
    path = Path(path)
    m = read_text_matrix(path, "intrinsics")
    if m.size == 4:
        fx, fy, cx, cy = m.reshape(-1)
        return make_intrinsics(fx, fy, cx, cy)
    if m.shape in ((3, 3), (4, 4)):
        K = m[:3, :3].copy()
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise CaptureFormatError(path, f"not a pinhole intrinsics matrix (last row {K[2].tolist()})")
        return K
    raise CaptureFormatError(
        path, f"intrinsics must be 'fx fy cx cy' or a 3x3/4x4 matrix, got {m.shape[0]}x{m.shape[1]} values"
    )


def validate_intrinsics(K: np.ndarray, width: int, height: int, source: str | Path) -> np.ndarray:
    """Check ``K`` against the ``width`` x ``height`` image it must describe.

    Raises :class:`CaptureFormatError` naming ``source`` (the intrinsics file, or the capture) when the
    focal lengths are not positive or the principal point lies outside the image, the usual sign of
    intrinsics written for another resolution.
    """
    try:
        return check_intrinsics(K, width, height, "intrinsics")
    except ValidationError as e:
        raise CaptureFormatError(source, e.problem) from e
