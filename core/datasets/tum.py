"""TUM RGB-D benchmark sequences (original layout), read lazily.

Layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    <root>/rgb.txt            "timestamp rgb/<timestamp>.png" per line, '#' comments
    <root>/depth.txt          "timestamp depth/<timestamp>.png"
    <root>/rgb/*.png          640x480 8-bit colour
    <root>/depth/*.png        640x480 uint16, metres = value / 5000, 0 = invalid (registered to colour)
    <root>/groundtruth.txt    optional, "timestamp tx ty tz qx qy qz qw" camera-to-world (colour camera
                              optical frame, OpenCV axes), motion capture at ~100 Hz
    <root>/intrinsics.txt     optional (our extension, written by the synthetic generator): one line
                              "fx fy cx cy" that overrides the per-sequence intrinsics below
    <root>/confidence.txt     optional (our extension, synthetic LiDAR mode): "timestamp
                              confidence/<ts>.png" lines, uint8 0/1/2 maps paired with the depth image
                              of the same timestamp
    <root>/gt_mesh.ply        optional ground-truth mesh (synthetic captures); ``gt_mesh_path``

Colour and depth are associated here from ``rgb.txt`` / ``depth.txt`` (``associate.txt`` is ignored) by
the benchmark's own rule: pairs sorted by time difference are taken greedily, each image used once,
only pairs closer than ``max_time_diff_s``. A frame's ``timestamp_s`` is its colour timestamp (the
benchmark evaluates trajectories at colour times); the depth time is kept in ``meta["depth_time_s"]``.

Entries listed in the text files whose image is absent on disk (trimmed sequences) are skipped before
association unless ``strict=True``; ``skipped_missing`` counts them.

Profile (``capture.profile``): kind ``tum``, depth trusted to 4 m (Kinect v1), colour registered; kind
``synthetic`` (exact depth to 10 m) when ``rgb.txt``'s header says ``voxfusion synth`` wrote it;
``has_confidence`` when ``confidence.txt`` pairs confidence maps with the depth images.

Intrinsics: TUM publishes one calibration per sensor (lens distortion is ignored here, as in most
dense SLAM systems): fr1 ``(517.3, 516.5, 318.6, 255.3)``, fr2 ``(520.9, 521.0, 325.1, 249.7)``,
fr3 ``(535.4, 539.2, 320.1, 247.6)`` as ``(fx, fy, cx, cy)``. With ``intrinsics=None`` the reader uses
``<root>/intrinsics.txt`` if present, else the sensor named in the folder name (``freiburg2``, ``fr2``,
...) or in the ``# file: 'rgbd_dataset_freiburg2_...'`` header of ``rgb.txt``, else fr1.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import CaptureError, CaptureFormatError, ValidationError
from ..geometry import make_intrinsics
from ..trajectory import MAX_INTERPOLATION_GAP_S, interpolate_pose, read_tum_trajectory
from .checks import apply_confidence, check_depth_size, require_dir
from .frame import BaseCapture, RGBDFrame
from .images import (
    image_size,
    read_color,
    read_confidence,
    read_depth_png,
    read_intrinsics_txt,
    validate_intrinsics,
)
from .profile import KINECT_MAX_DEPTH_M, SYNTHETIC_MAX_DEPTH_M, CaptureProfile

__all__ = ["TUM_INTRINSICS", "TUMCapture", "read_tum_file_list", "associate_timestamps"]

TUM_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
}
"""Per-sensor pinhole intrinsics ``(fx, fy, cx, cy)`` for the 640x480 TUM images."""

MAX_GT_GAP_S = MAX_INTERPOLATION_GAP_S
"""Ground truth is interpolated only between samples at most this far apart (:mod:`~..trajectory`)."""

_SENSOR_RE = re.compile(r"(?:freiburg|fr)_?([123])(?![0-9])")


def read_tum_file_list(path: str | Path) -> list[tuple[float, str]]:
    """Parse ``rgb.txt`` / ``depth.txt``: ``[(timestamp_s, relative_path), ...]`` sorted by time."""
    path = Path(path)
    if not path.is_file():
        raise CaptureFormatError(path, "file list not found (TUM layout needs rgb.txt and depth.txt)")
    out: list[tuple[float, str]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise CaptureFormatError(path, f"line {lineno}: expected 'timestamp filename', got {line!r}")
        try:
            out.append((float(parts[0]), parts[1]))
        except ValueError as e:
            raise CaptureFormatError(path, f"line {lineno}: bad timestamp ({e})") from e
    out.sort(key=lambda e: e[0])
    return out


def associate_timestamps(t_a: np.ndarray, t_b: np.ndarray, max_diff_s: float) -> list[tuple[int, int]]:
    """Match two sorted timestamp lists one-to-one, as TUM's ``associate.py`` does.

    All pairs closer than ``max_diff_s`` are sorted by their time difference and taken greedily, each
    index used at most once. Returns ``[(i_a, i_b), ...]`` sorted by ``i_a``.
    """
    t_a = np.asarray(t_a, dtype=np.float64)
    t_b = np.asarray(t_b, dtype=np.float64)
    cands: list[tuple[float, int, int]] = []
    for i, t in enumerate(t_a):
        lo = int(np.searchsorted(t_b, t - max_diff_s, side="left"))
        hi = int(np.searchsorted(t_b, t + max_diff_s, side="right"))
        for j in range(lo, hi):
            d = abs(t - t_b[j])
            if d < max_diff_s:
                cands.append((d, i, j))
    cands.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    pairs.sort()
    return pairs


def _detect_sensor(root: Path) -> str | None:
    m = _SENSOR_RE.search(root.name.lower())
    if m:
        return f"fr{m.group(1)}"
    rgb_txt = root / "rgb.txt"
    if rgb_txt.is_file():
        with rgb_txt.open() as f:
            for _ in range(5):
                line = f.readline()
                if line.startswith("#") and "file:" in line:
                    m = _SENSOR_RE.search(line.lower())
                    if m:
                        return f"fr{m.group(1)}"
    return None


def _written_by_synth(root: Path) -> bool:
    """Whether ``rgb.txt``'s header says ``voxfusion synth`` wrote this sequence (exact synthetic depth)."""
    with (root / "rgb.txt").open() as f:
        for _ in range(3):
            line = f.readline()
            if line.startswith("#") and "voxfusion synthetic capture" in line:
                return True
    return False


