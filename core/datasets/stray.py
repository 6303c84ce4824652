"""Stray Scanner (iPhone / iPad LiDAR) captures, read lazily.

Layout (https://docs.strayrobots.io/apps/scanner/format.html)::

    <root>/odometry.csv        header "timestamp, frame, x, y, z, qx, qy, qz, qw"; ARKit visual-inertial
                               pose, camera-to-world, already in OpenCV camera axes, metres
    <root>/depth/%06d.png      uint16 millimetres (e.g. 256x192); ``.npy`` also read (uint16 mm or
                               float metres)
    <root>/confidence/%06d.png optional, uint8 0/1/2 = low/medium/high
    <root>/camera_matrix.csv   3x3 row-major K for the *colour* resolution
    <root>/rgb.mp4             optional colour video (1920x1440); absent = depth-only capture

Intrinsics are scaled from the colour resolution (taken from ``rgb.mp4`` when present, else
1920x1440) to the depth resolution with :func:`geometry.scale_intrinsics`. Colour frames are decoded
sequentially from the video (one open decoder, cached position; backward jumps seek) and resized to
the depth resolution with area averaging.

The ARKit pose is the only pose a Stray capture has: it goes into both ``T_world_cam`` (reference
pose) and ``T_world_cam_device`` (the device prior tracking may start from). It is VIO, not ground
truth: expect a few centimetres of drift.

Depth with confidence below ``confidence_threshold`` is set to 0 (the raw confidence map is still
returned); ``None`` keeps all depth.
"""

from __future__ import annotations

import csv
import os
import threading
from pathlib import Path

import cv2
import numpy as np

from ..errors import CaptureError, CaptureFormatError
from ..geometry import pose_from_tum, scale_intrinsics
from .checks import apply_confidence, check_confidence_threshold, check_depth_size, require_dir
from .frame import BaseCapture, RGBDFrame
from .images import (
    image_size,
    read_confidence,
    read_depth_npy,
    read_depth_png,
    read_text_matrix,
    resize_color,
    validate_intrinsics,
)
from .profile import LIDAR_MAX_DEPTH_M, CaptureProfile

__all__ = ["StrayCapture", "VideoFrameReader", "STRAY_COLOR_SIZE"]

STRAY_COLOR_SIZE = (1920, 1440)
"""Colour resolution ``(width, height)`` ``camera_matrix.csv`` refers to when there is no ``rgb.mp4``."""

_ODOMETRY_COLUMNS = ("timestamp", "frame", "x", "y", "z", "qx", "qy", "qz", "qw")


class VideoFrameReader:
    """Random access to the frames of a video file, cheap when frames are read in order.

    One OpenCV decoder stays open; reading frame ``k`` right after ``k - 1`` is a single decode, a
    short forward jump skips with ``grab()``, a backward or long jump seeks. Thread-safe (one lock);
    picklable, and a forked or unpickled copy opens its own decoder on first use.
    """

    _MAX_GRAB_AHEAD = 30

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._cap: cv2.VideoCapture | None = None
        self._pid = -1
        self._next = 0
        cap = self._decoder()
        self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.frame_count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))

    def _open(self) -> cv2.VideoCapture:
        if not self.path.is_file():
            raise CaptureError(self.path, "video not found")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise CaptureError(self.path, "unreadable or corrupt video (OpenCV could not open it)")
        return cap

    def _decoder(self) -> cv2.VideoCapture:
        if self._cap is None or self._pid != os.getpid():
            self._cap = self._open()
            self._pid = os.getpid()
            self._next = 0
        return self._cap

    def read(self, k: int) -> np.ndarray:
        """Frame ``k`` (0-based) as ``[H, W, 3]`` uint8 RGB."""
        with self._lock:
            cap = self._decoder()
            if k < self._next or k - self._next > self._MAX_GRAB_AHEAD:
                cap.set(cv2.CAP_PROP_POS_FRAMES, k)
                self._next = int(cap.get(cv2.CAP_PROP_POS_FRAMES))
                if self._next != k:  # the backend could not seek exactly: decode forward from the start
                    cap.release()
                    self._cap = None
                    cap = self._decoder()
            while self._next < k:
                if not cap.grab():
                    raise CaptureError(self.path, f"video ends before frame {k} (at frame {self._next})")
                self._next += 1
            ok, bgr = cap.read()
            if not ok or bgr is None:
                raise CaptureError(self.path, f"could not decode video frame {k} (too short or corrupt)")
            self._next = k + 1
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        """Release the decoder (it reopens on the next read)."""
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cap"], state["_lock"], state["_pid"] = None, None, -1
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()


