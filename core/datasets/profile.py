"""What a capture is, as its reader knows it: the facts that settings should follow.

Every reader sets a :class:`CaptureProfile` (``capture.profile``): which family of captures it is (the
``kind``, which names a preset in ``configs/``), how far its depth can be trusted, whether it has a
confidence map, and whether it has colour that lines up with the depth image. The engine never reads a
profile; :func:`voxfusion.core.slam.presets.preset_for` turns it into a preset and a few config values,
so a user does not have to know that 7-Scenes colour is not registered or that LiDAR depth ends at 5 m.

Example::

    cap = open_capture("../shared/data/sevenscenes_redkitchen")
    cap.profile    # CaptureProfile(kind='sevenscenes', max_depth_m=4.0, has_confidence=False,
                   #                has_color=True, color_registered=False, sensor='7-Scenes, Kinect v1 ...')
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

from ..errors import ValidationError

if TYPE_CHECKING:  # frame.py imports this module
    from .frame import RGBDFrame

__all__ = ["CaptureKind", "CAPTURE_KINDS", "CaptureProfile", "KINECT_MAX_DEPTH_M", "LIDAR_MAX_DEPTH_M",
           "SYNTHETIC_MAX_DEPTH_M"]

CaptureKind = Literal["tum", "sevenscenes", "replica", "scannet", "iphone", "synthetic", "unknown"]
"""Families of captures. Each but ``unknown`` is also the name of its preset (``configs/<kind>.yaml``)."""
CAPTURE_KINDS: tuple[str, ...] = typing.get_args(CaptureKind)

KINECT_MAX_DEPTH_M = 4.0
"""Kinect v1 / structured-light depth gets noisy (errors of several cm, growing with z^2) beyond ~4 m."""
LIDAR_MAX_DEPTH_M = 5.0
"""ARKit scene depth (iPhone / iPad LiDAR) is specified to about 5 m."""
SYNTHETIC_MAX_DEPTH_M = 10.0
"""Exact rendered depth (our synthetic room, Replica): the range the synthetic generator and Replica's uint16
depth PNGs (value / 6553.5) hold."""


@dataclass(frozen=True)
class CaptureProfile:
    """Facts about one capture, set by its reader (see the module docstring).

    Example: ``CaptureProfile("tum", max_depth_m=4.0, sensor="TUM RGB-D, Kinect v1 640x480")``.
    """

    kind: CaptureKind = "unknown"
    """Family of the capture; names its preset (``unknown``: no kind preset, the built-in defaults)."""
    max_depth_m: float | None = None
    """Depth beyond this many metres is unreliable for the sensor (``None``: no known limit)."""
    has_confidence: bool = False
    """Frames carry a per-pixel confidence map (0/1/2 = low/medium/high)."""
    has_color: bool = True
    """Frames carry colour (False: depth-only, e.g. a Stray Scanner capture without its video)."""
    color_registered: bool = True
    """Colour pixel ``(u, v)`` sees the surface point of depth pixel ``(u, v)``. False where the colour is a
    different camera only resized to the depth image (7-Scenes, ScanNet): colour then blurs geometry."""
    sensor: str = ""
    """One human-readable phrase naming the source, for messages (e.g. ``"TUM RGB-D, Kinect v1 640x480"``)."""

    def __post_init__(self) -> None:
        if self.kind not in CAPTURE_KINDS:
            raise ValidationError("kind", f"must be one of {list(CAPTURE_KINDS)}, got {self.kind!r}")
        if self.max_depth_m is not None and not self.max_depth_m > 0:
            raise ValidationError("max_depth_m", f"must be > 0 metres or None, got {self.max_depth_m}")

    @classmethod
    def from_frame(cls, frame: RGBDFrame, kind: CaptureKind = "unknown", **facts: object) -> CaptureProfile:
        """A profile with ``has_confidence`` / ``has_color`` read off one frame, for captures whose format
        says nothing about them (server recordings, hand-made captures); ``facts`` set the other fields."""
        return cls(kind=kind, has_confidence=frame.confidence is not None, has_color=frame.color is not None,
                   **facts)  # type: ignore[arg-type]

    def with_(self, **changes: object) -> CaptureProfile:
        """A copy with some fields replaced (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]

    def describe(self) -> str:
        """The facts in a few words, e.g. ``"depth to 4 m, no confidence, colour not registered to depth"``."""
        depth = f"depth to {self.max_depth_m:g} m" if self.max_depth_m is not None else "no depth limit known"
        conf = "confidence map" if self.has_confidence else "no confidence"
        if not self.has_color:
            color = "depth only"
        else:
            color = "colour registered to depth" if self.color_registered else "colour not registered to depth"
        return f"{depth}, {conf}, {color}"