def _nearest_pose(ts: np.ndarray, T: np.ndarray, t: float, max_diff_s: float) -> np.ndarray | None:
    j = int(np.searchsorted(ts, t))
    best = min((k for k in (j - 1, j) if 0 <= k < len(ts)), key=lambda k: abs(ts[k] - t))
    return T[best].copy() if abs(ts[best] - t) <= max_diff_s else None


class TUMCapture(BaseCapture):
    """A TUM RGB-D sequence folder (see the module docstring for the layout).

    Args:
        path: the sequence folder (holding ``rgb.txt`` and ``depth.txt``).
        intrinsics: ``"fr1"``, ``"fr2"``, ``"fr3"``, a ``[3, 3]`` K for 640x480, or ``None`` (auto).
        max_time_diff_s: largest colour/depth time difference accepted as one frame (TUM default 0.02).
        gt: ``"interpolate"`` (linear translation + slerp between the bracketing ground-truth samples),
            ``"nearest"`` (closest sample within ``max_time_diff_s``) or ``"none"``. Frames outside the
            ground-truth time span (or across a gap > ``MAX_GT_GAP_S``) get ``T_world_cam=None`` and are
            listed in ``frames_without_gt``.
        depth_scale: raw depth units per metre (5000 for TUM).
        strict: raise :class:`CaptureError` for a listed image missing on disk instead of skipping it.

    Example::

        cap = TUMCapture("rgbd_dataset_freiburg1_desk")
        frame = cap[0]   # frame.depth_m [480, 640] float32 m, frame.color [480, 640, 3] uint8 RGB
    """

    def __init__(self, path: str | Path, intrinsics: str | np.ndarray | None = None, *,
                 max_time_diff_s: float = 0.02,
                 gt: Literal["interpolate", "nearest", "none"] = "interpolate",
                 depth_scale: float = 5000.0, strict: bool = False) -> None:
        root = require_dir(path, "TUM sequence folder")
        if gt not in ("interpolate", "nearest", "none"):
            raise ValidationError("gt", f"must be 'interpolate', 'nearest' or 'none', got {gt!r}")
        if not max_time_diff_s > 0:
            raise ValidationError("max_time_diff_s", f"must be > 0, got {max_time_diff_s}")
        self.path = root
        self.name = root.name
        self.depth_scale = float(depth_scale)

        rgb = read_tum_file_list(root / "rgb.txt")
        depth = read_tum_file_list(root / "depth.txt")
        self.skipped_missing = 0
        rgb, depth = self._existing(rgb, strict), self._existing(depth, strict)
        pairs = associate_timestamps([t for t, _ in rgb], [t for t, _ in depth], max_time_diff_s)
        if not pairs:
            raise CaptureFormatError(
                root, f"no colour/depth pairs closer than {max_time_diff_s} s "
                f"({len(rgb)} colour and {len(depth)} depth images on disk)"
            )
        self._rgb = [(rgb[i][0], root / rgb[i][1]) for i, _ in pairs]
        self._depth = [(depth[j][0], root / depth[j][1]) for _, j in pairs]

        self._confidence: list[Path | None] = [None] * len(self._depth)
        if (root / "confidence.txt").is_file():
            conf = {round(t, 6): root / rel for t, rel in read_tum_file_list(root / "confidence.txt")}
            self._confidence = [conf.get(round(t, 6)) for t, _ in self._depth]
        if (root / "gt_mesh.ply").is_file():
            self._gt_mesh_path = root / "gt_mesh.ply"

        self.width, self.height = image_size(self._depth[0][1])
        cw, ch = image_size(self._rgb[0][1])
        if (cw, ch) != (self.width, self.height):
            raise CaptureFormatError(
                self._rgb[0][1], f"colour is {cw}x{ch} but depth is {self.width}x{self.height}; "
                "TUM colour and depth must have the same size"
            )
        self.K, self.intrinsics_source = self._resolve_intrinsics(intrinsics)

        self._poses: list[np.ndarray | None] = [None] * len(self._rgb)
        gt_path = root / "groundtruth.txt"
        if gt != "none" and gt_path.is_file():
            traj = read_tum_trajectory(gt_path)
            order = np.argsort(traj.timestamps_s, kind="stable")
            ts, T = traj.timestamps_s[order], traj.T_world_cam[order]
            for k, (t, _) in enumerate(self._rgb):
                if gt == "interpolate":
                    self._poses[k] = interpolate_pose(ts, T, t, MAX_GT_GAP_S)
                else:
                    self._poses[k] = _nearest_pose(ts, T, t, max_time_diff_s)
            self.frames_without_gt = tuple(k for k, p in enumerate(self._poses) if p is None)
        else:
            self.frames_without_gt = tuple(range(len(self._rgb)))
        self.has_gt = gt != "none" and gt_path.is_file()
        has_conf = any(c is not None for c in self._confidence)
        if _written_by_synth(root):
            self._profile = CaptureProfile("synthetic", SYNTHETIC_MAX_DEPTH_M, has_confidence=has_conf,
                                           sensor=f"voxfusion synthetic room {self.width}x{self.height}")
        else:
            self._profile = CaptureProfile("tum", KINECT_MAX_DEPTH_M, has_confidence=has_conf,
                                           sensor=f"TUM RGB-D, Kinect v1 {self.width}x{self.height}")

    def _existing(self, entries: list[tuple[float, str]], strict: bool) -> list[tuple[float, str]]:
        kept = []
        for t, rel in entries:
            if (self.path / rel).is_file():
                kept.append((t, rel))
            elif strict:
                raise CaptureError(self.path / rel, "image listed in rgb.txt/depth.txt not found")
            else:
                self.skipped_missing += 1
        return kept

    def _resolve_intrinsics(self, intrinsics: str | np.ndarray | None) -> tuple[np.ndarray, str]:
        source: str | Path
        if intrinsics is None:
            file = self.path / "intrinsics.txt"
            if file.is_file():
                K, source = read_intrinsics_txt(file), file
            else:
                sensor = _detect_sensor(self.path) or "fr1"
                K, source = make_intrinsics(*TUM_INTRINSICS[sensor]), sensor
        elif isinstance(intrinsics, str):
            if intrinsics not in TUM_INTRINSICS:
                raise ValidationError("intrinsics", f"unknown TUM sensor {intrinsics!r}; use fr1, fr2 or fr3")
            K, source = make_intrinsics(*TUM_INTRINSICS[intrinsics]), intrinsics
        else:
            K, source = np.asarray(intrinsics, dtype=np.float64), "argument"
        where = source if isinstance(source, Path) else self.path
        K = validate_intrinsics(K, self.width, self.height, where)
        return K, str(source)

    def __len__(self) -> int:
        return len(self._rgb)

    def _load(self, i: int) -> RGBDFrame:
        t_rgb, rgb_path = self._rgb[i]
        t_depth, depth_path = self._depth[i]
        depth_m = check_depth_size(
            read_depth_png(depth_path, self.depth_scale), self.width, self.height, depth_path, "sequence"
        )
        color = read_color(rgb_path)
        if color.shape[:2] != depth_m.shape:
            raise CaptureFormatError(
                rgb_path, f"colour is {color.shape[1]}x{color.shape[0]} but depth is "
                f"{self.width}x{self.height}"
            )
        confidence = None
        if (conf_path := self._confidence[i]) is not None:
            confidence = apply_confidence(depth_m, read_confidence(conf_path), None, conf_path)
        return RGBDFrame(
            depth_m=depth_m, K=self.K, timestamp_s=t_rgb, color=color, confidence=confidence,
            T_world_cam=self._poses[i],
            index=i, meta={"depth_time_s": t_depth, "rgb_path": str(rgb_path), "depth_path": str(depth_path)},
        )
