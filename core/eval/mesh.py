"""Mesh accuracy, completion, completion ratio and F-score against a ground-truth mesh.

Two methods, both from ``n_samples`` area-uniform random points per mesh (seeded):

* ``"exact"`` (default): the distance of each sample to the *other mesh's surface* (exact
  point-to-triangle distance through a BVH: Open3D's ``RaycastingScene.compute_distance``, or
  ``trimesh.proximity.closest_point`` when Open3D is not installed). The sample density sets no error
  floor: a mesh against itself scores ~0.
* ``"sampled"``: the distance of each sample to the nearest *sample* of the other mesh (scipy
  ``cKDTree``), the variant NICE-SLAM, Vox-Fusion and most neural-SLAM papers report (they use 200k
  samples per mesh and quote centimetres). It is biased upwards by the sample spacing; use it only to
  compare with those tables.

Metrics (``d(x, S)``: distance from point ``x`` to surface / sample set ``S``):

* accuracy_m: mean over estimate samples of ``d(x, GT)``.
* completion_m: mean over GT samples of ``d(y, estimate)``.
* completion_ratio: fraction of GT samples with ``d(y, estimate) < completion_ratio_threshold_m`` (5 cm).
* precision / recall: fraction of estimate (GT) samples closer than ``threshold_m`` to the other mesh;
  fscore = ``2 P R / (P + R)`` (0 when both are 0).

Optional culling restricts the GT samples to what the cameras observed (see :func:`cull_to_views`);
the estimate's samples are never culled, and accuracy is always measured against the whole GT (its
surface, or all its samples for ``"sampled"``). Every :class:`MeshMetrics` says which GT it was measured
against (``gt_part``: ``"full"`` or ``"observed"``), and :func:`evaluate_mesh_against_gt` gives both from one
set of samples: the one code path ``voxfusion run``, ``voxfusion map`` and ``voxfusion eval`` share, so the
same mesh, GT and views give the same numbers everywhere. Completion against the whole GT asks for
surfaces no camera saw; quote the observed-GT numbers unless the capture covers the whole scene.

Example::

    >>> import trimesh
    >>> gt = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    >>> m = compute_mesh_metrics(gt, gt, MeshEvalConfig(n_samples=2000))
    >>> m.accuracy_m < 1e-4 and m.fscore == 1.0
    True
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ..errors import CaptureError, ShapeError, ValidationError
from ..geometry import check_intrinsics, check_rigid, invert_pose

__all__ = [
    "MeshMethod",
    "MeshEvalConfig",
    "MeshMetrics",
    "CameraView",
    "views_from_frames",
    "load_mesh",
    "sample_surface",
    "point_to_surface_distance",
    "cull_to_views",
    "compute_mesh_metrics",
    "GTPart",
    "MeshGTEvaluation",
    "evaluate_mesh_against_gt",
    "views_from_capture",
]

MeshMethod = Literal["exact", "sampled"]
GTPart = Literal["full", "observed"]


@dataclass(frozen=True)
class MeshEvalConfig:
    """Options of the mesh metrics."""

    n_samples: int = 200_000
    """Points sampled (area-uniform) on each mesh."""
    threshold_m: float = 0.05
    """Distance threshold of precision / recall / F-score, metres."""
    completion_ratio_threshold_m: float = 0.05
    """Distance threshold of the completion ratio, metres (the papers' 5 cm)."""
    seed: int = 0
    """Seed of the surface sampling (estimate and GT use different streams derived from it)."""
    method: MeshMethod = "exact"
    """``"exact"`` point-to-surface distances or the papers' ``"sampled"`` sample-to-sample variant."""

    def __post_init__(self) -> None:
        if self.n_samples < 1:
            raise ValidationError("n_samples", f"must be >= 1, got {self.n_samples}")
        if not self.threshold_m > 0:
            raise ValidationError("threshold_m", f"must be > 0 metres, got {self.threshold_m}")
        if not self.completion_ratio_threshold_m > 0:
            raise ValidationError("completion_ratio_threshold_m",
                                  f"must be > 0 metres, got {self.completion_ratio_threshold_m}")
        if self.method not in ("exact", "sampled"):
            raise ValidationError("method", f"must be 'exact' or 'sampled', got {self.method!r}")


@dataclass(frozen=True)
class MeshMetrics:
    """Reconstruction quality of an estimated mesh against a GT mesh (distances in metres).

    Attributes:
        accuracy_m, completion_m: mean distances (module docstring).
        completion_ratio, precision, recall, fscore: fractions in [0, 1].
        threshold_m: the precision / recall threshold used.
        n_samples: samples drawn per mesh.
        n_gt_samples: GT samples evaluated (fewer than ``n_samples`` after culling).
        method: ``"exact"`` or ``"sampled"``.
        gt_part: ``"full"`` (completion / recall against the whole GT) or ``"observed"`` (against the
            GT culled to what the cameras saw).
    """

    accuracy_m: float
    completion_m: float
    completion_ratio: float
    precision: float
    recall: float
    fscore: float
    threshold_m: float
    n_samples: int
    n_gt_samples: int
    method: str
    gt_part: GTPart = "full"


@dataclass(frozen=True)
class MeshGTEvaluation:
    """One mesh against one GT, both ways (from the same samples, so the figures are comparable).

    Attributes:
        full_gt: completion / recall against the whole GT mesh (``gt_part == "full"``).
        observed_gt: against the GT culled to what the views observed (``gt_part == "observed"``), or
            ``None`` when no views were given. Accuracy and precision are the same in both.
    """

    full_gt: MeshMetrics
    observed_gt: MeshMetrics | None = None

    def summary(self) -> dict[str, MeshMetrics]:
        """``{"mesh_full_gt": ..., "mesh_observed_gt": ...}`` (the second only with views): the keys
        ``metrics.json`` and ``eval.json`` use."""
        out = {"mesh_full_gt": self.full_gt}
        if self.observed_gt is not None:
            out["mesh_observed_gt"] = self.observed_gt
        return out


@dataclass(frozen=True, eq=False)
class CameraView:
    """One camera observation used to cull the GT.

    Attributes:
        K: ``[3, 3]`` intrinsics for a ``width`` x ``height`` image (pixels).
        width, height: image size, pixels.
        T_world_cam: ``[4, 4]`` camera-to-world pose, OpenCV axes, metres.
        depth_m: ``[height, width]`` observed depth in metres (0 = invalid), or ``None`` for a
            frustum-only test.
    """

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray
    depth_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", check_intrinsics(self.K, self.width, self.height, "K"))
        object.__setattr__(self, "T_world_cam", check_rigid(self.T_world_cam, "T_world_cam"))
        if self.depth_m is not None and np.shape(self.depth_m) != (self.height, self.width):
            raise ShapeError("depth_m", np.shape(self.depth_m), f"({self.height}, {self.width})")


def views_from_frames(frames: Iterable, use_depth: bool = True,
                      T_world_cam: Sequence[np.ndarray] | np.ndarray | None = None) -> list[CameraView]:
    """Build culling views from ``RGBDFrame``-like objects (``depth_m``, ``K``, ``T_world_cam``).

    Args:
        frames: e.g. ``capture.frames(step=10)``.
        use_depth: keep each frame's depth map for the depth test (else frustum only).
        T_world_cam: ``[N, 4, 4]`` poses to use instead of the frames' reference poses (e.g. the
            estimated trajectory).
    """
    views = []
    for k, f in enumerate(frames):
        T = f.T_world_cam if T_world_cam is None else T_world_cam[k]
        if T is None:
            raise ValidationError("T_world_cam", f"frame {getattr(f, 'index', k)} has no pose to cull with")
        h, w = f.depth_m.shape
        views.append(CameraView(f.K, w, h, T, f.depth_m if use_depth else None))
    return views


def views_from_capture(capture: Iterable, frames: int | None = None, max_views: int = 200) -> list[CameraView]:
    """Culling views from a capture's reference poses: every ``max(1, frames // max_views)``-th of its
    first ``frames`` frames (all by default), with their depth maps; frames without a reference pose are
    skipped (``[]`` when none has one). ``voxfusion run`` and ``voxfusion eval --capture`` both cull with
    this, so they cull the same way.

    Args:
        capture: a ``Capture`` (``len`` and ``frames(start, stop, step)``).
        frames: how many of its first frames were used (e.g. the run's ``--max-frames``).
        max_views: at most about this many views (cost is ``O(GT samples x views)``).
    """
    if max_views < 1:
        raise ValidationError("max_views", f"must be >= 1, got {max_views}")
    n = len(capture) if frames is None else min(int(frames), len(capture))
    chosen = [f for f in capture.frames(0, n, max(1, n // max_views)) if f.T_world_cam is not None]
    return views_from_frames(chosen)


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Load a triangle mesh (PLY, OBJ, GLB, ...) through trimesh; scenes are concatenated.

    Raises:
        CaptureError: the file is missing, unreadable, or holds no triangles (names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(path, "mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        raise CaptureError(path, f"cannot read mesh: {e}") from e
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise CaptureError(path, "mesh has no triangles")
    return loaded


def _check_mesh(mesh: trimesh.Trimesh, field: str) -> trimesh.Trimesh:
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValidationError(field, f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise ValidationError(field, "mesh has no triangles with area")
    return mesh


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """``[n, 3]`` float64 points drawn area-uniformly on ``mesh`` (deterministic for a seed / generator)."""
    pts, _ = trimesh.sample.sample_surface(_check_mesh(mesh, "mesh"), int(n), seed=seed)
    return np.asarray(pts, dtype=np.float64)


def point_to_surface_distance(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Exact unsigned distance from each point ``[N, 3]`` to the surface of ``mesh``, ``[N]`` metres.

    Uses Open3D's BVH (``RaycastingScene.compute_distance``, float32 inside: ~1e-7 relative precision)
    and falls back to ``trimesh.proximity.closest_point`` (float64, slower) if Open3D is missing.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError("points", points.shape, "[N, 3]")
    mesh = _check_mesh(mesh, "mesh")
    try:
        import open3d as o3d
    except ImportError:
        _, dist, _ = trimesh.proximity.closest_point(mesh, points)
        return np.asarray(dist, dtype=np.float64)
    # Distances are computed about the mesh's centre so float32 keeps precision far from the origin.
    centre = np.asarray(mesh.bounds, dtype=np.float64).mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((np.asarray(mesh.vertices) - centre).astype(np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces).astype(np.uint32)),
    )
    query = o3d.core.Tensor((points - centre).astype(np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def cull_to_views(points: np.ndarray, views: Iterable[CameraView], depth_abs_tol_m: float = 0.05,
                  depth_rel_tol: float = 0.03) -> np.ndarray:
    """Which world points ``[N, 3]`` some camera observed; returns an ``[N]`` bool mask.

    A point ``p`` counts as observed by a view when, with ``p_c = inv(T_world_cam) p`` (OpenCV camera
    frame) and ``(u, v) = (fx x/z + cx, fy y/z + cy)``:

    1. ``z > 0`` (in front of the camera);
    2. the pixel containing it, ``(round(u), round(v))`` (pixel centres at integer coordinates), lies
       inside the image: ``0 <= round(u) < width`` and ``0 <= round(v) < height``;
    3. depth test, only when the view has a depth map: that pixel's observed depth ``d`` is valid
       (``d > 0``; pixels without a measurement observe nothing) and ``z <= d + max(depth_abs_tol_m,
       depth_rel_tol * d)``, i.e. the point lies in front of or at the observed surface, within the
       tolerance. Points further behind the observed surface are occluded.

    The mask is the OR over all views. Cost ``O(N x views)``; pass every k-th frame for long captures.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError("points", points.shape, "[N, 3]")
    seen = np.zeros(len(points), dtype=bool)
    for view in views:
        T_cam_world = invert_pose(view.T_world_cam)
        pc = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        z = pc[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        K = view.K
        u = np.floor(K[0, 0] * pc[:, 0] / zs + K[0, 2] + 0.5)
        v = np.floor(K[1, 1] * pc[:, 1] / zs + K[1, 2] + 0.5)
        ok = front & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
        if view.depth_m is not None:
            idx = np.nonzero(ok)[0]
            d = np.asarray(view.depth_m, dtype=np.float64)[v[idx].astype(np.int64), u[idx].astype(np.int64)]
            tol = np.maximum(depth_abs_tol_m, depth_rel_tol * d)
            ok_depth = (d > 0) & (z[idx] <= d + tol)
            ok[:] = False
            ok[idx[ok_depth]] = True
        seen |= ok
    return seen


def _fractions(d_est: np.ndarray, d_gt: np.ndarray, config: MeshEvalConfig, n_samples: int,
               gt_part: GTPart) -> MeshMetrics:
    precision = float(np.mean(d_est < config.threshold_m))
    recall = float(np.mean(d_gt < config.threshold_m))
    fscore = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return MeshMetrics(
        accuracy_m=float(np.mean(d_est)),
        completion_m=float(np.mean(d_gt)),
        completion_ratio=float(np.mean(d_gt < config.completion_ratio_threshold_m)),
        precision=precision,
        recall=recall,
        fscore=float(fscore),
        threshold_m=config.threshold_m,
        n_samples=n_samples,
        n_gt_samples=int(len(d_gt)),
        method=config.method,
        gt_part=gt_part,
    )


def evaluate_mesh_against_gt(est: trimesh.Trimesh | str | Path, gt: trimesh.Trimesh | str | Path,
                             views: Iterable[CameraView] | None = None,
                             config: MeshEvalConfig | None = None) -> MeshGTEvaluation:
    """Accuracy, completion, completion ratio and precision / recall / F-score of ``est`` against the
    whole ``gt`` and (with ``views``) against the part of ``gt`` the views observed.

    Args:
        est: estimated mesh (a ``trimesh.Trimesh`` or a path for :func:`load_mesh`), in the GT's frame, metres.
        gt: ground-truth mesh.
        views: cameras that observed the scene (:func:`views_from_capture`); ``None``: whole GT only.
        config: sample count, thresholds, seed and method (``"exact"`` or ``"sampled"``).

    Raises:
        ValidationError: a mesh without triangles, or views that observe no GT sample.

    Example::

        >>> import trimesh
        >>> gt = trimesh.creation.icosphere(subdivisions=3)
        >>> r = evaluate_mesh_against_gt(gt, gt, config=MeshEvalConfig(n_samples=500))
        >>> r.full_gt.gt_part, r.observed_gt is None
        ('full', True)
    """
    config = config or MeshEvalConfig()
    est_mesh = load_mesh(est) if isinstance(est, str | Path) else _check_mesh(est, "estimate mesh")
    gt_mesh = load_mesh(gt) if isinstance(gt, str | Path) else _check_mesh(gt, "GT mesh")
    seeds = np.random.SeedSequence(config.seed).spawn(2)
    p_est = sample_surface(est_mesh, config.n_samples, seed=np.random.default_rng(seeds[0]))
    p_gt = sample_surface(gt_mesh, config.n_samples, seed=np.random.default_rng(seeds[1]))
    seen = None
    if views is not None:
        seen = cull_to_views(p_gt, views)
        if not seen.any():
            raise ValidationError("views", "no GT sample is observed by any view; check poses and intrinsics")
    if config.method == "exact":
        d_est = point_to_surface_distance(p_est, gt_mesh)
        d_gt = point_to_surface_distance(p_gt, est_mesh)
    else:
        d_est, _ = cKDTree(p_gt).query(p_est, workers=-1)
        d_gt, _ = cKDTree(p_est).query(p_gt, workers=-1)
    d_est, d_gt = np.asarray(d_est), np.asarray(d_gt)
    full = _fractions(d_est, d_gt, config, config.n_samples, "full")
    observed = None if seen is None else _fractions(d_est, d_gt[seen], config, config.n_samples, "observed")
    return MeshGTEvaluation(full, observed)


def compute_mesh_metrics(est: trimesh.Trimesh | str | Path, gt: trimesh.Trimesh | str | Path,
                         config: MeshEvalConfig | None = None,
                         views: Iterable[CameraView] | None = None) -> MeshMetrics:
    """Accuracy, completion, completion ratio and precision / recall / F-score of ``est`` against ``gt``:
    :func:`evaluate_mesh_against_gt`'s whole-GT figures, or its observed-GT figures when ``views`` are given
    (``gt_part`` says which).

    Args:
        est: estimated mesh (a ``trimesh.Trimesh`` or a path for :func:`load_mesh`), world frame, metres.
        gt: ground-truth mesh, same frame.
        config: sample count, thresholds, seed and method (``"exact"`` or ``"sampled"``).
        views: if given, GT samples not observed by any view are dropped (:func:`cull_to_views`).

    Raises:
        ValidationError: a mesh without triangles, or culling that leaves no GT sample.
    """
    r = evaluate_mesh_against_gt(est, gt, views, config)
    return r.full_gt if r.observed_gt is None else r.observed_gt
