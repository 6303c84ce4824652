"""Microsoft 7-Scenes sequences (one ``seq-XX`` folder), read lazily.

Layout::

    <root>/frame-%06d.color.png      640x480 colour (.color.jpg accepted too)
    <root>/frame-%06d.depth.png      640x480 uint16 millimetres; 0 and 65535 = invalid
    <root>/frame-%06d.pose.txt       4x4 camera-to-world (OpenCV axes, metres), KinectFusion poses
    <root>/camera-intrinsics.txt     optional: 3x3 matrix or one line "fx fy cx cy" (also looked for
                                     in the parent scene folder); default fx = fy = 585, cx 320, cy 240

Colour and depth come from two different Kinect cameras and are **not registered** to each other. The
reader uses the colour image as-is at the same resolution (it must be the size of the depth image) and
the depth camera's intrinsics; expect colour to be offset from depth by a few pixels. Depth-based
pipelines are unaffected; colour-supervised ones see a small misalignment, as every method published
on 7-Scenes does.

7-Scenes has no per-frame timestamps; ``timestamp_s = frame_id / 30`` (the Kinect's 30 Hz).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import CaptureError, CaptureFormatError, ValidationError
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
from .profile import KINECT_MAX_DEPTH_M, CaptureProfile

__all__ = ["SEVENSCENES_INTRINSICS", "SevenScenesCapture", "read_pose_matrix"]

SEVENSCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
"""Default ``(fx, fy, cx, cy)`` of the 7-Scenes depth camera (640x480)."""

FRAME_RATE_HZ = 30.0
_FRAME_RE = re.compile(r"^frame-(\d+)\.depth\.png$")


def read_pose_matrix(path: str | Path) -> np.ndarray | None:
    """Read a 4x4 camera-to-world pose text file; ``None`` if it holds non-finite values (unknown pose).

    Raises :class:`CaptureFormatError` naming the file if it is not 4x4 or not a rigid transform.
    """
    path = Path(path)
    m = read_text_matrix(path, "pose")
    if m.shape != (4, 4):
        raise CaptureFormatError(path, f"pose must be a 4x4 matrix, got {m.shape[0]}x{m.shape[1]}")
    if not np.all(np.isfinite(m)):
        return None
    try:
        return check_rigid(m, "pose")
    except ValidationError as e:
        raise CaptureFormatError(path, e.problem) from e


class SevenScenesCapture(BaseCapture):
    """A 7-Scenes sequence folder (see the module docstring).

    Args:
        path: the ``seq-XX`` folder holding ``frame-000000.depth.png`` ...
        K: optional ``[3, 3]`` intrinsics overriding ``camera-intrinsics.txt`` and the default.

    Example::

        cap = SevenScenesCapture("redkitchen/seq-01")
        f = cap[0]   # depth [480, 640] float32 m, colour [480, 640, 3] RGB, T_world_cam [4, 4]
    """

    def __init__(self, path: str | Path, K: np.ndarray | None = None) -> None:
        root = require_dir(path, "7-Scenes sequence folder")
        self.path = root
        self.name = root.name if not root.name.startswith("seq-") else f"{root.parent.name}-{root.name}"
        ids = sorted(int(m.group(1)) for p in root.iterdir() if (m := _FRAME_RE.match(p.name)))
        if not ids:
            raise CaptureFormatError(root, "no frame-XXXXXX.depth.png files (not a 7-Scenes sequence)")
        self._ids = ids
        self.width, self.height = image_size(self._file(0, "depth.png"))
        source: Path = root
        if K is None:
            for cand in (root / "camera-intrinsics.txt", root.parent / "camera-intrinsics.txt"):
                if cand.is_file():
                    K, source = read_intrinsics_txt(cand), cand
                    break
            else:
                K = make_intrinsics(*SEVENSCENES_INTRINSICS)
        self.K = validate_intrinsics(K, self.width, self.height, source)
        self._profile = CaptureProfile("sevenscenes", KINECT_MAX_DEPTH_M, color_registered=False,
                                       sensor=f"7-Scenes, Kinect v1 {self.width}x{self.height}")

    def _file(self, i: int, suffix: str) -> Path:
        return self.path / f"frame-{self._ids[i]:06d}.{suffix}"

    def __len__(self) -> int:
        return len(self._ids)

    def _load(self, i: int) -> RGBDFrame:
        depth_path = self._file(i, "depth.png")
        depth_m = check_depth_size(
            read_depth_png(depth_path, 1000.0, invalid_values=(65535,)), self.width, self.height, depth_path,
            "sequence",
        )
        color_path = self._file(i, "color.jpg")
        if not color_path.is_file():
            if not self._file(i, "color.png").is_file():
                raise CaptureError(color_path, "colour image not found (tried .color.jpg and .color.png)")
            color_path = self._file(i, "color.png")
        color = read_color(color_path)
        if color.shape[:2] != depth_m.shape:
            raise CaptureFormatError(
                color_path, f"colour is {color.shape[1]}x{color.shape[0]} but depth is "
                f"{self.width}x{self.height}; 7-Scenes colour is used unresized and must match"
            )
        pose_path = self._file(i, "pose.txt")
        return RGBDFrame(
            depth_m=depth_m, K=self.K, timestamp_s=self._ids[i] / FRAME_RATE_HZ, color=color,
            T_world_cam=read_pose_matrix(pose_path), index=i,
            meta={"frame_id": self._ids[i], "depth_path": str(depth_path)},
        )
