"""Whether a frame's values can be used at all: plausible intrinsics, poses within reach, enough depth.

A frame that fails these is never an error of the session that received it: the engine marks it lost and
skips it (the map starts with the first usable frame), and the wire decoder refuses what it can check at
the door (:class:`voxfusion.proto.FrameValueError`, HTTP 422). One place for the bounds, so both agree.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "MAX_POSE_TRANSLATION_M",
    "MIN_FOV_DEG",
    "MAX_FOV_DEG",
    "MIN_INIT_VALID_PIXELS",
    "intrinsics_problem",
    "pose_problem",
    "usable_pose",
]

MAX_POSE_TRANSLATION_M = 1.0e5
"""A camera more than 100 km from its world's origin is not a room-scale capture (ARKit, SLAM and dataset
worlds start near the first camera); float32 maps lose all precision long before 1e12 m."""
MIN_FOV_DEG = 2.0
MAX_FOV_DEG = 170.0
"""Field of view bounds (horizontal and vertical, degrees) of a pinhole camera we can map with: outside them
the focal length is a unit mistake (fx = 1e-6) rather than a lens."""
MIN_INIT_VALID_PIXELS = 64
"""Valid depth pixels (after range, confidence and outlier filtering) a frame needs to start the map."""


def intrinsics_problem(fx: float, fy: float, width: int, height: int) -> str | None:
    """Why focal lengths ``fx``, ``fy`` (pixels, for a ``width`` x ``height`` image) are implausible, or
    ``None`` when the field of view lies within [:data:`MIN_FOV_DEG`, :data:`MAX_FOV_DEG`]."""
    if not (math.isfinite(fx) and math.isfinite(fy)) or fx <= 0 or fy <= 0:
        return f"focal lengths must be finite and > 0, got fx={fx}, fy={fy}"
    fov_x = math.degrees(2.0 * math.atan(width / (2.0 * fx)))
    fov_y = math.degrees(2.0 * math.atan(height / (2.0 * fy)))
    if not (MIN_FOV_DEG <= fov_x <= MAX_FOV_DEG and MIN_FOV_DEG <= fov_y <= MAX_FOV_DEG):
        return (f"fx={fx:g}, fy={fy:g} for {width}x{height} give a field of view of {fov_x:.1f} x {fov_y:.1f} deg; "
                f"a camera has {MIN_FOV_DEG:g}-{MAX_FOV_DEG:g} deg (are the intrinsics in pixels, for this "
                "resolution?)")
    return None


def pose_problem(T: np.ndarray) -> str | None:
    """Why ``T`` (``[4, 4]`` camera-to-world, metres) cannot be used, or ``None``: finite, and the camera
    within :data:`MAX_POSE_TRANSLATION_M` of the origin (rigidity is checked where poses are parsed)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return "the pose must be a finite 4x4 matrix"
    distance = float(np.linalg.norm(T[:3, 3]))
    if distance > MAX_POSE_TRANSLATION_M:
        return (f"the camera is {distance:.3g} m from the world origin (more than {MAX_POSE_TRANSLATION_M:g} m): "
                "is the translation in metres?")
    return None


def usable_pose(T: np.ndarray | None) -> np.ndarray | None:
    """``T`` when :func:`pose_problem` finds nothing, else ``None`` (a pose the engine ignores)."""
    return None if T is None or pose_problem(T) is not None else T
