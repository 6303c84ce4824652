"""Reusable frame transforms and capture wrappers.

Frame transforms are plain functions ``RGBDFrame -> RGBDFrame`` (frames are immutable; each returns a
new, re-validated frame). :class:`TransformedCapture` applies a chain of them lazily to every frame of a
capture, :class:`SlicedCapture` is a lazy ``start:stop:step`` view of one and :class:`RevisitCapture` one in which
the camera comes back to a place it saw.

Example::

    from functools import partial
    cap = TransformedCapture(open_capture("scan"), partial(clip_depth, min_m=0.1, max_m=4.0))
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from ..errors import ValidationError
from ..geometry import scale_intrinsics
from .frame import BaseCapture, Capture, RGBDFrame
from .profile import CaptureProfile

__all__ = [
    "FrameTransform",
    "resize_frame",
    "filter_depth_by_confidence",
    "clip_depth",
    "drop_depth",
    "TransformedCapture",
    "SlicedCapture",
    "RevisitCapture",
]

FrameTransform = Callable[[RGBDFrame], RGBDFrame]


def resize_frame(frame: RGBDFrame, width: int, height: int) -> RGBDFrame:
    """Resize every image of ``frame`` to ``width`` x ``height`` and scale ``K`` to match.

    Depth and confidence use nearest-neighbour sampling (no depth is invented across edges, invalid
    zeros stay zeros), colour uses area averaging. ``K`` is scaled with
    :func:`geometry.scale_intrinsics`.
    """
    if width < 1 or height < 1:
        raise ValidationError("width/height", f"must be >= 1, got {width}x{height}")
    if (width, height) == (frame.width, frame.height):
        return frame
    size = (int(width), int(height))
    depth_m = cv2.resize(frame.depth_m, size, interpolation=cv2.INTER_NEAREST)
    color = None if frame.color is None else cv2.resize(frame.color, size, interpolation=cv2.INTER_AREA)
    conf = None
    if frame.confidence is not None:
        conf = cv2.resize(frame.confidence, size, interpolation=cv2.INTER_NEAREST)
    K = scale_intrinsics(frame.K, (frame.width, frame.height), size)
    return frame.with_(depth_m=depth_m, color=color, confidence=conf, K=K)


def filter_depth_by_confidence(frame: RGBDFrame, min_confidence: int) -> RGBDFrame:
    """Set depth to 0 where confidence < ``min_confidence`` (0, 1 or 2).

    Frames without a confidence map are returned unchanged (TUM, 7-Scenes, ... have none).
    """
    if min_confidence not in (0, 1, 2):
        raise ValidationError("min_confidence", f"must be 0, 1 or 2, got {min_confidence}")
    if frame.confidence is None or min_confidence == 0:
        return frame
    depth_m = np.where(frame.confidence >= min_confidence, frame.depth_m, np.float32(0.0))
    return frame.with_(depth_m=depth_m.astype(np.float32))


def drop_depth(frame: RGBDFrame, start: int, stop: int) -> RGBDFrame:
    """No depth (all 0) in frames ``start <= frame.index < stop``: a sensor that saw nothing for a while (pointed at
    the sky, covered, too close), for testing how tracking comes back after the gap."""
    if not 0 <= start <= stop:
        raise ValidationError("start/stop", f"need 0 <= start <= stop, got {start}, {stop}")
    if not start <= frame.index < stop:
        return frame
    return frame.with_(depth_m=np.zeros_like(frame.depth_m))


def clip_depth(frame: RGBDFrame, min_m: float = 0.0, max_m: float = float("inf")) -> RGBDFrame:
    """Set depth outside ``[min_m, max_m]`` metres to 0 (invalid)."""
    if not (0.0 <= min_m < max_m):
        raise ValidationError("min_m/max_m", f"need 0 <= min_m < max_m, got {min_m}, {max_m}")
    d = frame.depth_m
    depth_m = np.where((d >= min_m) & (d <= max_m), d, np.float32(0.0)).astype(np.float32)
    return frame.with_(depth_m=depth_m)


class TransformedCapture(BaseCapture):
    """``capture`` with ``transforms`` applied, in order, to each frame as it is read.

    Args:
        capture: any :class:`Capture`.
        *transforms: functions ``RGBDFrame -> RGBDFrame`` (use ``functools.partial`` for parameters).
    """

    def __init__(self, capture: Capture, *transforms: FrameTransform) -> None:
        for k, fn in enumerate(transforms):
            if not callable(fn):
                raise ValidationError(f"transforms[{k}]", f"must be callable, got {type(fn).__name__}")
        self.capture = capture
        self.transforms = tuple(transforms)
        self.name = capture.name
        self.path = Path(capture.path)

    def __len__(self) -> int:
        return len(self.capture)

    def _load(self, i: int) -> RGBDFrame:
        frame = self.capture[i]
        for fn in self.transforms:
            frame = fn(frame)
        return frame

    @property
    def gt_mesh_path(self) -> Path | None:
        return self.capture.gt_mesh_path

    @property
    def profile(self) -> CaptureProfile:
        """The wrapped capture's profile."""
        return self.capture.profile


