"""ScanNet scenes exported from ``.sens`` files (the official ``SensReader`` layout), read lazily.

Layout::

    <root>/color/%d.jpg                    colour, 1296x968
    <root>/depth/%d.png                    uint16 millimetres, 640x480, 0 = invalid
    <root>/pose/%d.txt                     4x4 camera-to-world (OpenCV axes, metres); some rows are
                                           ``-inf`` / ``nan`` where ScanNet's tracker failed
    <root>/intrinsic/intrinsic_depth.txt   4x4 (top-left 3x3 = K of the depth camera)

Frame ids are whatever the export wrote (every frame, or every n-th with ``--frame_skip``); frames are
ordered by id. Colour is resized to the depth resolution with area averaging and used with the depth
intrinsics (ScanNet's colour and depth are only approximately registered; this is the usual practice, and the
profile says ``color_registered=False``).
Non-finite poses give ``T_world_cam=None``. ``timestamp_s = frame_id / 30``. The ground-truth mesh is
``<scene>_vh_clean_2.ply`` in the root or its parent folder.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import CaptureFormatError
from .checks import check_depth_size, require_dir
from .frame import BaseCapture, RGBDFrame
from .images import (
    image_size,
    read_color,
    read_depth_png,
    read_intrinsics_txt,
    resize_color,
    validate_intrinsics,
)
from .profile import CaptureProfile
from .sevenscenes import read_pose_matrix

__all__ = ["ScanNetCapture"]

FRAME_RATE_HZ = 30.0
SCANNET_MAX_DEPTH_M = 5.0
"""Structure-sensor depth of ScanNet is used to 5 m (noisy beyond, like every structured-light sensor)."""


class ScanNetCapture(BaseCapture):
    """A ScanNet ``.sens`` export folder (see the module docstring).

    Args:
        path: the export folder (holding ``color/``, ``depth/``, ``pose/``, ``intrinsic/``).

    Example::

        cap = ScanNetCapture("scans/scene0000_00/export")
        f = cap[0]   # depth [480, 640] float32 m, colour resized to [480, 640, 3], K of the depth camera
    """

    def __init__(self, path: str | Path) -> None:
        root = require_dir(path, "ScanNet export folder")
        self.path = root
        self.name = root.name if root.name != "export" else root.parent.name
        for sub in ("color", "depth", "pose"):
            if not (root / sub).is_dir():
                raise CaptureFormatError(root / sub, f"{sub}/ folder not found (not a ScanNet export)")
        ids = []
        for p in (root / "depth").iterdir():
            if p.suffix == ".png" and p.stem.isdigit():
                ids.append(int(p.stem))
        if not ids:
            raise CaptureFormatError(root / "depth", "no <id>.png depth images")
        self._ids = sorted(ids)
        self.width, self.height = image_size(self._path("depth", 0, "png"))
        K_path = root / "intrinsic" / "intrinsic_depth.txt"
        if not K_path.is_file():
            raise CaptureFormatError(K_path, "depth intrinsics not found")
        self.K = validate_intrinsics(read_intrinsics_txt(K_path), self.width, self.height, K_path)
        self._profile = CaptureProfile("scannet", SCANNET_MAX_DEPTH_M, color_registered=False,
                                       sensor=f"ScanNet, Structure sensor {self.width}x{self.height}")
        for mesh in (root / f"{self.name}_vh_clean_2.ply", root.parent / f"{self.name}_vh_clean_2.ply"):
            if mesh.is_file():
                self._gt_mesh_path = mesh
                break

    def _path(self, sub: str, i: int, ext: str) -> Path:
        return self.path / sub / f"{self._ids[i]}.{ext}"

    def __len__(self) -> int:
        return len(self._ids)

    def _load(self, i: int) -> RGBDFrame:
        depth_path = self._path("depth", i, "png")
        depth_m = check_depth_size(read_depth_png(depth_path, 1000.0), self.width, self.height, depth_path, "scene")
        color = resize_color(read_color(self._path("color", i, "jpg")), self.width, self.height)
        return RGBDFrame(
            depth_m=depth_m, K=self.K, timestamp_s=self._ids[i] / FRAME_RATE_HZ, color=color,
            T_world_cam=read_pose_matrix(self._path("pose", i, "txt")), index=i,
            meta={"frame_id": self._ids[i], "depth_path": str(depth_path)},
        )
