"""Polycam "raw data" exports (developer mode, iPhone / iPad LiDAR), read lazily.

Layout (Polycam's own description: github.com/PolyCam/polyform, README "Polycam's data format")::

    <root>/keyframes/images/<ts>.jpg             colour as captured (slightly distorted), e.g. 1024x768
    <root>/keyframes/cameras/<ts>.json           ARKit camera: "fx", "fy", "cx", "cy" for the "width" x
                                                 "height" image, "t_00" ... "t_23" (row i, column j of the
                                                 3x4 camera-to-world; the last row [0, 0, 0, 1] is left
                                                 out), "timestamp" (µs), "blur_score" (lower = blurrier),
                                                 also "neighbors", "manual_keyframe" (ignored)
    <root>/keyframes/corrected_images/<ts>.jpg   optional: undistorted images (black borders possible)
    <root>/keyframes/corrected_cameras/<ts>.json optional: the same fields, poses globally optimised
    <root>/keyframes/depth/<ts>.png              uint16 millimetres, e.g. 256x192, 0 = invalid
    <root>/keyframes/confidence/<ts>.png         optional, uint8 0 / 127 / 255 = low / medium / high
    <root>/raw.glb, mesh_info.json, polycam.mp4, thumbnail.jpg   ignored

``<ts>`` is the keyframe's timestamp in microseconds; it names one keyframe's files in every folder.

**Corrected data is preferred**: when both ``corrected_cameras/`` and ``corrected_images/`` exist (Polycam
writes them when its on-device pose optimisation ran: "you should almost always use these"), the
keyframes, poses, intrinsics and colour come from them, as Polycam's own tools do; ``corrected=False``
reads the ARKit ``cameras/`` + ``images/`` instead, ``corrected=True`` requires the corrected pair.

Poses: ARKit's gravity-aligned world (+y up) with ARKit / OpenGL camera axes (x right, y up, looking along
-z), the convention Polycam documents and that nerfstudio's and instant-ngp's importers rely on (both use
the 3x4 as a camera-to-world in OpenGL camera axes; nerfstudio only permutes the world axes). Converted to
OpenCV camera axes with :func:`geometry.opengl_to_opencv`. ``T_world_cam`` (reference) is the pose of the
cameras used (the corrected one when corrected); ``T_world_cam_device`` (the prior tracking may start from)
is always ARKit's own pose from ``cameras/``, ``None`` for a keyframe without one.

Intrinsics describe the ``width`` x ``height`` image and differ a little per keyframe; each frame's ``K`` is
scaled to the depth resolution with :func:`geometry.scale_intrinsics` (Polycam: "you will have to scale the
camera intrinsics to match the depth map resolution"). Colour is resized to the depth resolution (area
averaging). Confidence 0 / 127 / 255 becomes 0 / 1 / 2; depth with confidence below
``confidence_threshold`` is set to 0 (the converted map is still returned); ``None`` keeps all depth.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import CaptureError, CaptureFormatError, ValidationError
from ..geometry import check_rigid, make_intrinsics, opengl_to_opencv, scale_intrinsics
from .checks import apply_confidence, check_confidence_threshold, check_depth_size, read_json_object, require_dir
from .frame import BaseCapture, RGBDFrame
from .images import image_size, read_color, read_depth_png, require_file, resize_color, validate_intrinsics
from .profile import LIDAR_MAX_DEPTH_M, CaptureProfile

__all__ = ["PolycamCapture", "POLYCAM_CONFIDENCE_LEVELS", "read_polycam_confidence", "looks_like_polycam"]

POLYCAM_CONFIDENCE_LEVELS = (0, 127, 255)
"""Raw values of Polycam's low / medium / high confidence (ours: 0 / 1 / 2)."""

_POSE_KEYS = tuple(f"t_{i}{j}" for i in range(3) for j in range(4))
_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", *_POSE_KEYS)


def looks_like_polycam(folder: Path) -> bool:
    """Whether ``folder`` holds a ``keyframes/`` folder (the Polycam raw-data layout's marker)."""
    return (folder / "keyframes").is_dir()


