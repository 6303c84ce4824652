"""Phantom-surface share: how much of a mesh's area no depth measurement supports. Needs no ground truth.

A reconstruction can invent surfaces: a neural map extrapolates into space no ray reached, a wrong pose
smears a wall, marching cubes closes a hole. None of that shows in completion, and without a GT mesh
(an iPhone capture) accuracy cannot be measured at all. The phantom share can: draw ``n_samples``
area-uniform points on the mesh and count those farther than ``threshold_m`` from every observed depth
point (the capture's depth back-projected with the poses the mesh was built with)::

    share = #{x in samples : min_p ||x - p|| > threshold_m} / n_samples
    phantom_area_m2 = share * area_m2

The observed points must be in the mesh's frame: the *estimated* poses for a SLAM mesh (it lives in the
estimate's frame), the reference poses for a mesh mapped with them. Depth is subsampled every
``stride_px`` pixels and merged into ``voxel_m`` voxels (centroids) to bound memory, which moves a point by
at most ``voxel_m * sqrt(3) / 2``: keep ``voxel_m`` well below ``threshold_m``. The observed points are
as far apart as one depth pixel's footprint times the stride (``depth * stride_px / fx``: 1.9 cm at 4 m
for 256 x 192 LiDAR depth); where that nears ``threshold_m`` (tiny test images, far walls) real surface
between points counts as phantom, so the share is an upper bound there.

Example::

    >>> import numpy as np, trimesh
    >>> plane = trimesh.creation.box(extents=(1.0, 1.0, 0.001))
    >>> pts = np.stack(np.meshgrid(np.linspace(-.5, .5, 41), np.linspace(-.5, .5, 41), [0.0]), -1).reshape(-1, 3)
    >>> phantom_share(plane, pts, n_samples=2000).share < 0.01
    True
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from ..errors import ShapeError, ValidationError
from ..geometry import backproject_depth
from ..map.morton import unique_rows
from ..trajectory import Trajectory
from .mesh import sample_surface

__all__ = [
    "PhantomResult",
    "phantom_share",
    "observed_points_from_frames",
    "phantom_for_capture",
    "auto_stride_px",
]


@dataclass(frozen=True)
class PhantomResult:
    """Share of a mesh's area farther than ``threshold_m`` from every observed depth point.

    Attributes:
        share: phantom fraction of the area, in [0, 1].
        area_m2: the mesh's total area, square metres.
        phantom_area_m2: ``share * area_m2``.
        n_samples: surface samples drawn.
        threshold_m: distance beyond which a sample is unsupported, metres.
        n_observed_points: observed depth points compared against (after voxel merging).
        n_views: frames whose depth was used (``None`` when the caller passed points directly).
        poses: which poses placed the depth: ``"estimate"``, ``"reference"`` or ``""`` (unknown).
    """

    share: float
    area_m2: float
    phantom_area_m2: float
    n_samples: int
    threshold_m: float
    n_observed_points: int = 0
    n_views: int | None = None
    poses: str = ""


def phantom_share(mesh: trimesh.Trimesh, observed_points: np.ndarray, threshold_m: float = 0.05,
                  n_samples: int = 200_000, seed: int = 0) -> PhantomResult:
    """Phantom-surface share of ``mesh`` against ``observed_points`` (module docstring).

    Args:
        mesh: triangle mesh, metres, in the frame of ``observed_points``.
        observed_points: ``[N, 3]`` observed depth points, metres (:func:`observed_points_from_frames`).
        threshold_m: a sample farther than this from every point is phantom (default 5 cm).
        n_samples: area-uniform surface samples.
        seed: sampling seed.

    Raises:
        ValidationError: a mesh without area, no observed point, or a bad threshold / sample count.
    """
    pts = np.asarray(observed_points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ShapeError("observed_points", pts.shape, "[N, 3]")
    if len(pts) == 0:
        raise ValidationError("observed_points", "no observed depth point: check the poses and the depth")
    if not threshold_m > 0:
        raise ValidationError("threshold_m", f"must be > 0 metres, got {threshold_m}")
    if n_samples < 1:
        raise ValidationError("n_samples", f"must be >= 1, got {n_samples}")
    samples = sample_surface(mesh, n_samples, seed=seed)
    d, _ = cKDTree(pts).query(samples, distance_upper_bound=threshold_m, workers=-1)
    share = float(np.mean(~(d <= threshold_m)))  # inf beyond the bound
    area = float(mesh.area)
    return PhantomResult(share, area, share * area, int(n_samples), float(threshold_m), int(len(pts)))


def auto_stride_px(width: int) -> int:
    """Pixel stride for :func:`observed_points_from_frames`: about 160 columns per image (1 for 160 px or
    less, 2 for 256 px LiDAR depth, 4 for 640 px), so neighbouring points stay a few cm apart."""
    return max(1, int(width) // 160)


class _VoxelMerger:
    """Running voxel-centroid merge of point batches (sums and counts per voxel key)."""

    def __init__(self, voxel_m: float) -> None:
        self.voxel_m = voxel_m
        self.keys = np.zeros((0, 3), dtype=np.int64)
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0)
        self._pending: list[np.ndarray] = []
        self._n_pending = 0

    def add(self, pts: np.ndarray) -> None:
        self._pending.append(pts)
        self._n_pending += len(pts)
        if self._n_pending > max(1_000_000, 2 * len(self.keys)):
            self.flush()

    def flush(self) -> None:
        if not self._pending:
            return
        pts = np.concatenate(self._pending)
        self._pending, self._n_pending = [], 0
        keys = np.floor(pts / self.voxel_m).astype(np.int64)
        self._merge(np.concatenate([self.keys, keys]), np.concatenate([self.sums, pts]),
                    np.concatenate([self.counts, np.ones(len(pts))]))

    def _merge(self, keys: np.ndarray, sums: np.ndarray, counts: np.ndarray) -> None:
        uniq, inv = (t.numpy() for t in unique_rows(torch.from_numpy(keys), return_inverse=True))
        out = np.zeros((len(uniq), 3))
        for k in range(3):
            out[:, k] = np.bincount(inv, weights=sums[:, k], minlength=len(uniq))
        self.keys, self.sums = uniq, out
        self.counts = np.bincount(inv, weights=counts, minlength=len(uniq))

    def coarsen(self) -> None:
        """Double the voxel size (merging what is there)."""
        self.flush()
        self.voxel_m *= 2
        self._merge(np.floor_divide(self.keys, 2), self.sums, self.counts)

    def points(self) -> np.ndarray:
        self.flush()
        return self.sums / self.counts[:, None] if len(self.counts) else np.zeros((0, 3))


def _observed_points(pairs: Iterable[tuple[object, np.ndarray | None]], stride_px: int | None, voxel_m: float,
                     max_points: int) -> tuple[np.ndarray, int]:
    """Merge the back-projected depth of ``(frame, T_world_cam or None)`` pairs; returns (points, frames used)."""
    if not voxel_m > 0:
        raise ValidationError("voxel_m", f"must be > 0 metres, got {voxel_m}")
    if stride_px is not None and stride_px < 1:
        raise ValidationError("stride_px", f"must be >= 1, got {stride_px}")
    if max_points < 1:
        raise ValidationError("max_points", f"must be >= 1, got {max_points}")
    merger = _VoxelMerger(voxel_m)
    used = 0
    for frame, T in pairs:
        if T is None:
            continue
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4):
            raise ShapeError("poses_T_world_cam", T.shape, "[4, 4] per frame")
        stride = stride_px or auto_stride_px(frame.depth_m.shape[1])
        merger.add(backproject_depth(frame.depth_m, frame.K, T, stride=stride))
        used += 1
        if len(merger.keys) > max_points:
            merger.coarsen()
    merger.flush()
    while len(merger.keys) > max_points:
        merger.coarsen()
    return merger.points(), used


def observed_points_from_frames(frames: Iterable, poses_T_world_cam: Sequence[np.ndarray | None] | np.ndarray,
                                stride_px: int | None = None, voxel_m: float = 0.01,
                                max_points: int = 5_000_000) -> np.ndarray:
    """Back-project the frames' valid depth with the given poses and merge it into ``voxel_m`` voxels.

    Args:
        frames: ``RGBDFrame``-like objects (``depth_m`` ``[H, W]`` float32 metres, 0 = invalid; ``K`` for
            that resolution, OpenCV pinhole), read one at a time.
        poses_T_world_cam: one ``[4, 4]`` camera-to-world pose (OpenCV axes, metres) per frame, in the
            frame the points should be in; ``None`` skips that frame (e.g. tracking was lost).
        stride_px: use every ``stride_px``-th pixel in both directions (default :func:`auto_stride_px`).
        voxel_m: points in one voxel of this edge are replaced by their centroid.
        max_points: if more voxels than this remain, the voxel size is doubled until they fit.

    Returns:
        ``[M, 3]`` float64 points, world frame of the poses, metres (``M = 0`` without valid depth).

    Raises:
        ValidationError: not one pose per frame, or bad options.
    """
    poses = list(poses_T_world_cam)
    n_frames = 0

    def pairs():  # noqa: ANN202
        nonlocal n_frames
        for k, frame in enumerate(frames):
            if k >= len(poses):
                raise ValidationError("poses_T_world_cam", f"{len(poses)} poses for more frames")
            n_frames += 1
            yield frame, poses[k]

    pts, _ = _observed_points(pairs(), stride_px, voxel_m, max_points)
    if n_frames != len(poses):
        raise ValidationError("poses_T_world_cam", f"{len(poses)} poses for {n_frames} frames")
    return pts


def phantom_for_capture(mesh: trimesh.Trimesh, capture: Iterable, trajectory: Trajectory | None = None,
                        frames: int | None = None, threshold_m: float = 0.05, n_samples: int = 200_000,
                        seed: int = 0, max_views: int = 200, max_diff_s: float = 0.02,
                        stride_px: int | None = None, voxel_m: float = 0.01) -> PhantomResult:
    """:func:`phantom_share` of ``mesh`` against a capture's depth: every ``max(1, frames // max_views)``-th
    of its first ``frames`` frames, placed with ``trajectory`` (the pose nearest in time, within
    ``max_diff_s``; frames without one are skipped) or, without it, the frames' reference poses.
    ``voxfusion run`` (estimated poses) and ``voxfusion eval --capture`` share this.

    Raises:
        ValidationError: no selected frame has a pose (names where the poses were looked for).
    """
    n = len(capture) if frames is None else min(int(frames), len(capture))
    chosen = capture.frames(0, n, max(1, n // max_views))  # read one at a time
    if trajectory is None:
        pairs = ((f, f.T_world_cam) for f in chosen)
        source, where = "reference", "the capture has no reference poses; pass an estimated trajectory"
    else:
        ts = np.asarray(trajectory.timestamps_s, dtype=np.float64)
        order = np.argsort(ts, kind="stable")
        ts_sorted = ts[order]

        def pose_at(t: float) -> np.ndarray | None:
            j = int(np.searchsorted(ts_sorted, t))
            near = [i for i in (j - 1, j) if 0 <= i < len(ts_sorted)]
            if not near:
                return None
            best = min(near, key=lambda i: abs(ts_sorted[i] - t))
            return trajectory.T_world_cam[order[best]] if abs(ts_sorted[best] - t) <= max_diff_s else None

        pairs = ((f, pose_at(f.timestamp_s)) for f in chosen)
        source = "estimate"
        where = f"no trajectory timestamp is within {max_diff_s} s of a capture frame's timestamp"
    pts, n_views = _observed_points(pairs, stride_px, voxel_m, max_points=5_000_000)
    if n_views == 0:
        raise ValidationError("poses", where)
    result = phantom_share(mesh, pts, threshold_m=threshold_m, n_samples=n_samples, seed=seed)
    return replace(result, n_views=n_views, poses=source)
