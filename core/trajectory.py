"""Trajectories: timestamps plus camera-to-world poses, and the TUM text format (the one place it is read
and written).

TUM format: one line per pose, ``timestamp tx ty tz qx qy qz qw`` (quaternion scalar last), ``#`` comments.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import CaptureFormatError, ShapeError
from .geometry import pose_from_tum, pose_to_tum

__all__ = ["Trajectory", "read_tum_trajectory", "write_tum_trajectory", "format_tum_trajectory", "interpolate_pose",
           "MAX_INTERPOLATION_GAP_S"]

MAX_INTERPOLATION_GAP_S = 0.1
"""Poses are interpolated only between samples at most this far apart (motion-capture dropouts are left unposed
rather than bridged)."""


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timestamped poses.

    Attributes:
        timestamps_s: ``[N]`` float64 seconds.
        T_world_cam: ``[N, 4, 4]`` float64 camera-to-world poses, OpenCV axes, metres.
    """

    timestamps_s: np.ndarray
    T_world_cam: np.ndarray

    def __post_init__(self) -> None:
        ts = np.asarray(self.timestamps_s, dtype=np.float64).reshape(-1)
        T = np.asarray(self.T_world_cam, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] != ts.shape[0]:
            raise ShapeError("T_world_cam", T.shape, f"[{ts.shape[0]}, 4, 4] (one pose per timestamp)")
        object.__setattr__(self, "timestamps_s", ts)
        object.__setattr__(self, "T_world_cam", T)

    def __len__(self) -> int:
        return int(self.timestamps_s.shape[0])

    def at(self, t_s: np.ndarray, max_gap_s: float = MAX_INTERPOLATION_GAP_S) -> Trajectory:
        """This trajectory's poses at the times ``t_s [M]`` (:func:`interpolate_pose`; sorted timestamps), leaving
        out the times it does not cover (outside its span, or between samples more than ``max_gap_s`` apart)."""
        kept, poses = [], []
        for t in np.asarray(t_s, dtype=np.float64).reshape(-1):
            T = interpolate_pose(self.timestamps_s, self.T_world_cam, float(t), max_gap_s)
            if T is not None:
                kept.append(t)
                poses.append(T)
        return Trajectory(np.asarray(kept, dtype=np.float64), np.stack(poses) if poses else np.zeros((0, 4, 4)))

    @property
    def positions(self) -> np.ndarray:
        """``[N, 3]`` camera centres in world frame (metres)."""
        return self.T_world_cam[:, :3, 3]


def read_tum_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM-format trajectory file; raises ``CaptureFormatError`` naming the file and line."""
    path = Path(path)
    if not path.is_file():
        raise CaptureFormatError(path, "trajectory file not found")
    rows: list[list[float]] = []
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise CaptureFormatError(path, "not a text file: expected a TUM trajectory (lines 'timestamp tx ty tz qx qy "
                                       "qz qw')") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise CaptureFormatError(
                path, f"line {lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}"
            )
        try:
            rows.append([float(p) for p in parts])
        except ValueError as e:
            raise CaptureFormatError(path, f"line {lineno}: {e}") from e
    if not rows:
        raise CaptureFormatError(path, "no poses in trajectory file")
    a = np.asarray(rows, dtype=np.float64)
    q = a[:, 4:8]
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-6) or not np.all(np.isfinite(a)):
        raise CaptureFormatError(path, "contains a zero-length quaternion or non-finite values")
    return Trajectory(a[:, 0], pose_from_tum(a[:, 1:4], q / norms[:, None]))


def format_tum_trajectory(traj: Trajectory) -> str:
    """``traj`` as TUM-format text (one line per pose, 9 decimals, with a header comment)."""
    t, q = pose_to_tum(traj.T_world_cam) if len(traj) else (np.zeros((0, 3)), np.zeros((0, 4)))
    lines = ["# timestamp tx ty tz qx qy qz qw  (camera-to-world, OpenCV camera axes, metres)"]
    for ts, ti, qi in zip(traj.timestamps_s, t, q, strict=True):
        lines.append(" ".join(f"{v:.9f}" for v in (ts, *ti, *qi)))
    return "\n".join(lines) + "\n"


def write_tum_trajectory(path: str | Path, traj: Trajectory) -> Path:
    """Write ``traj`` in TUM format (full float precision); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(format_tum_trajectory(traj))
    return path


def interpolate_pose(ts: np.ndarray, T: np.ndarray, t: float, max_gap_s: float = MAX_INTERPOLATION_GAP_S
                     ) -> np.ndarray | None:
    """The pose at time ``t`` from samples ``ts [N]`` (sorted, seconds) / ``T [N, 4, 4]``: linear in translation,
    slerp in rotation between the two bracketing samples; None outside ``[ts[0], ts[-1]]`` or across a gap longer
    than ``max_gap_s``."""
    if len(ts) == 0 or t < ts[0] or t > ts[-1]:
        return None
    j1 = int(np.searchsorted(ts, t, side="left"))
    if ts[j1] == t:
        return T[j1].copy()
    j0 = j1 - 1
    gap = ts[j1] - ts[j0]
    if gap > max_gap_s:
        return None
    a = (t - ts[j0]) / gap
    from scipy.spatial.transform import Rotation  # here: importing scipy.spatial takes ~0.2 s

    r0 = Rotation.from_matrix(T[j0, :3, :3])
    r1 = Rotation.from_matrix(T[j1, :3, :3])
    out = np.eye(4)
    out[:3, :3] = (r0 * Rotation.from_rotvec(a * (r0.inv() * r1).as_rotvec())).as_matrix()
    out[:3, 3] = (1.0 - a) * T[j0, :3, 3] + a * T[j1, :3, 3]
    return out
