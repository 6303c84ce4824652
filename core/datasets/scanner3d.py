"""3D Scanner App (Laan Labs, iPhone / iPad LiDAR) "All Data" exports, read lazily.

Layout (one flat folder; ``%05d`` is the frame index)::

    <root>/frame_%05d.json  per frame: "cameraPoseARFrame" (16 floats, row-major 4x4 camera-to-world,
                            ARKit world, OpenGL camera axes: x right, y up, looking along -z),
                            "intrinsics" (9 floats, row-major 3x3 K for the colour image, 1920x1440),
                            "time" (seconds, device clock); also GPS and exposure fields, ignored here
    <root>/depth_%05d.png   256x192 uint16 millimetres, 0 = invalid
    <root>/conf_%05d.png    optional, uint8 0/1/2 = low/medium/high
    <root>/frame_%05d.jpg   colour, 1920x1440, only for some frames (every third in app 1.9.7)
    <root>/info.json        optional capture summary (title, app version, frame count)

Frames are the ``frame_%05d.json`` files in index order; each must have its ``depth_%05d.png`` (and its
``conf_%05d.png`` when the export has confidence maps), else opening the capture raises
:class:`CaptureFormatError` naming the frames that lack them.

Poses are converted to OpenCV camera axes with :func:`geometry.opengl_to_opencv` and go into both
``T_world_cam`` (reference pose) and ``T_world_cam_device`` (the device prior tracking may start from):
ARKit VIO, not ground truth. ``K`` varies a little from frame to frame (autofocus): each frame's own ``K``
is scaled from the colour resolution (the JPEGs' size, 1920x1440 when the export has none) to the depth
resolution with :func:`geometry.scale_intrinsics`.

Colour: frames with a JPEG get it resized to the depth resolution (area averaging, registered to depth);
the others have ``color=None``, as a depth-only frame. The engine uses whatever colour a frame has, so
every depth frame still tracks and maps; ``open_capture(path, stride=3)`` (``voxfusion run --stride 3``)
keeps exactly the frames with colour in app 1.9.7's exports. ``capture.color_indices`` lists them.

Depth with confidence below ``confidence_threshold`` is set to 0 (the raw confidence map is still
returned); ``None`` keeps all depth.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import CaptureFormatError, ValidationError
from ..geometry import check_rigid, opengl_to_opencv, scale_intrinsics
from .checks import apply_confidence, check_confidence_threshold, check_depth_size, read_json_object, require_dir
from .frame import BaseCapture, RGBDFrame
from .images import image_size, read_color, read_confidence, read_depth_png, resize_color, validate_intrinsics
from .profile import LIDAR_MAX_DEPTH_M, CaptureProfile

__all__ = ["Scanner3DCapture", "SCANNER3D_COLOR_SIZE", "looks_like_scanner3d"]

SCANNER3D_COLOR_SIZE = (1920, 1440)
"""Colour resolution ``(width, height)`` the ``intrinsics`` refer to when the export holds no JPEG."""

_JSON_RE = re.compile(r"^frame_(\d+)\.json$")
_POSE_KEY, _K_KEY, _TIME_KEY = "cameraPoseARFrame", "intrinsics", "time"


def looks_like_scanner3d(folder: Path) -> bool:
    """Whether ``folder`` holds ``frame_<index>.json`` files (the 3D Scanner App layout's marker)."""
    return any(_JSON_RE.match(p.name) for p in folder.glob("frame_*.json"))


def _numbers(data: dict, key: str, count: int, path: Path, what: str) -> np.ndarray:
    """``data[key]`` as ``[count]`` finite float64, or :class:`CaptureFormatError` naming the key."""
    if key not in data:
        raise CaptureFormatError(path, f"no {key!r} ({what}); not a 3D Scanner App frame file")
    try:
        a = np.asarray(data[key], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise CaptureFormatError(path, f"{key!r} is not a list of numbers ({e})") from e
    if a.size != count:
        raise CaptureFormatError(path, f"{key!r} holds {a.size} values, expected {count} ({what})")
    if not np.all(np.isfinite(a)):
        raise CaptureFormatError(path, f"{key!r} holds a non-finite value")
    return a


def _read_frame_json(path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """``(T_world_cam_gl [4, 4], K_color [3, 3], time_s)`` from one ``frame_%05d.json``."""
    data = read_json_object(path, "frame file")
    T = _numbers(data, _POSE_KEY, 16, path, "16 floats, row-major 4x4 camera-to-world").reshape(4, 4)
    try:
        check_rigid(T, _POSE_KEY)
    except ValidationError as e:
        raise CaptureFormatError(path, e.problem + f" in {_POSE_KEY!r}") from e
    T[3] = (0.0, 0.0, 0.0, 1.0)  # stored as float32: 0.99999994 is 1
    K = _numbers(data, _K_KEY, 9, path, "9 floats, row-major 3x3 for the colour image").reshape(3, 3)
    t = _numbers(data, _TIME_KEY, 1, path, "seconds")[0]
    return T, K, float(t)


def _missing(ids: list[int], present: set[int], pattern: str, whose: str) -> str | None:
    """A sentence naming the frames of ``ids`` not in ``present`` (first few), or ``None``."""
    lacking = [i for i in ids if i not in present]
    if not lacking:
        return None
    first = ", ".join(pattern % i for i in lacking[:3]) + (", ..." if len(lacking) > 3 else "")
    return f"{len(lacking)} of {len(ids)} {whose} have no {pattern.replace('%05d', '*')} ({first})"


class Scanner3DCapture(BaseCapture):
    """A 3D Scanner App "All Data" export folder (see the module docstring).

    Args:
        path: the export folder (holding ``frame_%05d.json`` and ``depth_%05d.png``).
        confidence_threshold: zero depth whose confidence is below this (0, 1 or 2); ``None`` keeps all.

    Attributes:
        color_indices: positions (0-based, in this capture) of the frames that have a colour JPEG.
        color_size: ``(width, height)`` of the colour JPEGs, which the JSON intrinsics describe.

    Example::

        cap = Scanner3DCapture("scanner3d_iphone_corridor")
        f = cap[0]   # depth [192, 256] float32 m, K scaled to 256x192, colour [192, 256, 3] or None
    """

    def __init__(self, path: str | Path, confidence_threshold: int | None = 1) -> None:
        root = require_dir(path, "3D Scanner App export folder")
        self.confidence_threshold = check_confidence_threshold(confidence_threshold)
        self.path = root
        self.name = root.name

        def indices(prefix: str, suffix: str) -> set[int]:
            rx = re.compile(rf"^{prefix}_(\d+)\.{suffix}$")
            return {int(m.group(1)) for p in root.glob(f"{prefix}_*.{suffix}") if (m := rx.match(p.name))}

        ids = sorted(indices("frame", "json"))
        if not ids:
            raise CaptureFormatError(root, "no frame_%05d.json files (not a 3D Scanner App export)")
        depth_ids, conf_ids, jpg_ids = indices("depth", "png"), indices("conf", "png"), indices("frame", "jpg")
        problems = [_missing(ids, depth_ids, "depth_%05d.png", "frame_*.json")]
        if conf_ids:
            problems.append(_missing(ids, conf_ids, "conf_%05d.png", "frame_*.json"))
        problems.append(_missing(sorted(depth_ids), set(ids), "frame_%05d.json", "depth_*.png"))
        problems = [p for p in problems if p]
        if problems:
            raise CaptureFormatError(root, "; ".join(problems) + " (each frame needs its json and depth png)")
        self._ids = np.asarray(ids, dtype=np.int64)
        self._has_conf = bool(conf_ids)
        self._has_jpg = np.asarray([i in jpg_ids for i in ids])
        self.color_indices = tuple(int(k) for k in np.flatnonzero(self._has_jpg))

        self.width, self.height = image_size(self._path("depth", 0, "png"))
        if self.color_indices:
            self.color_size = image_size(self._path("frame", self.color_indices[0], "jpg"))
        else:
            self.color_size = SCANNER3D_COLOR_SIZE
        poses, Ks, times = [], [], []
        for k in range(len(ids)):
            json_path = self._path("frame", k, "json")
            T_gl, K_color, t = _read_frame_json(json_path)
            validate_intrinsics(K_color, self.color_size[0], self.color_size[1], json_path)
            K = scale_intrinsics(K_color, self.color_size, (self.width, self.height))
            Ks.append(validate_intrinsics(K, self.width, self.height, json_path))
            poses.append(opengl_to_opencv(T_gl))
            times.append(t)
        self._poses = np.stack(poses)
        self._K = np.stack(Ks)
        self._timestamps_s = np.asarray(times, dtype=np.float64)
        self._profile = CaptureProfile(
            "iphone", LIDAR_MAX_DEPTH_M, has_confidence=self._has_conf, has_color=bool(self.color_indices),
            sensor=f"3D Scanner App, iPhone LiDAR {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` intrinsics of frame 0 at the depth resolution (each frame carries its own)."""
        return self._K[0].copy()

    def _path(self, prefix: str, k: int, suffix: str) -> Path:
        return self.path / f"{prefix}_{self._ids[k]:05d}.{suffix}"

    def __len__(self) -> int:
        return len(self._ids)

    def _load(self, i: int) -> RGBDFrame:
        depth_path = self._path("depth", i, "png")
        depth_m = check_depth_size(read_depth_png(depth_path, 1000.0), self.width, self.height, depth_path)
        confidence = None
        if self._has_conf:
            conf_path = self._path("conf", i, "png")
            confidence = apply_confidence(depth_m, read_confidence(conf_path), self.confidence_threshold, conf_path)
        color = None
        if self._has_jpg[i]:
            color_path = self._path("frame", i, "jpg")
            color = read_color(color_path)
            if (color.shape[1], color.shape[0]) != self.color_size:
                raise CaptureFormatError(
                    color_path, f"colour is {color.shape[1]}x{color.shape[0]}, the export's other JPEGs are "
                    f"{self.color_size[0]}x{self.color_size[1]}"
                )
            color = resize_color(color, self.width, self.height)
        T = self._poses[i]
        return RGBDFrame(
            depth_m=depth_m, K=self._K[i], timestamp_s=float(self._timestamps_s[i]), color=color,
            confidence=confidence, T_world_cam=T.copy(), T_world_cam_device=T.copy(), index=i,
            meta={"frame_id": int(self._ids[i]), "depth_path": str(depth_path)},
        )
