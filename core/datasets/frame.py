"""The one frame type every capture format converts into, and the capture interface readers share."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ..errors import ShapeError, ValidationError
from ..geometry import check_intrinsics, check_rigid
from .profile import CaptureProfile

__all__ = ["RGBDFrame", "Capture", "BaseCapture", "TimedFrames"]


@dataclass(frozen=True, eq=False)
class RGBDFrame:
    """One RGB-D observation.

    Attributes:
        depth_m: ``[H, W]`` float32 depth in metres, 0 = invalid.
        K: ``[3, 3]`` float64 pinhole intrinsics for the *depth* resolution ``(W, H)``.
        timestamp_s: capture time in seconds (device clock, not wall clock).
        color: ``[H, W, 3]`` uint8 RGB at the depth resolution, or ``None`` for depth-only captures.
        confidence: ``[H, W]`` uint8 in {0, 1, 2} (low/medium/high) or ``None``.
        T_world_cam: reference pose, ``[4, 4]`` float64 camera-to-world, OpenCV axes, metres (ground
            truth or the dataset's pose), or ``None``.
        T_world_cam_device: the capture device's own pose estimate (e.g. ARKit VIO), same convention
            as ``T_world_cam``, or ``None``.
        index: position of the frame in its capture (0-based).
    """

    depth_m: np.ndarray
    K: np.ndarray
    timestamp_s: float
    color: np.ndarray | None = None
    confidence: np.ndarray | None = None
    T_world_cam: np.ndarray | None = None
    T_world_cam_device: np.ndarray | None = None
    index: int = 0
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        d = self.depth_m
        if not isinstance(d, np.ndarray) or d.ndim != 2:
            raise ShapeError("depth_m", getattr(d, "shape", ()), "[H, W]")
        if d.dtype != np.float32:
            raise ValidationError("depth_m", f"dtype must be float32 metres, got {d.dtype}")
        h, w = d.shape
        if self.color is not None:
            c = self.color
            if c.shape != (h, w, 3):
                raise ShapeError("color", c.shape, f"({h}, {w}, 3) (the depth resolution)")
            if c.dtype != np.uint8:
                raise ValidationError("color", f"dtype must be uint8, got {c.dtype}")
        if self.confidence is not None:
            if self.confidence.shape != (h, w):
                raise ShapeError("confidence", self.confidence.shape, f"({h}, {w})")
            if self.confidence.dtype != np.uint8:
                raise ValidationError("confidence", f"dtype must be uint8, got {self.confidence.dtype}")
        object.__setattr__(self, "K", check_intrinsics(self.K, w, h, "K"))
        if self.T_world_cam is not None:
            object.__setattr__(self, "T_world_cam", check_rigid(self.T_world_cam, "T_world_cam"))
        if self.T_world_cam_device is not None:
            object.__setattr__(
                self, "T_world_cam_device", check_rigid(self.T_world_cam_device, "T_world_cam_device")
            )
        if not np.isfinite(self.timestamp_s):
            raise ValidationError("timestamp_s", "must be finite")

    @property
    def height(self) -> int:
        return int(self.depth_m.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth_m.shape[1])

    @property
    def has_color(self) -> bool:
        return self.color is not None

    def with_(self, **changes: object) -> RGBDFrame:
        """Return a copy with some fields replaced (validated again)."""
        return replace(self, **changes)


@runtime_checkable
class Capture(Protocol):
    """A recorded capture: a lazily read, ordered sequence of frames.

    Readers open files only when a frame is asked for; ``len`` and ``frames()`` never load all images.
    """

    name: str
    path: Path

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> RGBDFrame: ...

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[RGBDFrame]: ...

    @property
    def gt_mesh_path(self) -> Path | None: ...

    @property
    def profile(self) -> CaptureProfile: ...


class BaseCapture:
    """Shared machinery for readers: subclasses set ``name``/``path`` and implement ``__len__`` and
    ``_load(i)``; indexing, negative indices, range checks and lazy iteration come from here. Readers set
    ``_profile`` (a :class:`CaptureProfile`) in ``__init__``; other captures get one read off frame 0."""

    name: str
    path: Path
    _gt_mesh_path: Path | None = None
    _profile: CaptureProfile | None = None

    def __len__(self) -> int:
        raise NotImplementedError  # abstract: every reader defines it

    def _load(self, i: int) -> RGBDFrame:
        raise NotImplementedError  # abstract: every reader defines it

    def __getitem__(self, i: int) -> RGBDFrame:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for {self.name} ({n} frames)")
        return self._load(i)

    def __iter__(self) -> Iterator[RGBDFrame]:
        return self.frames()

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[RGBDFrame]:
        """Yield frames ``start:stop:step`` one at a time (nothing is preloaded)."""
        for i in range(*slice(start, stop, step).indices(len(self))):
            yield self._load(i)

    @property
    def gt_mesh_path(self) -> Path | None:
        """Ground-truth mesh of the scene, when the capture has one."""
        return self._gt_mesh_path

    @property
    def profile(self) -> CaptureProfile:
        """What this capture is (kind, useful depth range, confidence, colour): the reader's
        :class:`CaptureProfile`, or for other captures one read off frame 0 (kind ``unknown``)."""
        if self._profile is None:
            self._profile = CaptureProfile.from_frame(self[0]) if len(self) else CaptureProfile()
        return self._profile

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, path='{self.path}', frames={len(self)})"


class TimedFrames:
    """Iterate ``frames`` (any iterable of :class:`RGBDFrame`) and add up the seconds spent waiting for each
    one in :attr:`load_s` (reading / decoding / rendering a capture), so a run's processing time can leave
    it out: a method's frames/s is ``n / (wall - load_s)``, as the TSDF baseline's is."""

    def __init__(self, frames: Iterable[RGBDFrame]) -> None:
        self._it = iter(frames)
        self.load_s = 0.0

    def __iter__(self) -> TimedFrames:
        return self

    def __next__(self) -> RGBDFrame:
        t = time.perf_counter()
        try:
            return next(self._it)
        finally:
            self.load_s += time.perf_counter() - t
