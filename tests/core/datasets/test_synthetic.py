"""Synthetic capture generator: determinism, exact z-depth on the GT mesh, textures, trajectory, LiDAR
model, and round trips through the TUM and Replica writers and readers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from voxfusion.core.datasets import ReplicaCapture, TUMCapture, open_capture
from voxfusion.core.datasets.images import read_confidence
from voxfusion.core.datasets.synthetic import (
    LidarNoise,
    SyntheticCapture,
    SyntheticConfig,
    apply_lidar_noise,
    make_trajectory,
    write_capture,
    write_replica_layout,
    write_tum_layout,
)
from voxfusion.core.datasets.synthetic_scene import (
    CAMERA_ZONE_MAX_M,
    CAMERA_ZONE_MIN_M,
    ROOM_MAX_M,
    ROOM_MIN_M,
    make_room_scene,
)
from voxfusion.core.errors import ConfigError, ValidationError
from voxfusion.core.geometry import backproject_depth, check_rigid, invert_pose

TINY = SyntheticConfig(n_frames=6, width=64, height=48, seed=0)


def _frame_arrays(cap: SyntheticCapture, i: int) -> tuple[np.ndarray, ...]:
    f = cap[i]
    return f.depth_m, f.color, f.T_world_cam, (f.confidence if f.confidence is not None else np.zeros(0))


def _relative_motion(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation (m) and rotation (deg) between consecutive poses ``[N, 4, 4]``."""
    rel = invert_pose(T[:-1]) @ T[1:]
    return np.linalg.norm(rel[:, :3, 3], axis=1), np.rad2deg(Rotation.from_matrix(rel[:, :3, :3]).magnitude())


# ------------------------------------------------------------------------------------------- determinism


@pytest.mark.parametrize("lidar", [False, True])
def test_same_seed_gives_identical_frames_in_any_access_order(lidar: bool):
    config = SyntheticConfig(n_frames=6, width=64, height=48, seed=3, lidar=lidar)
    a, b = SyntheticCapture(config), SyntheticCapture(config)
    forward = [_frame_arrays(a, i) for i in range(len(a))]
    backward = [_frame_arrays(b, i) for i in reversed(range(len(b)))][::-1]
    for fa, fb in zip(forward, backward, strict=True):
        for x, y in zip(fa, fb, strict=True):
            np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.gt_mesh.vertices, b.gt_mesh.vertices)
    np.testing.assert_array_equal(a[2].color, a[2].color)  # re-rendering a frame is stable too


def test_different_seeds_give_different_scenes_and_paths():
    s0, s1 = make_room_scene(0), make_room_scene(1)
    assert s0.object_names == s1.object_names
    assert not np.allclose(s0.mesh.vertices, s1.mesh.vertices)
    assert not np.allclose(s0.colors, s1.colors)
    T0 = make_trajectory(SyntheticConfig(seed=0))
    T1 = make_trajectory(SyntheticConfig(seed=1))
    assert np.abs(T0 - T1).max() > 0.1
    c0 = SyntheticCapture(TINY)
    c1 = SyntheticCapture(SyntheticConfig(n_frames=6, width=64, height=48, seed=1))
    assert np.abs(c0[0].color.astype(int) - c1[0].color.astype(int)).mean() > 10


def test_lidar_noise_differs_between_frames_but_not_between_runs():
    cap = SyntheticCapture(SyntheticConfig(n_frames=2, lidar=True, motion_scale=1e-6))  # ~static camera
    d0, d1 = cap[0].depth_m, cap[1].depth_m
    both = (d0 > 0) & (d1 > 0)
    assert np.abs(d0[both] - d1[both]).mean() > 1e-3  # fresh noise per frame
    np.testing.assert_array_equal(d1, SyntheticCapture(cap.config)[1].depth_m)


# -------------------------------------------------------------------------------------- geometry / depth


