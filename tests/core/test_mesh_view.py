"""Mesh pictures (voxfusion.core.mesh.view) and ``voxfusion view``: real ray-cast renders of analytic scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from typer.testing import CliRunner

from voxfusion.cli import app
from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.geometry import check_rigid, make_intrinsics
from voxfusion.core.mesh import (
    LIGHT_GREY_RGB,
    intrinsics_from_fov,
    look_at,
    overview_pose,
    render_mesh,
    save_png,
    side_by_side,
    write_mesh_pictures,
)

W, H = 64, 48
K = make_intrinsics(40.0, 40.0, 32.0, 24.0)  # pixel (32, 24) lies on the optical axis
RED, GREEN = (255, 0, 0), (0, 200, 0)
BOX_FRONT_Z_M, PLANE_Z_M = 2.5, 5.0
WHITE = (255, 255, 255)


def box_and_plane() -> trimesh.Trimesh:
    """Camera-at-origin scene looking along +z: a green 4 m plane at z = 5 (normal +z, away from the camera),
    listed *first*, then a red unit cube centred at z = 3 (front face at z = 2.5, outward normals)."""
    plane_v = np.array([[-2, -2, PLANE_Z_M], [2, -2, PLANE_Z_M], [2, 2, PLANE_Z_M], [-2, 2, PLANE_Z_M]], float)
    plane_f = np.array([[0, 1, 2], [0, 2, 3]])
    box = trimesh.creation.box(extents=(1, 1, 1))
    box_v = np.asarray(box.vertices) + [0.0, 0.0, 3.0]
    vertices = np.concatenate([plane_v, box_v])
    faces = np.concatenate([plane_f, np.asarray(box.faces) + 4])
    colours = np.concatenate([np.tile([*GREEN, 255], (4, 1)), np.tile([*RED, 255], (len(box_v), 1))])
    return trimesh.Trimesh(vertices, faces, vertex_colors=colours.astype(np.uint8), process=False)


def test_depth_ordering_colour_and_depth():
    view = render_mesh(box_and_plane(), K, np.eye(4), W, H)
    assert view.rgb.shape == (H, W, 3) and view.rgb.dtype == np.uint8
    assert view.depth_m.shape == (H, W) and view.depth_m.dtype == np.float32
    # centre: the box (nearer) wins over the plane listed before it; head-on, so shade = 1
    assert tuple(view.rgb[24, 32]) == RED
    assert view.depth_m[24, 32] == pytest.approx(BOX_FRONT_Z_M, abs=1e-3)
    # the whole front face is a plane at z = 2.5: z-depth is 2.5 everywhere on it (not the ray length)
    on_box = view.face_index >= 2
    assert on_box.sum() > 100
    np.testing.assert_allclose(view.depth_m[on_box & (np.abs(view.depth_m - 2.5) < 0.4)], 2.5, atol=1e-3)
    # 12 px right of centre: beside the box (it spans +-8 px), on the plane (+-16 px)
    r, g, b = (int(c) for c in view.rgb[24, 44])
    assert g > 150 and r < 20 and b < 20
    assert view.depth_m[24, 44] == pytest.approx(PLANE_Z_M, abs=1e-3)
    assert view.face_index[24, 44] in (0, 1)
    # corner: nothing there
    assert tuple(view.rgb[2, 2]) == WHITE and view.depth_m[2, 2] == 0 and view.face_index[2, 2] == -1


def test_cull_back_faces_sees_through_the_plane():
    mesh = box_and_plane()
    culled = render_mesh(mesh, K, np.eye(4), W, H, background=(0, 0, 80), cull_back_faces=True)
    assert tuple(culled.rgb[24, 32]) == RED  # the cube's front faces the camera
    assert tuple(culled.rgb[24, 44]) == (0, 0, 80) and culled.depth_m[24, 44] == 0  # the plane faces away


def test_vertex_colours_interpolate_with_barycentric_coordinates():
    z = 2.0
    tri = trimesh.Trimesh([[0, 0, z], [1, 0, z], [0, 1, z]], [[0, 2, 1]], process=False,
                          vertex_colors=np.array([[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255]], np.uint8))
    view = render_mesh(tri, K, np.eye(4), W, H)
    hits = np.argwhere(view.face_index == 0)
    assert len(hits) > 50
    for v, u in hits[:: max(1, len(hits) // 40)]:
        x, y = (u - 32.0) / 40.0, (v - 24.0) / 40.0  # normalised image coordinates; hit point = z * (x, y, 1)
        bary = np.array([1 - z * x - z * y, z * x, z * y])
        shade = 0.35 + 0.65 / np.sqrt(x * x + y * y + 1)
        np.testing.assert_allclose(view.rgb[v, u], np.clip(255 * bary * shade, 0, 255), atol=1.01)
        assert view.depth_m[v, u] == pytest.approx(z, abs=1e-4)


def test_uncoloured_and_empty_meshes():
    box = trimesh.creation.box(extents=(1, 1, 1))
    box.apply_translation([0, 0, 3])
    view = render_mesh(box, K, np.eye(4), W, H)
    assert tuple(view.rgb[24, 32]) == LIGHT_GREY_RGB
    grey = trimesh.Trimesh(box.vertices, box.faces, vertex_colors=np.full((8, 4), 128, np.uint8), process=False)
    assert tuple(render_mesh(grey, K, np.eye(4), W, H).rgb[24, 32]) == LIGHT_GREY_RGB
    empty = render_mesh(trimesh.Trimesh(), K, np.eye(4), W, H, background=(1, 2, 3))
    assert np.all(empty.rgb == [1, 2, 3]) and not empty.depth_m.any() and np.all(empty.face_index == -1)


def test_sphere_depth_and_outline_match_analytic_over_several_row_chunks():
    """640x480 = 307k rays: rows 0-408 are cast in one chunk and the rest in another; the sphere spans both."""
    radius, centre = 1.0, np.array([0.2, 0.3, 4.0])
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    sphere.apply_translation(centre)
    K_big = intrinsics_from_fov(640, 480, 50.0)
    view = render_mesh(sphere, K_big, np.eye(4), 640, 480)
    v, u = np.nonzero(view.depth_m > 0)
    assert v.min() < 409 < v.max()
    d = np.stack([(u - K_big[0, 2]) / K_big[0, 0], (v - K_big[1, 2]) / K_big[1, 1], np.ones_like(u, float)], 1)
    d_unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    b = d_unit @ centre
    disc = b * b - (centre @ centre - radius * radius)
    inside = disc > 0.01  # away from the silhouette, where the tessellation differs most from the sphere
    assert inside.sum() > 0.9 * len(v) > 20_000
    t = b[inside] - np.sqrt(disc[inside])
    np.testing.assert_allclose(view.depth_m[v[inside], u[inside]], t * d_unit[inside, 2], atol=3e-3)
    # top and bottom rows of the outline: planes y = k z (they hold the x axis) tangent to the sphere
    cy_, cz_ = centre[1], centre[2]
    a = cz_**2 - radius**2
    root = np.sqrt((cy_ * cz_) ** 2 - a * (cy_**2 - radius**2))
    k_top, k_bottom = (cy_ * cz_ - root) / a, (cy_ * cz_ + root) / a
    assert abs(v.min() - (K_big[1, 1] * k_top + K_big[1, 2])) < 1.5
    assert abs(v.max() - (K_big[1, 1] * k_bottom + K_big[1, 2])) < 1.5


def test_look_at_pose():
    eye, target = np.array([1.0, -2.0, 1.5]), np.array([0.3, 0.4, 0.2])
    T = look_at(eye, target, up=(0, 0, 1))
    check_rigid(T, tol=1e-9)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 3], eye)
    np.testing.assert_allclose(T[:3, 2], (target - eye) / np.linalg.norm(target - eye), atol=1e-12)
    assert -T[:3, 1] @ np.array([0, 0, 1.0]) > 0  # image up (camera -y) points to world up
    assert abs(T[:3, 0] @ np.array([0, 0, 1.0])) < 1e-12  # no roll
    p_cam = np.linalg.inv(T) @ np.append(target, 1.0)
    np.testing.assert_allclose((K @ p_cam[:3] / p_cam[2])[:2], [32.0, 24.0], atol=1e-9)
    with pytest.raises(ValidationError, match="same point"):
        look_at(eye, eye)
    with pytest.raises(ValidationError, match="parallel"):
        look_at([0, 0, 5], [0, 0, 0], up=(0, 0, 1))
    with pytest.raises(ShapeError):
        look_at([0, 0], [0, 0, 1])


def test_overview_pose_frames_every_vertex_from_above():
    room = trimesh.creation.box(extents=(5.0, 4.0, 2.7))
    room.apply_translation([0.5, 0.0, 1.35])
    K_o = intrinsics_from_fov(320, 240, 70.0)
    T = overview_pose(room, K_o, 320, 240, elevation_deg=35.0, margin=0.9)
    check_rigid(T)
    assert np.degrees(np.arcsin(-T[:3, 2] @ [0, 0, 1.0])) == pytest.approx(35.0, abs=1e-6)  # looks down 35 deg
    assert abs(T[:3, 0] @ [0, 0, 1.0]) < 1e-12  # no roll
    p = (np.asarray(room.vertices) - T[:3, 3]) @ T[:3, :3]
    assert np.all(p[:, 2] > 0)
    uv = (p @ K_o.T)[:, :2] / p[:, 2:3]
    off = np.abs(uv - K_o[:2, 2]) / (0.9 * K_o[:2, 2])  # 1 = on the margin
    assert off.max() <= 1 + 1e-9 and off.max() > 0.999  # inside the margin, and as large as it allows
    lo, hi = uv.min(0), uv.max(0)
    np.testing.assert_allclose((lo + hi) / 2, K_o[:2, 2], atol=1.0)  # centred
    view = render_mesh(room, K_o, T, 320, 240)
    assert (view.face_index >= 0).mean() > 0.4
    with pytest.raises(ValidationError, match="elevation"):
        overview_pose(room, K_o, 320, 240, elevation_deg=90.0)
    T_empty = overview_pose(trimesh.Trimesh(), K_o, 320, 240)
    check_rigid(T_empty)


def test_side_by_side_and_save_png(tmp_path: Path):
    a = np.full((60, 40, 3), 10, np.uint8)
    b = np.full((40, 50, 3), 200, np.uint8)
    out = side_by_side([a, b], ["a", "b"])
    assert out.shape == (60, 40 + 4 + 50, 3) and out.dtype == np.uint8
    assert np.all(out[25:, :40] == 10) and np.all(out[25:40, 44:] == 200)  # panels kept below the labels
    assert np.all(out[40:, 44:] == 64) and np.all(out[:, 40:44] == 64)  # padding and gap
    assert not np.all(out[:12, :20] == 10)  # a label was drawn
    with pytest.raises(ValidationError, match="labels"):
        side_by_side([a, b], ["only one"])
    path = save_png(tmp_path / "sub" / "x.png", out)
    np.testing.assert_array_equal(np.asarray(Image.open(path)), out)
    with pytest.raises(ValidationError, match="png"):
        save_png(tmp_path / "x.jpg", out)


def test_write_mesh_pictures(tmp_path: Path):
    mesh = box_and_plane()
    input_rgb = np.zeros((H // 2, W // 2, 3), np.uint8)  # another size: resized to the panel size
    path = write_mesh_pictures(tmp_path, {"ours": mesh, "again": mesh}, K, np.eye(4), W, H, input_rgb=input_rgb,
                               name="cmp.png")
    image = np.asarray(Image.open(path))
    assert path == tmp_path / "cmp.png" and image.shape == (H, 3 * W + 2 * 4, 3)
    assert tuple(image[24, W + 4 + 32]) == RED and tuple(image[24, 2 * (W + 4) + 32]) == RED
    assert np.all(image[30:, :W] == 0)


# --- the command line ------------------------------------------------------------------------------------


def _write_scene(tmp_path: Path) -> tuple[Path, Path]:
    mesh_path = tmp_path / "scene.ply"
    box_and_plane().export(mesh_path)
    traj = tmp_path / "traj.txt"
    traj.write_text("# timestamp tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n1.0 0 0 -1 0 0 0 1\n")
    return mesh_path, traj


def _invoke(*args: str):
    return CliRunner().invoke(app, ["view", *args])


def _png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def test_cli_pose_look_at_and_compare(tmp_path: Path):
    mesh_path, traj = _write_scene(tmp_path)
    out = tmp_path / "pose.png"
    result = _invoke(str(mesh_path), "--pose", f"{traj}:0", "--size", "64x48", "--out", str(out))
    assert result.exit_code == 0, result.output
    assert f"wrote {out}" in result.output
    image = _png(out)
    assert image.shape == (48, 64, 3) and tuple(image[24, 32]) == RED

    out = tmp_path / "look.png"
    result = _invoke(str(mesh_path), "--look-at", "0,0,0,0,0,5,0,-1,0", "--size", "80x60", "--out", str(out))
    assert result.exit_code == 0, result.output
    image = _png(out)
    assert image.shape == (60, 80, 3) and tuple(image[30, 40]) == RED

    out = tmp_path / "cmp.png"
    other = tmp_path / "other.ply"
    trimesh.creation.box().export(other)
    result = _invoke(str(mesh_path), "--compare", str(other), "--label", "ours", "--label", "box",
                     "--size", "64x48", "--out", str(out))  # automatic overview
    assert result.exit_code == 0, result.output
    assert _png(out).shape == (48, 2 * 64 + 4, 3)


def test_cli_refuses_to_overwrite_and_reports_bad_inputs(tmp_path: Path):
    mesh_path, traj = _write_scene(tmp_path)
    out = tmp_path / "v.png"
    base = [str(mesh_path), "--size", "32x24", "--out", str(out)]
    assert _invoke(*base).exit_code == 0
    result = _invoke(*base)
    assert result.exit_code == 2 and "exists" in result.output and "--force" in result.output
    assert _invoke(*base, "--force").exit_code == 0

    def fails(*args: str, expect: str) -> None:
        result = _invoke(*args)
        assert result.exit_code == 2, result.output
        assert "error:" in result.output and expect in result.output, result.output

    new = str(tmp_path / "new.png")
    fails(str(mesh_path), "--pose", f"{traj}:5", "--out", new, expect="has 2 poses")
    fails(str(mesh_path), "--pose", f"{traj}:x", "--out", new, expect="INDEX must be an integer")
    fails(str(mesh_path), "--pose", f"{tmp_path / 'nope.txt'}:0", "--out", new, expect="not found")
    fails(str(tmp_path / "missing.ply"), "--out", new, expect="mesh file not found")
    fails(str(mesh_path), "--look-at", "1,2,3", "--out", new, expect="6 or 9")
    fails(str(mesh_path), "--look-at", "0,0,5,0,0,0", "--out", new, expect="parallel")
    fails(str(mesh_path), "--size", "64by48", "--out", new, expect="WIDTHxHEIGHT")
    fails(str(mesh_path), "--out", str(tmp_path / "v.jpg"), expect=".png")
    fails(str(mesh_path), "--label", "a", "--label", "b", "--out", new, expect="2 labels for 1 meshes")
    assert not Path(new).exists()


def test_cli_capture_frame(tmp_path: Path, shared_data: Path):
    """A mesh made from frame 3's own depth, rendered at that frame's pose, gives back the measured depth."""
    root = shared_data / "tum_fr1_desk_9frames"
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    from voxfusion.core.datasets import open_capture

    frame = open_capture(root)[3]
    mesh = _depth_grid_mesh(frame.depth_m, frame.K, frame.T_world_cam, frame.color, stride=2)
    view = render_mesh(mesh, frame.K, frame.T_world_cam, frame.width, frame.height)
    both = (view.depth_m > 0) & (frame.depth_m > 0)
    assert both.mean() > 0.5
    assert np.median(np.abs(view.depth_m[both] - frame.depth_m[both])) < 5e-3

    mesh_path, out = tmp_path / "frame3.ply", tmp_path / "frame3.png"
    mesh.export(mesh_path)
    result = _invoke(str(mesh_path), "--capture", str(root), "--frame", "3", "--out", str(out))
    assert result.exit_code == 0, result.output
    image = _png(out)
    assert image.shape == (frame.height, 2 * frame.width + 4, 3)
    np.testing.assert_array_equal(image[40:, : frame.width], frame.color[40:])  # the input panel, under its label
    result = _invoke(str(mesh_path), "--capture", str(root), "--frame", "9", "--out", str(tmp_path / "x.png"))
    assert result.exit_code == 2 and "9 frames" in result.output


def _depth_grid_mesh(depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, color: np.ndarray,
                     stride: int) -> trimesh.Trimesh:
    """Triangulate every ``stride``-th depth pixel into a world-frame grid mesh (no faces across depth jumps)."""
    d = depth_m[::stride, ::stride].astype(np.float64)
    h, w = d.shape
    v, u = np.mgrid[0:h, 0:w] * stride
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d, d], -1).reshape(-1, 3)
    pts = pts @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    idx = np.arange(h * w).reshape(h, w)
    quads = [idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]]
    faces = np.concatenate([np.stack([quads[0], quads[2], quads[1]], -1).reshape(-1, 3),
                            np.stack([quads[1], quads[2], quads[3]], -1).reshape(-1, 3)])
    z = d.reshape(-1)[faces]
    ok = (z.min(1) > 0) & (z.max(1) - z.min(1) < 0.05 * z.min(1) + 0.01)
    rgba = np.concatenate([color[::stride, ::stride].reshape(-1, 3), np.full((h * w, 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(pts, faces[ok], vertex_colors=rgba, process=False)
