"""Multi-view depth consistency: a trajectory check that needs no ground truth.

For frame pairs ``(i, i + gap)`` the depth of frame ``i`` is back-projected with its pose, moved into
frame ``i + gap`` with that frame's pose and compared with the depth frame ``i + gap`` measured at the
same pixel. With perfect poses (and a static scene) the two agree up to sensor noise; pose errors add
disagreement that grows with their size. Per pair the statistic is the median ``|z_projected - z_measured|``
over pixels seen by both frames, after dropping differences above ``max_diff_m`` (occlusions, moving
objects); the result is the mean over pairs, per gap.

It is how a trajectory is judged on captures whose only reference is itself an estimate (ARKit poses on
an iPhone capture): the lower of two trajectories is the more self-consistent with the depth.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ValidationError
from ..geometry import backproject_depth, invert_pose

__all__ = ["DepthConsistency", "depth_consistency", "pair_disagreement"]


@dataclass(frozen=True)
class DepthConsistency:
    """Mean over pairs of the per-pair median depth disagreement (metres), per frame gap."""

    gaps: tuple[int, ...]
    disagreement_m: tuple[float, ...]
    """``nan`` for a gap where no pair had enough overlap."""
    pairs: tuple[int, ...]
    """Pairs that had enough overlap, per gap."""

    def as_dict(self) -> dict[str, float]:
        """``{"gap_15_cm": 0.94, ...}`` for reports."""
        return {f"gap_{g}_cm": round(d * 100, 3) for g, d in zip(self.gaps, self.disagreement_m, strict=True)}


def pair_disagreement(depth_i: np.ndarray, K_i: np.ndarray, T_i: np.ndarray, depth_j: np.ndarray,
                      K_j: np.ndarray, T_j: np.ndarray, max_diff_m: float = 0.5, min_pixels: int = 100,
                      stride: int = 2) -> float:
    """Median ``|z_projected - z_measured|`` (metres) of frame ``i``'s depth seen from frame ``j``.

    ``depth_*`` are ``[H, W]`` metres (0 = invalid), ``K_*`` ``[3, 3]``, ``T_*`` ``[4, 4]`` camera-to-world.
    Returns ``nan`` when fewer than ``min_pixels`` pixels overlap within ``max_diff_m``.
    """
    pts = backproject_depth(depth_i, K_i, invert_pose(T_j) @ T_i, stride=stride)  # in camera j
    z = pts[:, 2]
    front = z > 1e-3
    pts, z = pts[front], z[front]
    u = np.round(pts[:, 0] / z * K_j[0, 0] + K_j[0, 2]).astype(np.int64)
    v = np.round(pts[:, 1] / z * K_j[1, 1] + K_j[1, 2]).astype(np.int64)
    h, w = depth_j.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    measured = depth_j[v[inside], u[inside]]
    diff = np.abs(measured - z[inside])[measured > 0]
    diff = diff[diff < max_diff_m]
    return float(np.median(diff)) if diff.size >= min_pixels else float("nan")


def depth_consistency(load_frame: Callable[[int], tuple[np.ndarray, np.ndarray]], poses: np.ndarray,
                      gaps: Sequence[int] = (15, 60, 240), every: int = 20,
                      max_diff_m: float = 0.5) -> DepthConsistency:
    """Depth consistency of ``poses`` (``[N, 4, 4]`` camera-to-world, one per frame).

    ``load_frame(i)`` returns frame ``i``'s ``(depth_m [H, W], K [3, 3])``; it is called for both frames of
    every pair, so pass a cached loader (``functools.cache``) where reading a frame is slow. Pairs start
    every ``every``-th frame.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValidationError("poses", f"expected [N, 4, 4], got {poses.shape}")
    if every < 1 or any(g < 1 for g in gaps):
        raise ValidationError("gaps", "gaps and every must be >= 1")
    n = len(poses)
    means, counts = [], []
    for gap in gaps:
        vals = []
        for i in range(0, n - gap, every):
            (di, Ki), (dj, Kj) = load_frame(i), load_frame(i + gap)
            vals.append(pair_disagreement(di, Ki, poses[i], dj, Kj, poses[i + gap], max_diff_m))
        ok = [x for x in vals if np.isfinite(x)]
        means.append(float(np.mean(ok)) if ok else float("nan"))
        counts.append(len(ok))
    return DepthConsistency(tuple(gaps), tuple(means), tuple(counts))
