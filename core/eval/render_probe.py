"""Render-back probe: does the map render what it was shown?

Map a frame, render its depth at its own pose and compare with the depth it was given: the median
``|rendered - observed|`` over pixels valid in both. A clean map of one frame gives a few millimetres; a
phantom surface in front of the real one (e.g. from voxels that depth outliers allocated in free space)
gives tens of centimetres. Plus the perturbations the robustness tests and ``bench/bench_outliers.py`` use:
random near-range depth outliers, and re-anchoring a capture's world frame so that its first camera is
axis-aligned or rotated about an oblique axis.

Example::

    frame = add_depth_outliers(capture[0], fraction=0.02, seed=0)
    probe = depth_probe(rendered_depth_m, frame.depth_m)
    print(probe.median_abs_m)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..datasets.frame import RGBDFrame
from ..errors import ShapeError, ValidationError

__all__ = ["DepthProbe", "depth_probe", "add_depth_outliers", "oblique_rotation", "anchor_first_pose"]


@dataclass(frozen=True)
class DepthProbe:
    """Agreement of a rendered depth map with the observed one.

    Attributes:
        median_abs_m: median ``|rendered - observed|`` over pixels valid in both, metres (NaN if none).
        mean_abs_m: the mean of the same, metres.
        n_pixels: pixels valid in both.
        rendered_fraction: fraction of the observed-valid pixels that rendered a surface.
    """

    median_abs_m: float
    mean_abs_m: float
    n_pixels: int
    rendered_fraction: float


def _as_2d(x: object, field: str) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor (any device)
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2:
        raise ShapeError(field, a.shape, "[H, W]")
    return a


def depth_probe(rendered_m: object, observed_m: object) -> DepthProbe:
    """Compare ``rendered_m [H, W]`` with ``observed_m [H, W]`` (metres, 0 = none / invalid; numpy or torch)."""
    r = _as_2d(rendered_m, "rendered_m")
    o = _as_2d(observed_m, "observed_m")
    if r.shape != o.shape:
        raise ShapeError("rendered_m", r.shape, f"{o.shape} (the observed depth's shape)")
    obs = np.isfinite(o) & (o > 0)
    both = obs & np.isfinite(r) & (r > 0)
    n = int(both.sum())
    err = np.abs(r[both] - o[both])
    return DepthProbe(median_abs_m=float(np.median(err)) if n else float("nan"),
                      mean_abs_m=float(err.mean()) if n else float("nan"), n_pixels=n,
                      rendered_fraction=n / max(int(obs.sum()), 1))


def add_depth_outliers(frame: RGBDFrame, fraction: float, seed: int = 0, min_m: float = 0.3,
                       max_m: float = 1.0) -> RGBDFrame:
    """Set ``fraction`` of the frame's pixels (drawn uniformly, valid or not) to depths uniform in
    ``[min_m, max_m]`` metres: isolated near-range outliers like speckle and flying pixels.

    Deterministic in ``seed``; ``fraction`` 0 returns the frame unchanged.
    """
    if not 0 <= fraction <= 1:
        raise ValidationError("fraction", f"must be in [0, 1], got {fraction}")
    if not 0 < min_m < max_m:
        raise ValidationError("min_m", f"need 0 < min_m < max_m, got {min_m}, {max_m}")
    if fraction == 0:
        return frame
    rng = np.random.default_rng(seed)
    depth = frame.depth_m.copy()
    n = int(round(fraction * depth.size))
    flat = rng.choice(depth.size, size=n, replace=False)
    depth.reshape(-1)[flat] = rng.uniform(min_m, max_m, n).astype(np.float32)
    return frame.with_(depth_m=depth)


def oblique_rotation(angle_deg: float, axis: tuple[float, float, float] = (1.0, 2.0, 3.0)) -> np.ndarray:
    """``[4, 4]`` rigid transform rotating by ``angle_deg`` about ``axis`` (through the origin; Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    norm = float(np.linalg.norm(a))
    if a.shape != (3,) or not np.isfinite(norm) or norm == 0:
        raise ValidationError("axis", f"must be a non-zero 3-vector, got {axis!r}")
    k = a / norm
    th = np.deg2rad(angle_deg)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(th) * kx + (1.0 - np.cos(th)) * (kx @ kx)
    return T


def anchor_first_pose(frames: list[RGBDFrame], T_world_first: np.ndarray) -> list[RGBDFrame]:
    """Re-express ``frames``' reference poses in the world frame where the first camera is at ``T_world_first``.

    Every reference pose becomes ``G @ T_world_cam`` with ``G = T_world_first @ inv(T_first)`` (a change of
    world frame; the relative motion is unchanged), and the first frame gets ``T_world_first`` even without
    a reference pose. When the first frame has no reference pose, the others lose theirs (they lived in a
    frame we cannot relate). Device poses are left alone (only their relative motion is ever used).
    """
    T_new = np.asarray(T_world_first, dtype=np.float64)
    if T_new.shape != (4, 4):
        raise ShapeError("T_world_first", T_new.shape, "(4, 4)")
    if not frames:
        return []
    T0 = frames[0].T_world_cam
    G = None if T0 is None else T_new @ np.linalg.inv(T0)
    out = [frames[0].with_(T_world_cam=T_new.copy())]
    for f in frames[1:]:
        T = None if G is None or f.T_world_cam is None else G @ f.T_world_cam
        out.append(f.with_(T_world_cam=T))
    return out
