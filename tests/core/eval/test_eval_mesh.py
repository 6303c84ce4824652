"""Mesh accuracy / completion / F-score on analytic spheres, GT culling, loading, and the fallback path."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import trimesh

from voxfusion.core.errors import CaptureError, ShapeError, ValidationError
from voxfusion.core.eval import (
    CameraView,
    MeshEvalConfig,
    compute_mesh_metrics,
    cull_to_views,
    evaluate_mesh_against_gt,
    load_mesh,
    point_to_surface_distance,
    sample_surface,
    views_from_capture,
    views_from_frames,
)
from voxfusion.core.geometry import make_intrinsics


def sphere(radius: float = 1.0, subdivisions: int = 3) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


CFG = MeshEvalConfig(n_samples=4000)


def test_mesh_against_itself_is_zero():
    m = sphere()
    r = compute_mesh_metrics(m, m, CFG)
    assert r.method == "exact"
    assert r.accuracy_m < 1e-4 and r.completion_m < 1e-4
    assert r.completion_ratio == 1.0 and r.precision == 1.0 and r.recall == 1.0 and r.fscore == 1.0
    assert r.n_samples == r.n_gt_samples == 4000


def test_offset_sphere_gives_the_offset():
    gt = sphere(1.0)
    r = compute_mesh_metrics(sphere(1.01), gt, CFG)
    assert r.accuracy_m == pytest.approx(0.01, abs=1e-3)
    assert r.completion_m == pytest.approx(0.01, abs=1e-3)
    assert r.completion_ratio == 1.0 and r.fscore == 1.0
    far = compute_mesh_metrics(sphere(1.10), gt, CFG)
    assert far.accuracy_m == pytest.approx(0.10, abs=2e-3)
    assert far.completion_ratio == 0.0 and far.precision == 0.0 and far.recall == 0.0 and far.fscore == 0.0
    assert compute_mesh_metrics(sphere(1.03), gt, CFG).completion_ratio == 1.0
    # A 20 cm F-score threshold accepts the 10 cm offset; the completion ratio keeps its own 5 cm.
    loose = MeshEvalConfig(n_samples=4000, threshold_m=0.2)
    r = compute_mesh_metrics(sphere(1.10), gt, loose)
    assert r.fscore == 1.0 and r.completion_ratio == 0.0 and r.threshold_m == 0.2


def faces_below(mesh: trimesh.Trimesh, z_max: float) -> trimesh.Trimesh:
    """The part of ``mesh`` whose face centroids have ``z < z_max``."""
    return mesh.submesh([np.nonzero(mesh.triangles_center[:, 2] < z_max)[0]], append=True)


def test_partial_reconstruction_lowers_completion_not_accuracy():
    gt = sphere(1.0)
    half = faces_below(gt, 0.0)
    r = compute_mesh_metrics(half, gt, CFG)
    assert r.accuracy_m < 1e-4 and r.precision == 1.0
    assert 0.4 < r.completion_ratio < 0.6
    assert r.recall == r.completion_ratio
    assert r.fscore == pytest.approx(2 * r.recall / (1 + r.recall))
    assert r.completion_m > 0.1


def test_sampled_variant_is_biased_up_for_sparse_samples():
    m = sphere()
    sparse = MeshEvalConfig(n_samples=300)
    exact = compute_mesh_metrics(m, m, sparse)
    sampled = compute_mesh_metrics(m, m, MeshEvalConfig(n_samples=300, method="sampled"))
    assert sampled.method == "sampled"
    assert sampled.accuracy_m > exact.accuracy_m + 0.01
    assert sampled.completion_m > exact.completion_m + 0.01
    # With dense samples the bias shrinks.
    dense = compute_mesh_metrics(m, m, MeshEvalConfig(n_samples=20000, method="sampled"))
    assert dense.accuracy_m < sampled.accuracy_m / 3


def test_sampling_is_seeded():
    m = sphere()
    a = sample_surface(m, 100, seed=1)
    np.testing.assert_array_equal(a, sample_surface(m, 100, seed=1))
    assert not np.array_equal(a, sample_surface(m, 100, seed=2))
    assert a.shape == (100, 3) and a.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=0.01)
    cfg = MeshEvalConfig(n_samples=500, method="sampled")
    assert compute_mesh_metrics(sphere(1.02), m, cfg) == compute_mesh_metrics(sphere(1.02), m, cfg)


def test_point_to_surface_distance_exact_and_trimesh_fallback(monkeypatch):
    m = trimesh.creation.box(extents=[2.0, 2.0, 2.0])  # faces at +-1
    far = np.array([[3.0, 0.0, 0.0], [0.0, -1.5, 0.0], [0.2, 0.3, 0.1], [2.0, 2.0, 1.0], [1e3, 0.0, 0.0]])
    expected = np.array([2.0, 0.5, 0.7, np.sqrt(2.0), 999.0])
    np.testing.assert_allclose(point_to_surface_distance(far, m), expected, rtol=1e-6, atol=1e-6)
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` now raises ImportError
    np.testing.assert_allclose(point_to_surface_distance(far, m), expected, rtol=1e-9, atol=1e-9)
    r = compute_mesh_metrics(sphere(1.01), sphere(1.0), MeshEvalConfig(n_samples=300))
    assert r.accuracy_m == pytest.approx(0.01, abs=1e-3)
    with pytest.raises(ShapeError):
        point_to_surface_distance(np.zeros((4, 2)), m)


def test_far_from_origin_keeps_precision():
    offset = np.array([5000.0, -3000.0, 200.0])  # e.g. a georeferenced scan
    gt = sphere(1.0).apply_translation(offset)
    est = sphere(1.01).apply_translation(offset)
    r = compute_mesh_metrics(est, gt, MeshEvalConfig(n_samples=2000))
    assert r.accuracy_m == pytest.approx(0.01, abs=1e-3)


# ---------------------------------------------------------------------------------------------------
# Culling: a camera 3 m in front of the unit sphere sees the cap z < -1/3 only.

W, H = 64, 48
K = make_intrinsics(40.0, 40.0, 31.5, 23.5)


def camera_at(z: float) -> np.ndarray:
    T = np.eye(4)  # OpenCV axes aligned with the world: looks along +z
    T[2, 3] = z
    return T


def render_sphere_depth(T_world_cam: np.ndarray, radius: float = 1.0) -> np.ndarray:
    """Analytic z-depth of a sphere at the origin for the camera ``T_world_cam`` (no rotation)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    c = T_world_cam[:3, 3]
    a = (d * d).sum(-1)
    b = 2 * (d @ c)
    disc = b * b - 4 * a * (c @ c - radius**2)
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    return np.where(t > 0, t, 0.0).astype(np.float32)