def test_depth_is_z_depth_that_backprojects_onto_the_gt_mesh():
    cap = SyntheticCapture(SyntheticConfig(n_frames=60, width=64, height=48, seed=2))
    for i in (0, 29, 59):
        f = cap[i]
        assert np.all(f.depth_m > 0)  # closed room: every ray hits something
        pts = backproject_depth(f.depth_m, f.K, f.T_world_cam)
        _, dist, _ = trimesh.proximity.closest_point(cap.gt_mesh, pts)
        assert dist.max() < 1e-3, f"frame {i}: back-projected depth is {dist.max():.2e} m off the mesh"
        # Reading the same values as ray lengths instead puts the image corners well off the surface.
        v, u = np.mgrid[0:f.height, 0:f.width]
        rays = np.stack([(u - f.K[0, 2]) / f.K[0, 0], (v - f.K[1, 2]) / f.K[1, 1], np.ones(u.shape)], -1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        corner = (rays[[0, -1, 0, -1], [0, 0, -1, -1]] * f.depth_m[[0, -1, 0, -1], [0, 0, -1, -1], None])
        corner_w = corner @ f.T_world_cam[:3, :3].T + f.T_world_cam[:3, 3]
        _, dist_ray, _ = trimesh.proximity.closest_point(cap.gt_mesh, corner_w)
        assert dist_ray.max() > 0.05


def test_room_mesh_is_inward_facing_and_furniture_stays_in_the_room():
    scene = make_room_scene(4)
    mesh, ids = scene.mesh, scene.face_object_id
    assert ids.shape == (len(mesh.faces),) and ids.max() == scene.n_objects - 1
    normals = mesh.face_normals
    for name, inward in (("floor", [0, 0, 1]), ("ceiling", [0, 0, -1]), ("wall_x-", [1, 0, 0]),
                         ("wall_x+", [-1, 0, 0]), ("wall_y-", [0, 1, 0]), ("wall_y+", [0, -1, 0])):
        sel = ids == scene.object_names.index(name)
        assert sel.sum() == 2
        np.testing.assert_allclose(normals[sel], np.tile(inward, (2, 1)), atol=1e-12)
    assert np.all(mesh.vertices >= ROOM_MIN_M - 0.02) and np.all(mesh.vertices <= ROOM_MAX_M + 0.02)
    assert {"table_leg_0", "sphere", "bin", "cabinet"} <= set(scene.object_names)
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)


def test_texture_varies_within_a_planar_surface():
    scene = make_room_scene(0)
    rng = np.random.default_rng(0)
    for name in ("floor", "wall_x+", "table_top"):
        oid = scene.object_names.index(name)
        faces = np.nonzero(scene.face_object_id == oid)[0]
        top = faces[np.argmax(scene.mesh.area_faces[faces])]  # one planar triangle
        a, b, c = scene.mesh.triangles[top]
        r1, r2 = np.sqrt(rng.uniform(size=(2000, 1))), rng.uniform(size=(2000, 1))
        pts = (1 - r1) * a + r1 * (1 - r2) * b + r1 * r2 * c  # uniform on the triangle
        albedo = scene.albedo(pts, np.full(len(pts), oid))
        assert albedo.std(axis=0).max() > 0.05, name
        assert np.unique(np.round(albedo * 255), axis=0).shape[0] > 200
    # and in the rendered image: the pixels of one surface have many different colours
    cap = SyntheticCapture(SyntheticConfig(n_frames=1, width=96, height=72, seed=0))
    view, frame = cap.render_view(0), cap[0]
    ids, counts = np.unique(view.object_id, return_counts=True)
    biggest = view.object_id == ids[np.argmax(counts)]
    colours = frame.color[biggest].astype(float)
    assert colours.std(axis=0).max() > 10 and np.unique(colours, axis=0).shape[0] > 50