class SlicedCapture(BaseCapture):
    """A lazy ``start:stop:step`` view of ``capture`` (e.g. every 2nd frame, or the first 100).

    Frames keep their source position in ``meta["source_index"]``; ``index`` is the position in the
    view, so ``view[k].index == k``.
    """

    def __init__(self, capture: Capture, start: int = 0, stop: int | None = None, step: int = 1) -> None:
        if step < 1:
            raise ValidationError("step", f"must be >= 1, got {step}")
        self.capture = capture
        self.name = capture.name
        self.path = Path(capture.path)
        self._indices: Sequence[int] = range(*slice(start, stop, step).indices(len(capture)))

    def __len__(self) -> int:
        return len(self._indices)

    def _load(self, i: int) -> RGBDFrame:
        src = self._indices[i]
        frame = self.capture[src]
        return frame.with_(index=i, meta={**frame.meta, "source_index": src})

    @property
    def gt_mesh_path(self) -> Path | None:
        return self.capture.gt_mesh_path

    @property
    def profile(self) -> CaptureProfile:
        """The wrapped capture's profile."""
        return self.capture.profile


class RevisitCapture(SlicedCapture):
    """The first ``at`` frames of ``capture``, then, after ``pause_s`` seconds without frames, its frames ``back_to
    .. back_to + frames - 1`` again: a camera that comes back to a place it saw (covered while its user walked back,
    or a robot that returned), for testing relocalisation. A view like :class:`SlicedCapture` (re-indexed in order,
    the source position in ``meta["source_index"]``, the reference pose kept), re-stamped so that the clock runs
    on: the revisit's frames keep their own spacing, ``pause_s`` after the last first-pass frame.
    """

    def __init__(self, capture: Capture, at: int, back_to: int, frames: int, pause_s: float = 1.0) -> None:
        if not (1 <= at <= len(capture) and 0 <= back_to < at and frames >= 1 and back_to + frames <= len(capture)):
            raise ValidationError("at/back_to/frames", f"need 1 <= at <= {len(capture)}, 0 <= back_to < at, "
                                  f"frames >= 1 and back_to + frames <= {len(capture)}; got {at}, {back_to}, {frames}")
        if not pause_s > 0:
            raise ValidationError("pause_s", f"must be > 0 (the clock runs on), got {pause_s}")
        super().__init__(capture)
        self._indices = [*range(at), *range(back_to, back_to + frames)]
        self._at = at
        # the revisit's clock: its first frame pause_s after the last first-pass frame, its own spacing after that
        self._shift_s = capture[at - 1].timestamp_s + pause_s - capture[back_to].timestamp_s

    def _load(self, i: int) -> RGBDFrame:
        frame = super()._load(i)
        return frame.with_(timestamp_s=frame.timestamp_s + self._shift_s) if i >= self._at else frame