def test_cull_keeps_only_the_visible_cap():
    pts = sample_surface(sphere(1.0, 4), 5000, seed=0)
    T = camera_at(-3.0)
    depth = render_sphere_depth(T)
    view = CameraView(K, W, H, T, depth)
    seen = cull_to_views(pts, [view])
    # Visible cap from distance 3: z <= -1/3, 1/3 of the sphere's area; the pixels on the silhouette
    # (about 1.4 degrees wide here) have no depth, so a rim just inside the cap is lost too.
    assert np.all(pts[seen, 2] < -1 / 3 + 0.01)
    assert seen[pts[:, 2] < -0.7].all()
    assert 0.22 < seen.mean() < 1 / 3 + 0.01
    # Frustum only (no depth): the whole sphere is in the image, nothing is culled.
    assert cull_to_views(pts, [CameraView(K, W, H, T)]).all()
    # A second camera 3 m behind, looking back (x flipped, z flipped), sees the back cap; by symmetry
    # its depth map is the same image.
    T_back = camera_at(3.0)
    T_back[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    back = cull_to_views(pts, [CameraView(K, W, H, T_back, depth)])
    assert np.all(pts[back, 2] > 1 / 3 - 0.01)
    both = cull_to_views(pts, [view, CameraView(K, W, H, T_back, depth)])
    np.testing.assert_array_equal(both, seen | back)
    assert both.mean() == pytest.approx(2 * seen.mean(), abs=0.03)
    # The front camera turned around sees nothing (everything is behind it).
    T_away = camera_at(-3.0)
    T_away[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    assert not cull_to_views(pts, [CameraView(K, W, H, T_away)]).any()
    # A camera looking at the sphere from far off to the side: the sphere is outside its image.
    T_side = camera_at(-3.0)
    T_side[0, 3] = 10.0
    assert not cull_to_views(pts, [CameraView(K, W, H, T_side)]).any()


def test_invalid_depth_pixels_observe_nothing():
    pts = sample_surface(sphere(1.0), 2000, seed=0)
    T = camera_at(-3.0)
    depth = render_sphere_depth(T)
    depth[:, : W // 2] = 0.0  # left half of the image has no measurement
    seen = cull_to_views(pts, [CameraView(K, W, H, T, depth)])
    assert seen.any()
    assert np.all(pts[seen, 0] > -0.05)  # left of the image is world -x (OpenCV x right)


def test_culled_completion_ignores_unseen_gt():
    gt = sphere(1.0, 4)
    front = faces_below(gt, -0.2)
    T = camera_at(-3.0)
    views = [CameraView(K, W, H, T, render_sphere_depth(T))]
    full = compute_mesh_metrics(front, gt, CFG)
    culled = compute_mesh_metrics(front, gt, CFG, views=views)
    assert full.completion_ratio < 0.5
    assert culled.completion_ratio == 1.0
    assert culled.completion_m < 1e-4
    assert culled.n_gt_samples < 0.4 * CFG.n_samples
    assert culled.accuracy_m == pytest.approx(full.accuracy_m)  # accuracy is never culled
    away = camera_at(-3.0)
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    with pytest.raises(ValidationError, match="views"):
        compute_mesh_metrics(front, gt, CFG, views=[CameraView(K, W, H, away)])


def test_views_from_frames_uses_frames_or_given_poses():
    from voxfusion.core.datasets.frame import RGBDFrame

    T = camera_at(-3.0)
    frames = [RGBDFrame(depth_m=render_sphere_depth(T), K=K, timestamp_s=0.0, T_world_cam=T)]
    views = views_from_frames(frames)
    assert len(views) == 1 and views[0].depth_m is not None and views[0].width == W
    assert views_from_frames(frames, use_depth=False)[0].depth_m is None
    views = views_from_frames(frames, T_world_cam=[camera_at(-4.0)])
    assert views[0].T_world_cam[2, 3] == -4.0
    no_pose = [RGBDFrame(depth_m=render_sphere_depth(T), K=K, timestamp_s=0.0)]
    with pytest.raises(ValidationError):
        views_from_frames(no_pose)
    with pytest.raises(ShapeError):
        CameraView(K, W, H, T, np.zeros((H + 1, W), np.float32))


# ---------------------------------------------------------------------------------------------------
# Loading and input checks.


@pytest.mark.parametrize("ext", ["ply", "obj", "glb"])
def test_load_mesh_round_trip(tmp_path, ext):
    m = sphere(1.0, 2)
    path = tmp_path / f"mesh.{ext}"
    m.export(path)
    loaded = load_mesh(path)
    assert len(loaded.faces) == len(m.faces)
    assert loaded.area == pytest.approx(m.area, rel=1e-5)
    r = compute_mesh_metrics(path, m, MeshEvalConfig(n_samples=500))
    assert r.accuracy_m < 1e-4


def test_load_mesh_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.ply"
    with pytest.raises(CaptureError, match="nope.ply"):
        load_mesh(missing)
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    with pytest.raises(CaptureError, match="empty.ply"):
        load_mesh(empty)
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(CaptureError, match="garbage.obj"):
        load_mesh(garbage)
    points_only = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(points_only)
    with pytest.raises(CaptureError, match="points.ply"):
        load_mesh(points_only)


def test_config_and_input_validation():
    with pytest.raises(ValidationError):
        MeshEvalConfig(n_samples=0)
    with pytest.raises(ValidationError):
        MeshEvalConfig(threshold_m=0.0)
    with pytest.raises(ValidationError):
        MeshEvalConfig(method="chamfer")
    with pytest.raises(ValidationError):
        compute_mesh_metrics(trimesh.Trimesh(), sphere(), CFG)
    with pytest.raises(ValidationError):
        compute_mesh_metrics(np.zeros((3, 3)), sphere(), CFG)


def test_evaluate_mesh_against_gt_labels_whole_and_observed_gt():
    gt = sphere(1.0, 4)
    front = faces_below(gt, -0.2)  # the estimate covers only the cap the camera saw
    T = camera_at(-3.0)
    views = [CameraView(K, W, H, T, render_sphere_depth(T))]
    r = evaluate_mesh_against_gt(front, gt, views, CFG)
    assert r.full_gt.gt_part == "full" and r.observed_gt.gt_part == "observed"
    assert r.full_gt.completion_ratio < 0.5 and r.full_gt.completion_m > 0.3  # asks for the unseen back
    assert r.observed_gt.completion_ratio == 1.0 and r.observed_gt.completion_m < 1e-4
    assert r.observed_gt.accuracy_m == r.full_gt.accuracy_m  # the estimate's samples are never culled
    assert r.observed_gt.n_gt_samples < 0.4 * CFG.n_samples and r.full_gt.n_gt_samples == CFG.n_samples
    # The same figures compute_mesh_metrics gives one at a time (it runs this).
    assert compute_mesh_metrics(front, gt, CFG) == r.full_gt
    assert compute_mesh_metrics(front, gt, CFG, views=views) == r.observed_gt
    assert set(r.summary()) == {"mesh_full_gt", "mesh_observed_gt"}
    alone = evaluate_mesh_against_gt(front, gt, None, CFG)
    assert alone.observed_gt is None and set(alone.summary()) == {"mesh_full_gt"}
    assert alone.full_gt == r.full_gt
    sampled = evaluate_mesh_against_gt(front, gt, views, MeshEvalConfig(n_samples=4000, method="sampled"))
    assert sampled.observed_gt.method == "sampled" and sampled.observed_gt.gt_part == "observed"


def test_views_from_capture_skips_frames_without_poses_and_caps_the_count():
    from voxfusion.core.datasets.frame import RGBDFrame

    class Cap:
        def __init__(self, frames: list) -> None:
            self.f = frames

        def __len__(self) -> int:
            return len(self.f)

        def frames(self, start: int = 0, stop: int | None = None, step: int = 1):  # noqa: ANN201
            return iter(self.f[start:stop:step])

    T = camera_at(-3.0)
    depth = render_sphere_depth(T)
    frames = [RGBDFrame(depth_m=depth, K=K, timestamp_s=float(i), T_world_cam=T if i % 3 else None)
              for i in range(12)]
    assert len(views_from_capture(Cap(frames))) == 8
    assert len(views_from_capture(Cap(frames), frames=6)) == 4
    assert len(views_from_capture(Cap(frames), max_views=6)) == 4  # every 2nd frame: 2, 4, 8, 10 have poses
    assert views_from_capture(Cap(frames), max_views=4) == []  # every 3rd frame: 0, 3, 6, 9, none posed
