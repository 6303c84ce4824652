"""Record3D ``.r3d`` exports (iPhone / iPad LiDAR), read lazily from the zip archive.

An ``.r3d`` file is a zip archive::

    metadata           JSON: "w", "h" (colour size), "dw", "dh" (depth size), "K" (9 values, column-major,
                       for the w x h colour image), "poses" (one [qx, qy, qz, qw, px, py, pz] per frame:
                       camera-to-world, ARKit world, OpenGL camera axes), "fps", optional
                       "frameTimestamps" (seconds, one per frame)
    rgbd/<i>.jpg       colour, w x h
    rgbd/<i>.depth     LZFSE-compressed float32 metres, dh x dw row-major (non-finite / <= 0 = invalid)
    rgbd/<i>.conf      optional, LZFSE-compressed uint8 confidence 0/1/2, dh x dw

Frames are ``i = 0 .. N-1`` for the ``rgbd/<i>.depth`` entries. Poses are converted to OpenCV camera
axes with :func:`geometry.opengl_to_opencv` and go into both ``T_world_cam`` (reference pose) and
``T_world_cam_device`` (device prior): ARKit VIO, not ground truth. ``K`` is scaled from ``w x h`` to the
depth resolution and colour is resized to it with area averaging. Timestamps come from
``frameTimestamps`` when present, else ``i / fps``.

The archive is opened on first read and kept open (one handle per process, guarded by a lock, so a
capture may be shared between threads; after ``fork`` the child reopens its own handle). Call
:meth:`Record3DCapture.close` or use the capture as a context manager to release it early.
"""

from __future__ import annotations

import json
import os
import re
import threading
import zipfile
from pathlib import Path

import lzfse
import numpy as np

from ..errors import CaptureError, CaptureFormatError
from ..geometry import opengl_to_opencv, pose_from_tum, scale_intrinsics
from .frame import BaseCapture, RGBDFrame
from .images import check_confidence, decode_color, resize_color, validate_intrinsics
from .profile import LIDAR_MAX_DEPTH_M, CaptureProfile

__all__ = ["Record3DCapture"]

_DEPTH_RE = re.compile(r"^rgbd/(\d+)\.depth$")