def test_default_trajectory_is_smooth_moves_and_stays_in_the_room():
    for seed in (0, 1, 7):
        T = make_trajectory(SyntheticConfig(seed=seed))
        assert T.shape == (100, 4, 4)
        for pose in T:
            check_rigid(pose, tol=1e-9)
        trans_m, rot_deg = _relative_motion(T)
        assert trans_m.max() < 0.05 and rot_deg.max() < 3.0
        assert 0.005 < trans_m.mean() < 0.03 and 0.2 < rot_deg.mean() < 1.5  # hand-held, not static
        accel = np.linalg.norm(np.diff(T[:, :3, 3], n=2, axis=0), axis=1)
        assert accel.max() < 0.005  # smooth: no jumps in velocity
        pos = T[:, :3, 3]
        assert np.all(pos >= CAMERA_ZONE_MIN_M) and np.all(pos <= CAMERA_ZONE_MAX_M)
        assert np.all(pos > ROOM_MIN_M + 0.5) and np.all(pos < ROOM_MAX_M - 0.5)
    # motion_scale runs along the same path faster
    slow = make_trajectory(SyntheticConfig(seed=0))
    fast = make_trajectory(SyntheticConfig(seed=0, motion_scale=2.0, n_frames=50))
    np.testing.assert_allclose(fast, slow[::2], atol=1e-12)


def test_camera_looks_at_furniture_from_a_safe_distance():
    cap = SyntheticCapture(SyntheticConfig(n_frames=100, width=48, height=36, seed=5))
    furniture = cap.scene.object_names.index("table_top")  # ids from here on are furniture
    for i in range(0, 100, 11):
        view = cap.render_view(i)
        assert view.depth_m.min() > 0.3
        assert np.mean(view.object_id >= furniture) > 0.02, f"frame {i} sees no furniture"


# ------------------------------------------------------------------------------------------------ LiDAR


def test_lidar_noise_model_on_a_depth_step():
    depth = np.full((200, 200), 1.0, np.float32)
    depth[:, 100:] = 3.5
    noise = LidarNoise()
    out, conf = apply_lidar_noise(depth, np.ones_like(depth), np.random.default_rng(0), noise)
    assert out.dtype == np.float32 and conf.dtype == np.uint8
    assert np.all(out[:, 99:101] == 0) and np.all(conf[:, 99:101] == 0)  # both sides of the edge drop
    assert np.all(conf[:, [98, 101]] == 1)  # next to the dropped edge: medium
    near, far = out[:, 2:97] - 1.0, out[:, 104:198] - 3.5
    assert near.std() == pytest.approx(0.001 + 0.002 * 1.0, rel=0.1)
    assert far.std() == pytest.approx(0.001 + 0.002 * 3.5**2, rel=0.1)
    assert np.all(conf[:, 2:97] == 2) and np.all(conf[:, 104:198] == 1)  # 3.5 m is beyond high confidence
    _, conf_grazing = apply_lidar_noise(depth, np.full_like(depth, 0.1), np.random.default_rng(0), noise)
    assert conf_grazing.max() == 1
    with pytest.raises(ValidationError):
        apply_lidar_noise(depth, np.ones((3, 3)), np.random.default_rng(0), noise)


def test_lidar_capture_resolution_confidence_noise_growth_and_edge_holes():
    cap = SyntheticCapture(SyntheticConfig(n_frames=40, lidar=True, seed=1))
    assert (cap.width, cap.height) == (256, 192)
    resid_near, resid_far = [], []
    for i in (0, 20, 39):
        f, clean = cap[i], cap.render_view(i).depth_m
        assert f.depth_m.shape == (192, 256) and f.color.shape == (192, 256, 3)
        assert f.confidence.dtype == np.uint8 and set(np.unique(f.confidence)) <= {0, 1, 2}
        assert np.all(f.confidence[f.depth_m == 0] == 0)
        assert 0.0 < np.mean(f.depth_m == 0) < 0.1
        # strong depth discontinuities (> 20 % to the right-hand neighbour) are holes in the LiDAR depth
        jump = np.abs(np.diff(clean, axis=1)) > 0.2 * clean[:, :-1]
        assert jump.any() and np.all(f.depth_m[:, :-1][jump] == 0) and np.all(f.depth_m[:, 1:][jump] == 0)
        ok = f.depth_m > 0
        r = (f.depth_m - clean)[ok]
        z = clean[ok]
        resid_near.append(r[z < 1.5])
        resid_far.append(r[z > 2.5])
    near, far = np.concatenate(resid_near), np.concatenate(resid_far)
    assert near.size > 500 and far.size > 500
    assert far.std() > 2.5 * near.std()
    assert near.std() < 0.001 + 0.002 * 1.5**2
    assert np.mean(np.concatenate([np.unique(cap[i].confidence) for i in (0, 20)]) == 2) > 0


