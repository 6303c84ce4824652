"""Phantom-surface share: analytic plane + unobserved box, back-projection, and capture / trajectory poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.eval import observed_points_from_frames, phantom_for_capture, phantom_share
from voxfusion.core.geometry import make_intrinsics
from voxfusion.core.trajectory import Trajectory


def plane(size_m: float = 2.0, z: float = 0.0) -> trimesh.Trimesh:
    """A ``size_m`` square in the plane ``z`` (two triangles)."""
    h = size_m / 2
    v = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
    return trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


def grid_points(size_m: float = 2.0, spacing_m: float = 0.02, z: float = 0.0) -> np.ndarray:
    a = np.arange(-size_m / 2, size_m / 2 + 1e-9, spacing_m)
    x, y = np.meshgrid(a, a)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def test_observed_plane_has_no_phantom_and_an_unobserved_box_is_its_area_share():
    floor, pts = plane(), grid_points()
    r = phantom_share(floor, pts, n_samples=5000)
    assert r.share < 0.002 and r.area_m2 == pytest.approx(4.0)
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    box.apply_translation([0.0, 0.0, 1.0])  # 0.75 m above the observed floor: nothing observed it
    mesh = trimesh.util.concatenate([floor, box])
    r = phantom_share(mesh, pts, threshold_m=0.05, n_samples=20000, seed=1)
    expected = 1.5 / 5.5  # box area / total area
    assert r.share == pytest.approx(expected, abs=0.015)
    assert r.phantom_area_m2 == pytest.approx(1.5, abs=0.08)
    assert r.area_m2 == pytest.approx(5.5) and r.n_samples == 20000 and r.threshold_m == 0.05
    assert r.n_observed_points == len(pts)
    # The box's nearest face is 0.75 m off the floor: a 1 m threshold accepts all of it.
    assert phantom_share(mesh, pts, threshold_m=1.6, n_samples=2000).share == 0.0
    # Only half the floor observed: half of its area (and all of the box) is phantom.
    half = pts[pts[:, 0] < 0]
    r = phantom_share(mesh, half, n_samples=20000)
    assert r.share == pytest.approx((1.5 + 2.0) / 5.5, abs=0.02)


def test_phantom_share_rejects_bad_input():
    with pytest.raises(ValidationError, match="no observed depth point"):
        phantom_share(plane(), np.zeros((0, 3)))
    with pytest.raises(ShapeError):
        phantom_share(plane(), np.zeros((5, 2)))
    with pytest.raises(ValidationError):
        phantom_share(plane(), grid_points(), threshold_m=0.0)


W, H = 48, 36
K = make_intrinsics(30.0, 30.0, 23.5, 17.5)


def camera(x: float = 0.0, z: float = -2.0) -> np.ndarray:
    T = np.eye(4)  # OpenCV axes = world axes: looks along +z at the plane z = 0
    T[0, 3], T[2, 3] = x, z
    return T


def plane_frame(T_world_cam: np.ndarray, t_s: float, index: int = 0) -> RGBDFrame:
    depth = np.full((H, W), -T_world_cam[2, 3], dtype=np.float32)  # fronto-parallel plane at world z = 0
    depth[:, :4] = 0.0  # a few invalid pixels
    return RGBDFrame(depth_m=depth, K=K, timestamp_s=t_s, T_world_cam=T_world_cam, index=index)


def test_observed_points_back_project_with_the_given_poses_and_merge_voxels():
    frames = [plane_frame(camera(0.0), 0.0), plane_frame(camera(0.3), 0.1)]
    pts = observed_points_from_frames(frames, [f.T_world_cam for f in frames], stride_px=1, voxel_m=0.01)
    assert np.allclose(pts[:, 2], 0.0, atol=1e-9)  # on the plane
    # Frame 0 sees x in [(4 - 23.5) / 30 * 2, (47 - 23.5) / 30 * 2] = [-1.3, 1.567]; frame 1 is 0.3 m right.
    assert pts[:, 0].min() == pytest.approx(-1.3, abs=0.011) and pts[:, 0].max() == pytest.approx(1.867, abs=0.011)
    assert len(pts) == 2 * (W - 4) * H  # 6.7 cm pixel footprint, 1 cm voxels: nothing merged
    merged = observed_points_from_frames(frames, [f.T_world_cam for f in frames], stride_px=1, voxel_m=0.5)
    assert len(merged) <= 8 * 6  # at most one centroid per 0.5 m cell of the 3.17 x 2.33 m seen
    assert np.allclose(merged[:, 2], 0.0, atol=1e-9) and merged[:, 0].min() > -1.3 - 1e-9
    assert len(observed_points_from_frames(frames, [f.T_world_cam for f in frames], stride_px=2)) == 2 * 22 * 18
    coarse = observed_points_from_frames(frames, [f.T_world_cam for f in frames], stride_px=1, voxel_m=0.01,
                                         max_points=200)
    assert 0 < len(coarse) <= 200
    # A None pose skips its frame; the other frame's points only.
    one = observed_points_from_frames(frames, [None, frames[1].T_world_cam], stride_px=1)
    assert one[:, 0].min() == pytest.approx(-1.0, abs=0.011)
    with pytest.raises(ValidationError, match="poses"):
        observed_points_from_frames(frames, [camera()], stride_px=1)
    with pytest.raises(ValidationError, match="poses"):
        observed_points_from_frames(frames[:1], [camera(), camera()], stride_px=1)


class ListCapture:
    """Just enough of the Capture interface (``len``, ``frames``, ``gt_mesh_path``)."""

    def __init__(self, frames: list[RGBDFrame]) -> None:
        self._frames = frames
        self.gt_mesh_path = None

    def __len__(self) -> int:
        return len(self._frames)

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1):  # noqa: ANN201
        yield from self._frames[start:stop:step]


def test_phantom_for_capture_uses_the_trajectory_or_the_reference_poses():
    frames = [plane_frame(camera(0.1 * i), 0.1 * i, i) for i in range(4)]
    cap = ListCapture(frames)
    seen = plane(2.0)
    seen.apply_translation([0.3, 0.0, 0.0])  # inside what the cameras saw: x in [-1.3, 1.87]
    r = phantom_for_capture(seen, cap, n_samples=4000)
    assert r.share < 0.01 and r.n_views == 4 and r.poses == "reference"
    # The same depth placed 1 m further along z by an estimated trajectory: the plane is 1 m off it.
    shifted = np.stack([f.T_world_cam for f in frames])
    shifted[:, 2, 3] += 1.0
    traj = Trajectory(np.array([f.timestamp_s for f in frames]) + 0.001, shifted)
    r = phantom_for_capture(seen, cap, traj, n_samples=4000, max_diff_s=0.01)
    assert r.share == 1.0 and r.poses == "estimate" and r.n_views == 4
    # Only two of the frames have a pose within max_diff_s: they are the views used.
    sparse = Trajectory(np.array([0.0, 0.3]), np.stack([frames[0].T_world_cam, frames[3].T_world_cam]))
    assert phantom_for_capture(seen, cap, sparse, n_samples=1000).n_views == 2
    with pytest.raises(ValidationError, match="within"):
        phantom_for_capture(seen, cap, Trajectory(np.array([50.0]), camera()[None]), n_samples=100)
    no_pose = ListCapture([f.with_(T_world_cam=None) for f in frames])
    with pytest.raises(ValidationError, match="no reference poses"):
        phantom_for_capture(seen, no_pose, n_samples=100)


def test_voxel_keys_are_deduplicated_as_rows_are():
    from voxfusion.core.map.morton import unique_rows

    rng = np.random.default_rng(0)
    keys = rng.integers(-40, 40, (5000, 3))
    keys = np.concatenate([keys, keys[:1500], [[2**40, -(2**40), 0]]])  # repeats; a span past 62 bits: the fallback
    for k in (keys[:-1], keys, keys[:0]):
        uniq, inv = unique_rows(torch.from_numpy(k.reshape(-1, 3)), return_inverse=True)
        expected, expected_inv = np.unique(k.reshape(-1, 3), axis=0, return_inverse=True)
        assert np.array_equal(uniq.numpy(), expected) and np.array_equal(inv.numpy(), expected_inv.reshape(-1))
        assert torch.equal(unique_rows(torch.from_numpy(k.reshape(-1, 3))), uniq)
