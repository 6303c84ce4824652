"""Observation support for meshes (voxfusion.core.mesh.support), the surface mask it reads, the evidence rule
that uses it, and the frame sidecar / Y-up GLB of mesh exports."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import torch
import trimesh

from voxfusion.core.errors import ValidationError
from voxfusion.core.eval import read_mesh_frame
from voxfusion.core.map import SURFACE_CELLS, VoxelMap
from voxfusion.core.map.evidence import EvidenceConfig, evidence_active
from voxfusion.core.mesh import SurfaceSupport, export_mesh, extract_mesh, mesh_bytes
from voxfusion.core.mesh.mesh_frame import T_GLTF_WORLD, WorldAxes, camera_up_forward, gltf_from_world

VOXEL_M = 0.2


def sphere(points: torch.Tensor):
    sdf = (points.double() - torch.tensor([0.013, -0.021, 0.037])).norm(dim=1) - 0.5
    return sdf.float(), None, torch.ones(len(points), dtype=torch.bool)


def test_surface_mask_marks_cells_counts_and_survives_a_checkpoint():
    vmap = VoxelMap(VOXEL_M, seed=0)
    pts = torch.tensor([[0.01, 0.01, 1.01], [0.012, 0.011, 1.012], [0.19, 0.19, 1.19], [0.3, 0.1, 1.0]])
    vmap.allocate(pts)
    assert vmap.add_surface_points(pts) == 3  # the first two share a 2.5 cm cell
    assert vmap.add_surface_points(pts) == 0
    # non-finite points and points outside every voxel mark nothing, and leave the others alone
    nonfinite = torch.tensor([[float("nan"), 0.0, 1.0], [float("inf"), 0.1, 1.0], [0.1, -float("inf"), 1.0],
                              [5.0, 5.0, 5.0]])
    assert vmap.add_surface_points(nonfinite) == 0
    assert vmap.add_surface_points(pts[:0]) == 0
    cell = VOXEL_M / SURFACE_CELLS
    expected = {tuple(c) for c in np.floor(pts.numpy() / cell).astype(int).tolist()}
    assert {tuple(c) for c in vmap.surface_cells().tolist()} == expected
    assert sorted(vmap.surface_cell_counts().tolist()) == [1, 2]
    back = VoxelMap.from_state_dict(vmap.state_dict())
    assert back.has_surface_evidence and torch.equal(back.voxel_surface, vmap.voxel_surface)
    assert torch.equal(back.surface_cell_counts(), vmap.surface_cell_counts())
    # the counts kept by add_surface_points equal the mask's popcount, also after many random updates
    rng = torch.Generator().manual_seed(0)
    cloud = torch.rand(5000, 3, generator=rng, dtype=torch.float64) * 0.6 + torch.tensor([-0.2, -0.2, 0.8])
    vmap.allocate(cloud)
    for part in cloud.split(700):
        vmap.add_surface_points(part)
    bits = sum(((vmap.voxel_surface.long() >> b) & 1).sum(1) for b in range(8))
    assert torch.equal(vmap.surface_cell_counts().long(), bits) and int(bits.sum()) > 1000
    # and the mask holds exactly the cells of every point added (each bit where it belongs)
    expected |= {tuple(c) for c in np.floor(cloud.numpy() / cell).astype(int).tolist()}
    assert {tuple(c) for c in vmap.surface_cells().tolist()} == expected
    # located first (the mapper looks a frame's points up once for the mask and the evidence): the same marks;
    # points located before an allocation are refused, not marked in the wrong voxels
    more = torch.rand(300, 3, generator=rng, dtype=torch.float64) * 0.6 + torch.tensor([-0.2, -0.2, 0.8])
    twin = VoxelMap.from_state_dict(vmap.state_dict())
    located = twin.locate_surface_points(more)
    assert torch.equal(located.voxel_idx, twin.lookup_voxels(more)) and int((located.cell >= 0).sum()) == 300
    assert twin.add_surface_points(located) == vmap.add_surface_points(more) > 0
    assert torch.equal(twin.voxel_surface, vmap.voxel_surface)
    stale = twin.locate_surface_points(more + 1.0)
    twin.allocate(more + 1.0)
    with pytest.raises(ValidationError, match="points"):
        twin.add_surface_points(stale)
    old = vmap.state_dict()
    del old["voxel_surface"]
    legacy = VoxelMap.from_state_dict(old)
    assert not legacy.has_surface_evidence and SurfaceSupport.from_map(legacy) is None


def test_support_keeps_only_faces_near_observed_points():
    ijk = torch.cartesian_prod(*[torch.arange(-4, 4)] * 3)
    full = extract_mesh(ijk, VOXEL_M, sphere, mesh_res=8)
    # "observe" the upper half of the sphere only (points exactly on it, z > centre)
    seen = full.vertices[full.vertices[:, 2] > 0.037 + 0.1]
    support = SurfaceSupport(torch.from_numpy(np.floor(seen / (VOXEL_M / SURFACE_CELLS))).long(),
                             VOXEL_M / SURFACE_CELLS)
    kept = extract_mesh(ijk, VOXEL_M, sphere, mesh_res=8, keep_fn=support)
    assert 0.2 * len(full.faces) < len(kept.faces) < 0.6 * len(full.faces)
    centres = kept.triangles_center
    assert centres[:, 2].min() > 0.037 + 0.1 - 2 * np.sqrt(3) * VOXEL_M / SURFACE_CELLS  # <= 2 cell diagonals
    assert len(np.unique(kept.faces)) == len(kept.vertices)  # no unused vertices left behind
    nothing = extract_mesh(ijk, VOXEL_M, sphere, mesh_res=8, keep_fn=SurfaceSupport(
        torch.zeros(0, 3, dtype=torch.long), 0.025))
    assert len(nothing.faces) == 0


def test_evidence_keeps_an_extended_sliver_but_not_isolated_points():
    config = EvidenceConfig()
    hits = torch.tensor([80.0, 3.0, 80.0])
    free = torch.tensor([10000.0, 10000.0, 10.0])  # ratio < 1 % for the first two
    cells = torch.tensor([40, 2, 1])
    active = evidence_active(hits, free, config, cells)
    assert active.tolist() == [True, False, True]
    assert evidence_active(hits, free, config).tolist() == [False, False, True]  # ratio alone


def test_glb_is_y_up_and_every_export_has_a_sidecar(tmp_path):
    # a first-camera world (OpenCV: y down): a point above the camera has negative y
    mesh = trimesh.Trimesh(vertices=[[0.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, -1.0, 3.0]], faces=[[0, 1, 2]],
                           process=False)
    axes = WorldAxes("first_camera", T_first_camera_world=np.eye(4))
    assert np.allclose(axes.T_file_world("glb"), T_GLTF_WORLD) and np.allclose(axes.T_file_world("ply"), np.eye(4))
    glb = trimesh.load(io.BytesIO(mesh_bytes(mesh, "glb", axes)), file_type="glb", force="mesh")
    assert (glb.vertices[:, 1] > 0.9).all()  # above the camera is +Y in glTF
    assert (glb.vertices[:, 2] < -1.9).all()  # in front of the first camera is -Z
    for name in ("mesh.glb", "mesh.ply"):
        path = export_mesh(mesh, tmp_path / name, axes)
        frame = read_mesh_frame(path)
        assert frame.world == "first_camera"
        loaded = trimesh.load(path, force="mesh", process=False)
        back = loaded.vertices @ frame.T_world_file[:3, :3].T + frame.T_world_file[:3, 3]
        np.testing.assert_allclose(np.sort(back, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-6)
        rebuilt = WorldAxes.from_sidecar(json.loads((tmp_path / f"{name}.frame.json").read_text()))
        assert rebuilt.world == axes.world and rebuilt.up_m == axes.up_m and rebuilt.forward_m == axes.forward_m


def test_up_is_estimated_from_camera_orientations():
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])  # cameras looking along +y, image up = +z
    up, forward = camera_up_forward(T)
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(forward, [0, 1, 0], atol=1e-12)
    R = gltf_from_world(up, forward)[:3, :3]
    np.testing.assert_allclose(R @ up, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ forward, [0, 0, -1], atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)


def test_image_colours_follow_the_pixels_and_skip_occluded_views():
    from voxfusion.core.mesh.colors import ColorView, image_vertex_colors

    h, w = 40, 60
    K = torch.tensor([[50.0, 0, 29.5], [0, 50.0, 19.5], [0, 0, 1]], dtype=torch.float64)
    color = torch.zeros(h, w, 3)
    color[:, : w // 2, 0] = 1.0  # left half red, right half green
    color[:, w // 2:, 1] = 1.0
    depth = torch.full((h, w), 2.0)
    view = ColorView(color, depth, K, torch.eye(4, dtype=torch.float64))
    pts = torch.tensor([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0], [0.5, 0.0, 1.0], [5.0, 0.0, 2.0]], dtype=torch.float64)
    rgb, seen = image_vertex_colors(pts, None, [view])
    assert seen.tolist() == [True, True, False, False]  # 1 m in front of the observed surface; outside
    assert torch.allclose(rgb[0], torch.tensor([1.0, 0, 0])) and torch.allclose(rgb[1], torch.tensor([0, 1.0, 0]))
    # two views: the weighted mean, the closer (head-on) view weighing more
    far = ColorView(torch.full((h, w, 3), 0.5), torch.full((h, w), 4.0), K,
                    torch.tensor([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.0], [0, 0, 0, 1]], dtype=torch.float64))
    rgb2, _ = image_vertex_colors(pts[:1], None, [view, far])
    assert 0.5 < float(rgb2[0, 0]) < 1.0 and float(rgb2[0, 0]) > 0.5 + 0.25


def test_vertex_normals_are_area_weighted_face_normals():
    """The colour weights' normals: outward on a sphere (trimesh's own within a degree there), the area-weighted
    sum at a box corner, zero for a vertex without a face, and an empty mesh."""
    import trimesh

    from voxfusion.core.mesh.colors import vertex_normals

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.7)
    v = torch.from_numpy(np.asarray(sphere.vertices))
    f = torch.from_numpy(np.asarray(sphere.faces, dtype=np.int64))
    n = vertex_normals(v, f)
    assert n.dtype == v.dtype and n.shape == v.shape
    radial = torch.nn.functional.normalize(v, dim=1)
    assert float((n * radial).sum(1).min()) > np.cos(np.radians(1.0))
    assert float((n * torch.from_numpy(np.array(sphere.vertex_normals))).sum(1).min()) > np.cos(np.radians(1.0))
    # a corner where a big and a small face meet: the big one (area 2 against 0.5) pulls the normal towards it
    pts = torch.tensor([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 1], [0, 1, 0], [5, 5, 5]], dtype=torch.float32)
    tri = torch.tensor([[0, 1, 2], [0, 4, 3]])  # normals +z (area 2) and +x (area 0.5)
    n = vertex_normals(pts, tri)
    want = torch.nn.functional.normalize(torch.tensor([[0.5, 0, 2.0]]), dim=1)[0]  # 4 times less +x than +z
    torch.testing.assert_close(n[0], want, rtol=0, atol=1e-6)
    assert n[5].tolist() == [0.0, 0.0, 0.0]
    assert vertex_normals(pts, torch.zeros(0, 3, dtype=torch.int64)).abs().sum() == 0


@pytest.mark.parametrize("dilate", [0, 1, 2])
def test_support_probes_nearest_first_and_agrees_with_the_whole_neighbourhood(dilate):
    g = torch.Generator().manual_seed(dilate)
    cells = torch.randint(-30, 30, (400, 3), generator=g)
    support = SurfaceSupport(cells, cell_size_m=0.0125, dilate=dilate)
    spread = 2 * dilate + 4  # cells around each picked cell, its supported block in the middle
    near = cells[torch.randint(0, 400, (3000,), generator=g)] + torch.rand(3000, 3, generator=g) * spread
    near = (near - spread / 2 + 0.5) * 0.0125
    far = (torch.rand(500, 3, generator=g, dtype=torch.float64) - 0.5) * 3.0  # many outside the cells' bounds
    points = torch.cat([near.double(), far])
    got = support(points)
    assert torch.equal(got, support.reference(points))
    assert 0.01 < float(got[:3000].float().mean()) < 0.9  # both answers occur
    assert torch.equal(SurfaceSupport(cells[:0], 0.0125, dilate)(points), torch.zeros(len(points), dtype=torch.bool))
