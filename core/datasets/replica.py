"""Replica scenes as released by NICE-SLAM (rendered RGB-D), read lazily.

Layout::

    <root>/results/frame%06d.jpg     colour (1200x680 in the release)
    <root>/results/depth%06d.png     uint16, metres = value / 6553.5, 0 = invalid
    <root>/traj.txt                  one line per frame: 16 numbers, the 4x4 camera-to-world matrix
                                     row-major (OpenCV camera axes, metres)

Intrinsics, first match wins:

1. the ``K`` argument (a ``[3, 3]`` matrix or ``(fx, fy, cx, cy)``);
2. ``<root>/cam_params.json`` or ``<root>/../cam_params.json`` (the file shipped with the Replica
   release: ``{"camera": {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5,
   "scale": 6553.5}}``; ``w``/``h`` must match the depth images, ``scale`` sets the depth scale);
3. ``<root>/intrinsics.txt``: one line ``fx fy cx cy`` or a 3x3 matrix;
4. the NICE-SLAM Replica config: fx = fy = 600, cx = 599.5, cy = 339.5 (for 1200x680).

The ground-truth mesh is ``<root>/../<name>_mesh.ply`` (release layout), ``<root>/gt_mesh.ply`` (our
synthetic captures) or ``<root>/mesh.ply``.
Replica has no timestamps; ``timestamp_s = index / frame_rate_hz``.
Profile: kind ``replica`` (exact rendered depth to 10 m, colour registered); kind ``synthetic`` when
``<root>/gt_mesh.ply`` marks a scene that ``voxfusion synth --layout replica`` wrote.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from ..errors import CaptureFormatError, ValidationError
from ..geometry import check_rigid, make_intrinsics
from .checks import check_depth_size, require_dir
from .frame import BaseCapture, RGBDFrame
from .images import (
    image_size,
    read_color,
    read_depth_png,
    read_intrinsics_txt,
    read_text_matrix,
    validate_intrinsics,
)
from .profile import SYNTHETIC_MAX_DEPTH_M, CaptureProfile

__all__ = ["REPLICA_INTRINSICS", "REPLICA_DEPTH_SCALE", "ReplicaCapture"]

REPLICA_INTRINSICS = (600.0, 600.0, 599.5, 339.5)
"""NICE-SLAM's Replica ``(fx, fy, cx, cy)`` for 1200x680 images."""
REPLICA_DEPTH_SCALE = 6553.5
"""Raw depth units per metre in the Replica release."""

_DEPTH_RE = re.compile(r"^depth(\d+)\.png$")


def _read_cam_params(path: Path) -> tuple[np.ndarray, float | None, tuple[int, int] | None]:
    try:
        cam = json.loads(path.read_text())["camera"]
        K = make_intrinsics(float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]))
        scale = float(cam["scale"]) if "scale" in cam else None
        size = (int(cam["w"]), int(cam["h"])) if "w" in cam and "h" in cam else None
    except (ValueError, KeyError, TypeError) as e:
        raise CaptureFormatError(
            path, f"expected {{'camera': {{'fx', 'fy', 'cx', 'cy', ['w', 'h', 'scale']}}}} ({e!r})"
        ) from e
    return K, scale, size