class Record3DCapture(BaseCapture):
    """A Record3D ``.r3d`` file (see the module docstring).

    Args:
        path: the ``.r3d`` file.

    Example::

        with Record3DCapture("scan.r3d") as cap:
            f = cap[0]   # depth [dh, dw] float32 m, colour resized to [dh, dw, 3], K for dw x dh
    """

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        if not path.is_file():
            raise CaptureError(path, "Record3D file not found")
        self.path = path
        self.name = path.stem
        self._lock = threading.Lock()
        self._zf: zipfile.ZipFile | None = None
        self._pid = -1
        try:
            with zipfile.ZipFile(path) as zf:
                names = zf.namelist()
                if "metadata" not in names:
                    raise CaptureFormatError(path, "no 'metadata' entry (not a Record3D .r3d archive)")
                meta_bytes = zf.read("metadata")
        except zipfile.BadZipFile as e:
            raise CaptureFormatError(path, f"not a zip archive, so not a Record3D .r3d file ({e})") from e
        self._names = set(names)
        ids = sorted(int(m.group(1)) for n in names if (m := _DEPTH_RE.match(n)))
        if not ids:
            raise CaptureFormatError(path, "no rgbd/<i>.depth entries")
        if ids != list(range(len(ids))):
            raise CaptureFormatError(path, "rgbd/<i>.depth entries are not numbered 0..N-1 without gaps")
        n = len(ids)
        self._n = n
        try:
            meta = json.loads(meta_bytes)
            self.color_size = (int(meta["w"]), int(meta["h"]))
            self.width, self.height = int(meta["dw"]), int(meta["dh"])
            K_color = np.asarray(meta["K"], dtype=np.float64).reshape(3, 3).T  # stored column-major
            poses = np.asarray(meta.get("poses", []), dtype=np.float64)
            timestamps = meta.get("frameTimestamps")
            fps = meta.get("fps")
        except (ValueError, KeyError, TypeError) as e:
            raise CaptureFormatError(f"{path}/metadata", f"bad or incomplete metadata JSON ({e!r})") from e
        meta_src = f"{path}/metadata"
        validate_intrinsics(K_color, *self.color_size, meta_src)
        self.K = validate_intrinsics(
            scale_intrinsics(K_color, self.color_size, (self.width, self.height)), self.width, self.height,
            meta_src,
        )
        if poses.size == 0:
            self._poses = None
        elif poses.ndim != 2 or poses.shape[1] != 7 or poses.shape[0] < n:
            raise CaptureFormatError(
                meta_src,
                f"'poses' must hold {n} rows of [qx, qy, qz, qw, px, py, pz], got shape {poses.shape}",
            )
        else:
            q = poses[:n, :4]
            norms = np.linalg.norm(q, axis=1)
            if not np.all(np.isfinite(poses[:n])) or np.any(norms < 1e-6):
                raise CaptureFormatError(meta_src, "'poses' holds a non-finite value or a zero quaternion")
            self._poses = opengl_to_opencv(pose_from_tum(poses[:n, 4:7], q / norms[:, None]))
        self._profile = CaptureProfile(
            "iphone", LIDAR_MAX_DEPTH_M, has_confidence="rgbd/0.conf" in self._names,
            sensor=f"Record3D, iPhone LiDAR {self.width}x{self.height}")
        if timestamps is not None and len(timestamps) >= n:
            self._timestamps_s = np.asarray(timestamps[:n], dtype=np.float64)
        elif fps:
            self._timestamps_s = np.arange(n, dtype=np.float64) / float(fps)
        else:
            raise CaptureFormatError(meta_src, "neither 'frameTimestamps' (one per frame) nor 'fps' given")

    # --- archive handle -------------------------------------------------------------------------
    def _read(self, name: str) -> bytes:
        if name not in self._names:
            raise CaptureError(f"{self.path}/{name}", "entry not found in the .r3d archive")
        with self._lock:
            if self._zf is None or self._pid != os.getpid():
                self._zf = zipfile.ZipFile(self.path)
                self._pid = os.getpid()
            try:
                return self._zf.read(name)
            except (zipfile.BadZipFile, OSError, EOFError) as e:
                raise CaptureError(f"{self.path}/{name}", f"corrupt archive entry ({e})") from e

    def close(self) -> None:
        """Close the archive handle (it reopens on the next read)."""
        with self._lock:
            if self._zf is not None:
                self._zf.close()
                self._zf = None

    def __enter__(self) -> Record3DCapture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_zf"], state["_lock"] = None, None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    # --- frames ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    def _decompress(self, name: str, dtype: type, what: str) -> np.ndarray:
        try:
            raw = lzfse.decompress(self._read(name))
        except lzfse.error as e:
            raise CaptureError(f"{self.path}/{name}", f"corrupt LZFSE {what} ({e})") from e
        expected = self.width * self.height * np.dtype(dtype).itemsize
        if len(raw) != expected:
            raise CaptureFormatError(
                f"{self.path}/{name}", f"{what} holds {len(raw)} bytes, expected {expected} for "
                f"{self.width}x{self.height} {np.dtype(dtype).name} (metadata dw x dh)"
            )
        return np.frombuffer(raw, dtype=dtype).reshape(self.height, self.width).copy()

    def _load(self, i: int) -> RGBDFrame:
        depth_m = self._decompress(f"rgbd/{i}.depth", np.float32, "depth")
        depth_m[~np.isfinite(depth_m) | (depth_m < 0)] = 0.0
        confidence = None
        conf_name = f"rgbd/{i}.conf"
        if conf_name in self._names:
            raw_conf = self._decompress(conf_name, np.uint8, "confidence")
            confidence = check_confidence(raw_conf, f"{self.path}/{conf_name}")
        color_name = f"rgbd/{i}.jpg"
        color = decode_color(self._read(color_name), f"{self.path}/{color_name}")
        if (color.shape[1], color.shape[0]) != self.color_size:
            raise CaptureFormatError(
                f"{self.path}/{color_name}", f"colour is {color.shape[1]}x{color.shape[0]}, metadata says "
                f"{self.color_size[0]}x{self.color_size[1]}"
            )
        color = resize_color(color, self.width, self.height)
        T = None if self._poses is None else self._poses[i]
        return RGBDFrame(
            depth_m=depth_m, K=self.K, timestamp_s=float(self._timestamps_s[i]), color=color,
            confidence=confidence, T_world_cam=None if T is None else T.copy(),
            T_world_cam_device=None if T is None else T.copy(), index=i, meta={"entry": f"rgbd/{i}.depth"},
        )
