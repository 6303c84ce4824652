"""Checks the capture readers share: on their arguments, on a frame's depth and confidence, on metadata JSON.

A bad argument raises :class:`ValidationError`; a file that cannot be read raises :class:`CaptureError`, one
that holds the wrong thing :class:`CaptureFormatError`, both naming the file. Conventions as in
:mod:`.images`: depth is ``[H, W]`` float32 metres with 0 = invalid, confidence ``[H, W]`` uint8 in
{0, 1, 2} (low/medium/high).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import CaptureError, CaptureFormatError, ValidationError

__all__ = [
    "require_dir",
    "check_confidence_threshold", "check_depth_size", "apply_confidence",
    "read_json_object",
]


def require_dir(path: str | Path, what: str) -> Path:
    """Return ``path`` as a :class:`Path`, or raise :class:`CaptureError` "``what`` not found" if it is not an
    existing folder (``what``: e.g. ``"ScanNet export folder"``)."""
    path = Path(path)
    if not path.is_dir():
        raise CaptureError(path, f"{what} not found")
    return path


def check_confidence_threshold(threshold: int | None) -> int | None:
    """Return a reader's ``confidence_threshold`` argument if valid, else raise :class:`ValidationError`.

    Valid: 0, 1 or 2 (depth whose confidence is below it is zeroed, see :func:`apply_confidence`), or
    ``None`` (all depth is kept).
    """
    if threshold is not None and threshold not in (0, 1, 2):
        raise ValidationError("confidence_threshold", f"must be 0, 1, 2 or None, got {threshold}")
    return threshold


def check_depth_size(depth_m: np.ndarray, width: int, height: int, source: str | Path,
                     whole: str = "capture") -> np.ndarray:
    """Return ``depth_m`` if it is ``[height, width]``, the depth resolution of the rest of its capture.

    Otherwise raises :class:`CaptureFormatError` naming ``source`` (the depth file): "depth is WxH, the
    ``whole`` is WxH", ``whole`` being what the frame belongs to (``"capture"``, ``"scene"``, ``"sequence"``).
    """
    if depth_m.shape != (height, width):
        raise CaptureFormatError(
            source, f"depth is {depth_m.shape[1]}x{depth_m.shape[0]}, the {whole} is {width}x{height}"
        )
    return depth_m


def apply_confidence(depth_m: np.ndarray, confidence: np.ndarray, threshold: int | None,
                     source: str | Path) -> np.ndarray:
    """Zero, in place, the depth whose confidence is below ``threshold``; ``None`` keeps all depth.

    Args:
        depth_m: ``[H, W]`` float32 depth in metres, modified in place.
        confidence: ``[H, W]`` uint8 in {0, 1, 2}; a different resolution from ``depth_m`` raises
            :class:`CaptureFormatError` naming ``source`` (the confidence file).
        threshold: 0, 1 or 2 (see :func:`check_confidence_threshold`), or ``None``.
        source: where ``confidence`` was read from, for the error message.

    Returns:
        ``confidence`` itself, unchanged (the frame still carries the raw map).
    """
    if confidence.shape != depth_m.shape:
        raise CaptureFormatError(
            source, f"confidence is {confidence.shape[1]}x{confidence.shape[0]}, depth is "
            f"{depth_m.shape[1]}x{depth_m.shape[0]}"
        )
    if threshold is not None:
        depth_m[confidence < threshold] = 0.0
    return confidence


def read_json_object(path: str | Path, what: str = "JSON file") -> dict:
    """Read a JSON file that must hold an object (``{...}``) and return it as a ``dict``.

    ``what`` names the file in the messages (e.g. ``"frame file"``): :class:`CaptureError` "unreadable
    <what>" for a missing or undecodable file, :class:`CaptureFormatError` "not valid JSON" or "<what> must
    hold a JSON object".
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise CaptureError(path, f"unreadable {what} ({e})") from e
    except json.JSONDecodeError as e:
        raise CaptureFormatError(path, f"not valid JSON ({e})") from e
    if not isinstance(data, dict):
        raise CaptureFormatError(path, f"{what} must hold a JSON object")
    return data