def read_polycam_confidence(path: str | Path) -> np.ndarray:
    """Read a Polycam confidence PNG (uint8 0 / 127 / 255) as ``[H, W]`` uint8 0 / 1 / 2."""
    path = require_file(path, "confidence image")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise CaptureError(path, "unreadable or corrupt image (OpenCV could not decode it)")
    if raw.ndim != 2 or raw.dtype != np.uint8:
        raise CaptureFormatError(path, f"confidence must be single-channel uint8, got {raw.dtype} {raw.shape}")
    bad = ~np.isin(raw, POLYCAM_CONFIDENCE_LEVELS)
    if bad.any():
        raise CaptureFormatError(
            path, f"confidence values must be 0/127/255 (low/medium/high), found {int(raw[bad][0])}"
        )
    return (raw // 127).astype(np.uint8)


def _read_camera(path: Path) -> dict:
    """One camera JSON, checked: every key of ``_CAMERA_KEYS`` present and finite."""
    data = read_json_object(path, "camera file")
    missing = [k for k in _CAMERA_KEYS if k not in data]
    if missing:
        raise CaptureFormatError(path, f"camera lacks {missing}; a Polycam camera has fx, fy, cx, cy, width, "
                                       "height and t_00 ... t_23")
    try:
        values = np.asarray([data[k] for k in _CAMERA_KEYS], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise CaptureFormatError(path, f"camera fields must be numbers ({e})") from e
    if not np.all(np.isfinite(values)):
        raise CaptureFormatError(path, "camera holds a non-finite value")
    return data


def _pose(data: dict, path: Path) -> np.ndarray:
    """``[4, 4]`` camera-to-world (OpenCV axes) from the ``t_ij`` fields of one camera JSON."""
    T = np.eye(4)
    T[:3] = np.asarray([data[k] for k in _POSE_KEYS], dtype=np.float64).reshape(3, 4)
    try:
        check_rigid(T, "t_00..t_23")
    except ValidationError as e:
        raise CaptureFormatError(path, e.problem + " in t_00..t_23") from e
    return opengl_to_opencv(T)


def _stems(folder: Path, suffix: str) -> set[str]:
    return {p.stem for p in folder.glob(f"*{suffix}")} if folder.is_dir() else set()


class PolycamCapture(BaseCapture):
    """A Polycam raw-data export (see the module docstring).

    Args:
        path: the export folder (holding ``keyframes/``).
        confidence_threshold: zero depth whose confidence is below this (0, 1 or 2); ``None`` keeps all.
        corrected: ``None`` uses the corrected cameras and images when both folders exist, ``True`` requires
            them, ``False`` reads ARKit's ``cameras/`` and ``images/``.

    Attributes:
        corrected: whether the corrected cameras and images are in use.

    Example::

        cap = PolycamCapture("my_polycam_export")
        f = cap[0]   # depth [192, 256] float32 m, K scaled to 256x192, colour [192, 256, 3] uint8 RGB
    """

    def __init__(self, path: str | Path, confidence_threshold: int | None = 1,
                 corrected: bool | None = None) -> None:
        root = require_dir(path, "Polycam export folder")
        self.confidence_threshold = check_confidence_threshold(confidence_threshold)
        kf = root / "keyframes"
        if not kf.is_dir():
            raise CaptureFormatError(kf, "keyframes folder not found (not a Polycam raw-data export)")
        self.path = root
        self.name = root.name
        has_corrected = (kf / "corrected_cameras").is_dir() and (kf / "corrected_images").is_dir()
        if corrected and not has_corrected:
            raise CaptureFormatError(kf, "corrected=True but keyframes/corrected_cameras and "
                                         "keyframes/corrected_images are not both there")
        self.corrected = has_corrected if corrected is None else bool(corrected)
        prefix = "corrected_" if self.corrected else ""
        self._cameras, self._images = kf / f"{prefix}cameras", kf / f"{prefix}images"
        self._depth, self._conf = kf / "depth", kf / "confidence"
        for folder in (self._cameras, self._images, self._depth):
            if not folder.is_dir():
                raise CaptureFormatError(folder, f"keyframes/{folder.name} folder not found")

        stems = sorted(_stems(self._cameras, ".json"), key=lambda s: (_stem_us(s) is None, _stem_us(s) or 0, s))
        if not stems:
            raise CaptureFormatError(self._cameras, "no <timestamp>.json camera files")
        self._has_conf = self._conf.is_dir()
        needs = [(self._depth, ".png"), (self._images, ".jpg")] + ([(self._conf, ".png")] if self._has_conf else [])
        problems = []
        for folder, suffix in needs:
            present = _stems(folder, suffix)
            lacking = [s for s in stems if s not in present]
            if lacking:
                first = ", ".join(s + suffix for s in lacking[:3]) + (", ..." if len(lacking) > 3 else "")
                problems.append(f"{len(lacking)} of {len(stems)} cameras in keyframes/{self._cameras.name} have "
                                f"no keyframes/{folder.name}/<timestamp>{suffix} ({first})")
        if problems:
            raise CaptureFormatError(kf, "; ".join(problems))
        self._stems = stems

        self.width, self.height = image_size(self._depth / f"{stems[0]}.png")
        poses, device, Ks, times, sizes, blur = [], [], [], [], [], []
        for stem in stems:
            cam_path = self._cameras / f"{stem}.json"
            cam = _read_camera(cam_path)
            w, h = int(cam["width"]), int(cam["height"])
            if abs(w / h - self.width / self.height) > 0.01 * self.width / self.height:
                raise CaptureFormatError(cam_path, f"image is {w}x{h} but depth is {self.width}x{self.height}: "
                                                   "different aspect ratios, K cannot be scaled to the depth")
            K_img = validate_intrinsics(make_intrinsics(cam["fx"], cam["fy"], cam["cx"], cam["cy"]), w, h, cam_path)
            K = scale_intrinsics(K_img, (w, h), (self.width, self.height))
            Ks.append(validate_intrinsics(K, self.width, self.height, cam_path))
            poses.append(_pose(cam, cam_path))
            sizes.append((w, h))
            times.append(_timestamp_s(cam, stem, cam_path))
            blur.append(cam.get("blur_score"))
            arkit_path = kf / "cameras" / f"{stem}.json"
            if not self.corrected:
                device.append(poses[-1])
            elif arkit_path.is_file():
                device.append(_pose(_read_camera(arkit_path), arkit_path))
            else:
                device.append(None)
        self._poses, self._device_poses, self._K = poses, device, np.stack(Ks)
        self._image_sizes, self._blur = sizes, blur
        self._timestamps_s = np.asarray(times, dtype=np.float64)
        which = "corrected poses" if self.corrected else "ARKit poses"
        self._profile = CaptureProfile(
            "iphone", LIDAR_MAX_DEPTH_M, has_confidence=self._has_conf,
            sensor=f"Polycam, iPhone LiDAR {self.width}x{self.height}, {which}")

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` intrinsics of frame 0 at the depth resolution (each frame carries its own)."""
        return self._K[0].copy()

    def __len__(self) -> int:
        return len(self._stems)

    def _load(self, i: int) -> RGBDFrame:
        stem = self._stems[i]
        depth_path = self._depth / f"{stem}.png"
        depth_m = check_depth_size(read_depth_png(depth_path, 1000.0), self.width, self.height, depth_path)
        confidence = None
        if self._has_conf:
            conf_path = self._conf / f"{stem}.png"
            confidence = apply_confidence(
                depth_m, read_polycam_confidence(conf_path), self.confidence_threshold, conf_path
            )
        color_path = self._images / f"{stem}.jpg"
        color = read_color(color_path)
        if (color.shape[1], color.shape[0]) != self._image_sizes[i]:
            w, h = self._image_sizes[i]
            raise CaptureFormatError(
                color_path, f"image is {color.shape[1]}x{color.shape[0]}, its camera says {w}x{h}"
            )
        color = resize_color(color, self.width, self.height)
        device = self._device_poses[i]
        return RGBDFrame(
            depth_m=depth_m, K=self._K[i], timestamp_s=float(self._timestamps_s[i]), color=color,
            confidence=confidence, T_world_cam=self._poses[i].copy(),
            T_world_cam_device=None if device is None else device.copy(), index=i,
            meta={"stem": stem, "depth_path": str(depth_path), "blur_score": self._blur[i]},
        )


def _stem_us(stem: str) -> float | None:
    """The microseconds a ``<timestamp>`` file stem names, or ``None`` if it is not a number."""
    try:
        return float(stem)
    except ValueError:
        return None


def _timestamp_s(cam: dict, stem: str, path: Path) -> float:
    """Seconds from the camera's ``timestamp`` (µs), else from its file name."""
    us = cam.get("timestamp", _stem_us(stem))
    try:
        t = float(us) / 1e6  # type: ignore[arg-type]
    except (TypeError, ValueError):
        t = float("nan")
    if not np.isfinite(t):
        raise CaptureFormatError(path, f"no usable timestamp: 'timestamp' is {cam.get('timestamp')!r} and the "
                                       "file name is not a number of microseconds")
    return t