def _read_odometry(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(timestamps_s [N], frame_ids [N] int, T_world_cam [N, 4, 4])`` from ``odometry.csv``."""
    if not path.is_file():
        raise CaptureFormatError(path, "odometry.csv not found (not a Stray Scanner capture)")
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise CaptureFormatError(path, "empty odometry file")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in _ODOMETRY_COLUMNS if c not in header]
    if missing:
        expected = ", ".join(_ODOMETRY_COLUMNS)
        raise CaptureFormatError(path, f"header lacks columns {missing}; expected {expected}")
    cols = [header.index(c) for c in _ODOMETRY_COLUMNS]
    values = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        try:
            values.append([float(row[c]) for c in cols])
        except (ValueError, IndexError) as e:
            raise CaptureFormatError(path, f"line {lineno}: bad odometry row ({e})") from e
    if not values:
        raise CaptureFormatError(path, "no poses in odometry file")
    a = np.asarray(values, dtype=np.float64)
    q = a[:, 5:9]
    norms = np.linalg.norm(q, axis=1)
    if not np.all(np.isfinite(a)) or np.any(norms < 1e-6):
        raise CaptureFormatError(path, "non-finite value or zero-length quaternion in odometry")
    order = np.argsort(a[:, 1], kind="stable")
    a, q, norms = a[order], q[order], norms[order]
    return a[:, 0], a[:, 1].astype(np.int64), pose_from_tum(a[:, 2:5], q / norms[:, None])


class StrayCapture(BaseCapture):
    """A Stray Scanner capture folder (see the module docstring).

    Args:
        path: the capture folder (holding ``odometry.csv`` and ``depth/``).
        confidence_threshold: zero depth whose confidence is below this (0, 1 or 2); ``None`` keeps all.

    Example::

        cap = StrayCapture("my_scan")
        f = cap[0]   # depth [192, 256] float32 m, K scaled to 256x192, colour None if no rgb.mp4
    """

    def __init__(self, path: str | Path, confidence_threshold: int | None = 1) -> None:
        root = require_dir(path, "Stray Scanner capture folder")
        self.confidence_threshold = check_confidence_threshold(confidence_threshold)
        self.path = root
        self.name = root.name
        self._timestamps_s, self._ids, self._poses = _read_odometry(root / "odometry.csv")
        if not (root / "depth").is_dir():
            raise CaptureFormatError(root / "depth", "depth folder not found")
        self.width, self.height = self._depth_size()

        video_path = root / "rgb.mp4"
        self._video = VideoFrameReader(video_path) if video_path.is_file() else None
        color_wh = (self._video.width, self._video.height) if self._video else STRAY_COLOR_SIZE
        self.color_size = color_wh
        K_path = root / "camera_matrix.csv"
        K_color = read_text_matrix(K_path, "camera matrix")
        if K_color.shape != (3, 3):
            raise CaptureFormatError(K_path, f"camera matrix must be 3x3, got {K_color.shape}")
        validate_intrinsics(K_color, color_wh[0], color_wh[1], K_path)
        self.K = validate_intrinsics(
            scale_intrinsics(K_color, color_wh, (self.width, self.height)), self.width, self.height, K_path
        )
        self._profile = CaptureProfile(
            "iphone", LIDAR_MAX_DEPTH_M, has_confidence=(root / "confidence").is_dir(),
            has_color=self._video is not None, sensor=f"Stray Scanner, iPhone LiDAR {self.width}x{self.height}")

    def _depth_path(self, i: int) -> Path:
        stem = self.path / "depth" / f"{self._ids[i]:06d}"
        png = stem.with_suffix(".png")
        if png.is_file():
            return png
        npy = stem.with_suffix(".npy")
        if npy.is_file():
            return npy
        raise CaptureError(png, "depth image not found (looked for .png and .npy)")

    def _depth_size(self) -> tuple[int, int]:
        p = self._depth_path(0)
        if p.suffix == ".png":
            return image_size(p)
        d = read_depth_npy(p)
        return int(d.shape[1]), int(d.shape[0])

    def __len__(self) -> int:
        return len(self._ids)

    def _load(self, i: int) -> RGBDFrame:
        depth_path = self._depth_path(i)
        if depth_path.suffix == ".png":
            depth_m = read_depth_png(depth_path, 1000.0)
        else:
            depth_m = read_depth_npy(depth_path)
        check_depth_size(depth_m, self.width, self.height, depth_path)
        conf_path = self.path / "confidence" / f"{self._ids[i]:06d}.png"
        confidence = None
        if conf_path.is_file():
            confidence = apply_confidence(depth_m, read_confidence(conf_path), self.confidence_threshold, conf_path)
        color = None
        if self._video is not None:
            color = resize_color(self._video.read(int(self._ids[i])), self.width, self.height)
        T = self._poses[i]
        return RGBDFrame(
            depth_m=depth_m, K=self.K, timestamp_s=float(self._timestamps_s[i]), color=color,
            confidence=confidence, T_world_cam=T.copy(), T_world_cam_device=T.copy(), index=i,
            meta={"frame_id": int(self._ids[i]), "depth_path": str(depth_path)},
        )
