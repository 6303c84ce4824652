"""The newest frame a session received, as the live viewer shows it: metadata, a colour-mapped depth
preview (PNG) and the colour image (JPEG).

Open sessions keep a reference to the last frame they accepted (:class:`LatestFrame`, no copy); stored
and resumed sessions read the last record of their recording (:func:`last_recorded_frame`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.proto.frame_codec import decode_frame
from voxfusion.proto.recording import iter_messages, scan_recording

__all__ = ["LatestFrame", "last_recorded_frame", "depth_preview_png", "colour_jpeg", "DEPTH_PREVIEW_MAX_M"]

DEPTH_PREVIEW_MAX_M = 6.0
"""Depth preview colour scale: 0 m -> the colour map's first colour, this many metres and beyond -> its
last; a fixed scale so successive frames are comparable."""


@dataclass(frozen=True)
class LatestFrame:
    """One received frame: its wire ``seq`` and the decoded frame (depth ``[H, W]`` float32 metres, ``K``
    for the depth resolution, colour ``[H, W, 3]`` uint8 RGB or ``None``)."""

    seq: int
    frame: RGBDFrame

    def info(self) -> dict:
        """JSON metadata: ``seq``, ``timestamp_s``, ``width`` / ``height`` (depth pixels), ``fx fy cx cy``
        (pixels, depth resolution), ``has_colour``, ``valid_depth_fraction`` and ``median_depth_m``
        (over valid pixels; ``None`` when there are none)."""
        f = self.frame
        valid = f.depth_m > 0
        n_valid = int(valid.sum())
        median = float(np.median(f.depth_m[valid])) if n_valid else None
        return {"seq": self.seq, "timestamp_s": float(f.timestamp_s), "width": f.width, "height": f.height,
                "fx": float(f.K[0, 0]), "fy": float(f.K[1, 1]), "cx": float(f.K[0, 2]), "cy": float(f.K[1, 2]),
                "has_colour": f.color is not None, "valid_depth_fraction": n_valid / max(1, valid.size),
                "median_depth_m": median}


def last_recorded_frame(recording: Path) -> LatestFrame | None:
    """The last acknowledged frame of a recording file, decoded; ``None`` when it holds none.

    Cached per file version (path, size, modification time): a finished session's viewer polls this, and
    a scan reads the whole file to check its records.
    """
    try:
        st = recording.stat()
    except FileNotFoundError:
        return None
    return _last_recorded(str(recording), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=2)  # decoded frames are large (up to 4096x4096): keep the newest few
def _last_recorded(path: str, _size: int, _mtime_ns: int) -> LatestFrame | None:
    recording = Path(path)
    scan = scan_recording(recording)
    if not scan.offsets:
        return None
    last = len(scan.offsets) - 1
    tail = type(scan)(scan.offsets[last:], scan.lengths[last:], scan.valid_end, scan.file_size)
    message = next(iter_messages(recording, tail))
    decoded = decode_frame(message)
    return LatestFrame(decoded.seq, decoded.frame)


def depth_preview_png(depth_m: np.ndarray, max_depth_m: float = DEPTH_PREVIEW_MAX_M) -> bytes:
    """A colour-mapped 8-bit RGB PNG of ``depth_m`` (``[H, W]`` metres): turbo from 0 to ``max_depth_m``,
    invalid pixels (0 or non-finite) black."""
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    scaled = np.clip(d / max_depth_m * 255.0, 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    bgr[d <= 0] = 0
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise RuntimeError("PNG encoding of the depth preview failed")
    return buf.tobytes()


def colour_jpeg(color: np.ndarray, quality: int = 85) -> bytes:
    """``color`` (``[H, W, 3]`` uint8 RGB) as a JPEG."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(color, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding of the colour frame failed")
    return buf.tobytes()