class ReplicaCapture(BaseCapture):
    """A NICE-SLAM Replica scene folder (see the module docstring).

    Args:
        path: the scene folder (holding ``results/`` and ``traj.txt``).
        K: optional intrinsics, ``[3, 3]`` or ``(fx, fy, cx, cy)``, for the depth resolution.
        depth_scale: raw depth units per metre; ``None`` = ``cam_params.json``'s ``scale`` or 6553.5.
        frame_rate_hz: used to make timestamps (``index / frame_rate_hz``).

    Example::

        cap = ReplicaCapture("Replica/room0")
        f = cap[0]   # depth [680, 1200] float32 m, colour [680, 1200, 3] RGB, T_world_cam [4, 4]
    """

    def __init__(self, path: str | Path, K: np.ndarray | tuple[float, float, float, float] | None = None,
                 depth_scale: float | None = None, *, frame_rate_hz: float = 30.0) -> None:
        root = require_dir(path, "Replica scene folder")
        if not frame_rate_hz > 0:
            raise ValidationError("frame_rate_hz", f"must be > 0, got {frame_rate_hz}")
        self.path = root
        self.name = root.name
        self.frame_rate_hz = float(frame_rate_hz)
        results = root / "results"
        if not results.is_dir():
            raise CaptureFormatError(results, "results/ folder not found (not a NICE-SLAM Replica scene)")
        self._ids = sorted(int(m.group(1)) for p in results.iterdir() if (m := _DEPTH_RE.match(p.name)))
        if not self._ids:
            raise CaptureFormatError(results, "no depthXXXXXX.png files")
        self.width, self.height = image_size(self._depth_path(0))

        traj_path = root / "traj.txt"
        traj = read_text_matrix(traj_path, "trajectory")
        if traj.shape[1] != 16:
            raise CaptureFormatError(
                traj_path, f"each line must hold 16 numbers (a 4x4 pose), got {traj.shape[1]}"
            )
        if traj.shape[0] <= self._ids[-1]:
            raise CaptureFormatError(
                traj_path, f"{traj.shape[0]} poses but frames go up to depth{self._ids[-1]:06d}.png"
            )
        self._traj = traj.reshape(-1, 4, 4)
        self._traj_path = traj_path

        self.K, self.depth_scale, self.intrinsics_source = self._resolve_intrinsics(K, depth_scale)
        for mesh in (root.parent / f"{root.name}_mesh.ply", root / "gt_mesh.ply", root / "mesh.ply"):
            if mesh.is_file():
                self._gt_mesh_path = mesh
                break
        size = f"{self.width}x{self.height}"
        if (root / "gt_mesh.ply").is_file():  # what `voxfusion synth --layout replica` writes
            kind, sensor = "synthetic", f"voxfusion synthetic room {size}"
        else:
            kind, sensor = "replica", f"Replica (rendered) {size}"
        self._profile = CaptureProfile(kind, SYNTHETIC_MAX_DEPTH_M, sensor=sensor)

    def _resolve_intrinsics(self, K: np.ndarray | tuple | None,
                            depth_scale: float | None) -> tuple[np.ndarray, float, str]:
        scale: float | None = None
        source: Path = self.path
        if K is not None:
            K = np.asarray(K, dtype=np.float64)
            if K.shape == (4,):
                K = make_intrinsics(*K)
        else:
            for cand in (self.path / "cam_params.json", self.path.parent / "cam_params.json"):
                if cand.is_file():
                    K, scale, size = _read_cam_params(cand)
                    if size is not None and size != (self.width, self.height):
                        raise CaptureFormatError(
                            cand, f"camera is {size[0]}x{size[1]} but the depth images are "
                            f"{self.width}x{self.height}"
                        )
                    source = cand
                    break
            else:
                if (self.path / "intrinsics.txt").is_file():
                    source = self.path / "intrinsics.txt"
                    K = read_intrinsics_txt(source)
                else:
                    K = make_intrinsics(*REPLICA_INTRINSICS)
        K = validate_intrinsics(K, self.width, self.height, source)
        scale = float(depth_scale) if depth_scale is not None else (scale or REPLICA_DEPTH_SCALE)
        if not scale > 0:
            raise ValidationError("depth_scale", f"must be > 0, got {scale}")
        return K, scale, str(source) if source != self.path else "default"

    def _depth_path(self, i: int) -> Path:
        return self.path / "results" / f"depth{self._ids[i]:06d}.png"

    def __len__(self) -> int:
        return len(self._ids)

    def _load(self, i: int) -> RGBDFrame:
        fid = self._ids[i]
        depth_path = self._depth_path(i)
        depth_m = check_depth_size(
            read_depth_png(depth_path, self.depth_scale), self.width, self.height, depth_path, "scene"
        )
        color_path = self.path / "results" / f"frame{fid:06d}.jpg"
        if not color_path.is_file() and (alt := color_path.with_suffix(".png")).is_file():
            color_path = alt
        color = read_color(color_path)
        if color.shape[:2] != depth_m.shape:
            raise CaptureFormatError(
                color_path,
                f"colour is {color.shape[1]}x{color.shape[0]} but depth is {self.width}x{self.height}",
            )
        T = self._traj[fid]
        if np.all(np.isfinite(T)):
            try:
                T = check_rigid(T, "pose")
            except ValidationError as e:
                raise CaptureFormatError(self._traj_path, f"pose of frame {fid}: {e.problem}") from e
        else:
            T = None
        return RGBDFrame(
            depth_m=depth_m, K=self.K, timestamp_s=fid / self.frame_rate_hz, color=color, T_world_cam=T,
            index=i, meta={"frame_id": fid, "depth_path": str(depth_path)},
        )