# --------------------------------------------------------------------------------------- config / errors


@pytest.mark.parametrize("kwargs", [
    {"n_frames": 0}, {"seed": -1}, {"width": 1}, {"fx": 0.0}, {"motion_scale": 0.0}, {"fps": -1.0},
    {"max_depth_m": 11.0}, {"cx": 500.0}, {"lidar_noise": "loud"},
])
def test_config_rejects_bad_values(kwargs: dict):
    with pytest.raises(ConfigError):
        SyntheticConfig(**kwargs)


def test_config_defaults_and_intrinsics():
    c = SyntheticConfig()
    assert c.image_size == (320, 240)
    np.testing.assert_allclose(c.K, [[192, 0, 159.5], [0, 192, 119.5], [0, 0, 1]])
    hfov = 2 * np.degrees(np.arctan(160 / 192))
    assert 75 < hfov < 85
    assert SyntheticConfig(lidar=True).image_size == (256, 192)
    assert SyntheticConfig(lidar=True, width=128, height=96).image_size == (128, 96)
    custom = SyntheticConfig(fx=100, cx=10, cy=20).K
    np.testing.assert_allclose(custom, [[100, 0, 10], [0, 100, 20], [0, 0, 1]])


def test_writers_refuse_non_empty_folders_and_unknown_layouts(tmp_path: Path):
    cap = SyntheticCapture(SyntheticConfig(n_frames=1, width=16, height=12))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(ValidationError, match="out_dir"):
        write_tum_layout(cap, tmp_path / "full")
    with pytest.raises(ValidationError, match="layout"):
        write_capture(cap, tmp_path / "new", "kitti")  # type: ignore[arg-type]
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


# ------------------------------------------------------------------------------------------- round trips


def test_tum_layout_round_trip(tmp_path: Path):
    cap = SyntheticCapture(SyntheticConfig(n_frames=4, width=64, height=48, seed=6, lidar=True))
    assert cap.gt_mesh_path is None
    out = write_tum_layout(cap, tmp_path / "synth")
    assert cap.gt_mesh_path == out / "gt_mesh.ply"
    back = TUMCapture(out)
    assert open_capture(out).__class__ is TUMCapture
    assert len(back) == len(cap) and back.intrinsics_source.endswith("intrinsics.txt")
    # the reader knows it is our synthetic room (rgb.txt's header), with exact depth and LiDAR confidence
    assert back.profile == cap.profile.with_(sensor=back.profile.sensor)
    assert (back.profile.kind, back.profile.max_depth_m, back.profile.has_confidence) == ("synthetic", 10.0, True)
    np.testing.assert_allclose(back.K, cap.K, atol=1e-12)
    for i in range(len(cap)):
        f, g = cap[i], back[i]
        assert g.timestamp_s == f.timestamp_s
        np.testing.assert_allclose(g.depth_m, f.depth_m, atol=0.5 / 5000 + 1e-6)
        np.testing.assert_array_equal(g.depth_m == 0, f.depth_m == 0)
        np.testing.assert_array_equal(g.color, f.color)  # PNG: exact
        np.testing.assert_allclose(g.T_world_cam, f.T_world_cam, atol=1e-6)
        conf_path = out / "confidence" / Path(g.meta["rgb_path"]).name
        np.testing.assert_array_equal(read_confidence(conf_path), f.confidence)
    mesh = trimesh.load(out / "gt_mesh.ply", process=False)
    np.testing.assert_allclose(mesh.vertices, cap.gt_mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, cap.gt_mesh.faces)


def test_replica_layout_round_trip(tmp_path: Path):
    cap = SyntheticCapture(SyntheticConfig(n_frames=4, width=64, height=48, seed=6))
    out = write_replica_layout(cap, tmp_path / "room")
    cam = json.loads((out / "cam_params.json").read_text())["camera"]
    assert cam == {"w": 64, "h": 48, "fx": 38.4, "fy": 38.4, "cx": 31.5, "cy": 23.5, "scale": 6553.5}
    back = ReplicaCapture(out)
    assert open_capture(out).__class__ is ReplicaCapture
    assert len(back) == len(cap)
    assert (back.profile.kind, back.profile.has_confidence) == ("synthetic", False)  # gt_mesh.ply marks it
    np.testing.assert_allclose(back.K, cap.K, atol=1e-12)
    assert back.depth_scale == 6553.5
    for i in range(len(cap)):
        f, g = cap[i], back[i]
        assert g.timestamp_s == pytest.approx(f.timestamp_s, abs=1e-6)
        np.testing.assert_allclose(g.depth_m, f.depth_m, atol=0.5 / 6553.5 + 1e-6)
        assert np.abs(g.color.astype(int) - f.color.astype(int)).mean() < 4  # JPEG quality 95
        np.testing.assert_allclose(g.T_world_cam, f.T_world_cam, atol=1e-6)
    assert (out / "gt_mesh.ply").is_file()


def test_cli_synth_writes_a_capture(tmp_path: Path):
    from voxfusion.cli import app

    runner = CliRunner()
    out = tmp_path / "cli"
    res = runner.invoke(app, ["synth", str(out), "--layout", "replica", "--frames", "2", "--width", "32",
                              "--height", "24", "--seed", "3"])
    assert res.exit_code == 0, res.output
    back = ReplicaCapture(out)
    assert len(back) == 2 and back[0].depth_m.shape == (24, 32)
    res = runner.invoke(app, ["synth", str(out)])
    assert res.exit_code == 2 and "out_dir" in res.output and "--force" in res.output
    # --force replaces the capture synth wrote there, in the other layout too (nothing of the old one stays)
    res = runner.invoke(app, ["synth", str(out), "--frames", "3", "--width", "32", "--height", "24", "--force"])
    assert res.exit_code == 0, res.output
    assert not (out / "results").exists() and len(TUMCapture(out)) == 3
    # ... but never a folder holding anything else: nothing there is deleted
    (out / "notes.md").write_text("mine")
    res = runner.invoke(app, ["synth", str(out), "--frames", "2", "--width", "32", "--height", "24", "--force"])
    assert res.exit_code == 2 and "'notes.md'" in res.output
    assert (out / "notes.md").read_text() == "mine" and len(TUMCapture(out)) == 3


def test_fast_rotation_mode_reaches_the_requested_yaw_rate():
    """180 deg/s at 30 Hz: the fastest frame-to-frame rotation is ~6 deg (the swing) plus the slow base
    motion; with the mode off it stays around a degree."""
    from voxfusion.core.datasets.synthetic import SyntheticConfig, make_trajectory

    def max_step_deg(cfg):
        T = make_trajectory(cfg)
        R = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
        return np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1))).max()

    fast = max_step_deg(SyntheticConfig(n_frames=90, yaw_rate_deg_s=180.0))
    slow = max_step_deg(SyntheticConfig(n_frames=90))
    assert 5.0 < fast < 8.0, fast
    assert slow < 2.0, slow
