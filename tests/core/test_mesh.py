"""Sparse marching cubes (voxfusion.core.mesh): watertightness, accuracy, sparsity, colours, export."""

from __future__ import annotations

import io
from collections import defaultdict

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.mesh import GREY_RGB, export_mesh, extract_mesh, mesh_bytes
from voxfusion.core.mesh.cases import CENTRE_CODE, EDGE_CORNERS, triangle_table

VOXEL_M = 0.2
CENTRE = np.array([0.013, -0.021, 0.037])  # off the lattice
RADIUS_M = 0.5


def sphere_query(points: torch.Tensor, centre=CENTRE, radius=RADIUS_M, rgb=False, valid=None):
    sdf = (points.double() - torch.as_tensor(centre)).norm(dim=1) - radius
    colour = ((points.double() + 1.0) / 2.0).clamp(0, 1).float() if rgb else None
    ok = torch.ones(len(points), dtype=torch.bool) if valid is None else valid(points)
    return sdf.float(), colour, ok


def box_voxels(lo: int, hi: int) -> torch.Tensor:
    """All voxels ijk with lo <= i, j, k < hi, ``[M, 3]`` int64."""
    r = torch.arange(lo, hi)
    return torch.cartesian_prod(r, r, r)


def shell_voxels(centre=CENTRE, radius=RADIUS_M, band=1.5 * VOXEL_M) -> torch.Tensor:
    """Voxels whose centres are within ``band`` of the sphere surface."""
    ijk = box_voxels(-6, 6)
    d = np.linalg.norm((ijk.numpy() + 0.5) * VOXEL_M - centre, axis=1) - radius
    return ijk[torch.from_numpy(np.abs(d) < band)]


def boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """Vertex index pairs ``[B, 2]`` of edges used by exactly one face."""
    edges, counts = np.unique(np.sort(mesh.edges, axis=1), axis=0, return_counts=True)
    assert counts.max() <= 2, "an edge is shared by more than two faces"
    return edges[counts == 1]


def vertex_links_are_cycles(mesh: trimesh.Trimesh) -> bool:
    """Every vertex of a closed mesh has one cycle of faces around it (a manifold vertex)."""
    link = defaultdict(dict)
    for face in mesh.faces:
        for i in range(3):
            link[face[i]][face[(i + 1) % 3]] = face[(i + 2) % 3]
    for ring in link.values():
        start = next(iter(ring))
        cur, steps = ring[start], 1
        while cur != start and steps <= len(ring):
            cur, steps = ring.get(cur, start), steps + 1
        if steps != len(ring):
            return False
    return True


@pytest.fixture(scope="module")
def sphere_mesh() -> trimesh.Trimesh:
    return extract_mesh(shell_voxels(), VOXEL_M, lambda p: sphere_query(p, rgb=True), mesh_res=8)


def test_sphere_is_watertight_welded_and_accurate(sphere_mesh):
    m = sphere_mesh
    assert len(m.faces) > 1000
    assert m.is_watertight and m.is_winding_consistent
    assert len(np.unique(m.vertices.round(9), axis=0)) == len(m.vertices)
    assert m.euler_number == 2
    assert vertex_links_are_cycles(m)
    radial_error = np.abs(np.linalg.norm(m.vertices - CENTRE, axis=1) - RADIUS_M)
    assert radial_error.max() < 2e-3
    outward = np.einsum("ij,ij->i", m.face_normals, m.triangles_center - CENTRE)
    assert (outward > 0).all()
    assert m.volume == pytest.approx(4 / 3 * np.pi * RADIUS_M**3, rel=5e-3)


def test_dense_block_matches_skimage_vertices():
    """With every voxel allocated, the vertices are those of skimage's marching cubes on the dense grid."""
    centre, radius, res = np.array([0.31, 0.29, 0.33]), 0.21, 4
    ijk = box_voxels(0, 3)
    m = extract_mesh(ijk, VOXEL_M, lambda p: sphere_query(p, centre, radius), mesh_res=res)
    step = VOXEL_M / res
    axis = np.arange(3 * res + 1) * step
    lattice = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)
    grid = np.linalg.norm(lattice - centre, axis=-1) - radius
    ref_v, ref_f, _, _ = marching_cubes(grid.astype(np.float32), level=0.0, spacing=(step,) * 3)
    assert len(m.vertices) == len(ref_v)
    reference = trimesh.Trimesh(ref_v, ref_f, process=False)
    dist, _ = trimesh.proximity.ProximityQuery(reference).vertex(m.vertices)
    assert dist.max() < 1e-3 * step + 1e-5  # ours keep 1e-3 of an edge away from its ends
    assert np.median(dist) < 1e-6  # and sample a hair inside voxels
    assert m.volume == pytest.approx(reference.volume, rel=1e-3)


def test_tilted_plane_has_no_cracks():
    """A plane through an irregular band of voxels: open only along the outer rim of the allocated box."""
    normal = np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0])
    offset = 0.531

    def plane(points):
        sdf = points.double() @ torch.from_numpy(normal) - offset
        return sdf.float(), None, torch.ones(len(points), dtype=torch.bool)

    ijk = torch.cartesian_prod(torch.arange(0, 6), torch.arange(0, 6), torch.arange(-2, 8))
    d = (ijk.numpy() + 0.5) * VOXEL_M @ normal - offset
    ijk = ijk[torch.from_numpy(np.abs(d) < 1.5 * VOXEL_M)]
    m = extract_mesh(ijk, VOXEL_M, plane, mesh_res=5)
    assert m.is_winding_consistent
    assert np.abs(m.vertices @ normal - offset).max() < 1e-5
    assert (m.face_normals @ normal > 0.999).all()  # towards positive SDF
    rim = m.vertices[boundary_edges(m)]  # [B, 2, 3]
    on_rim = (np.abs(rim[..., :2]) < 1e-9) | (np.abs(rim[..., :2] - 6 * VOXEL_M) < 1e-9)
    assert len(rim) > 0 and on_rim.any(-1).all()
    assert m.area == pytest.approx((6 * VOXEL_M) ** 2 / normal[2], rel=1e-5)


def hashed_field(seed: int, res: int, n_vox: int):
    """A rough random SDF on the lattice (many ambiguous faces), positive on the block's border."""

    def query(points):
        lattice = torch.round(points.double() * res / VOXEL_M).long()
        key = (lattice[:, 0] * 1000 + lattice[:, 1]) * 1000 + lattice[:, 2] + seed * 7919
        h = torch.sin(key.double() * 12.9898) * 43758.5453
        sdf = (h - h.floor()) - 0.5
        border = ((lattice == 0) | (lattice == n_vox * res)).any(1)
        return torch.where(border, 0.5, sdf).float(), None, torch.ones(len(points), dtype=torch.bool)

    return query


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_field_gives_closed_manifold(seed):
    m = extract_mesh(box_voxels(0, 3), VOXEL_M, hashed_field(seed, 4, 3), mesh_res=4)
    assert len(m.faces) > 1000
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert vertex_links_are_cycles(m)
    assert len(np.unique(m.vertices.round(9), axis=0)) == len(m.vertices)
    lattice = m.vertices / (VOXEL_M / 4)
    on_lattice_axes = (np.abs(lattice - np.round(lattice)) < 1e-6).sum(1)
    assert (on_lattice_axes >= 2).mean() > 0.99  # vertices on lattice edges ...
    assert (on_lattice_axes < 2).any()  # ... and (these seeds) some loop-centre vertices


def test_table_rows_use_exactly_the_crossed_edges():
    triangles, centres = triangle_table()
    for row in range(0, 256 * 64, 7):
        case = row // 64
        negative = [(case >> c) & 1 for c in range(8)]
        crossed = {e for e, (a, b) in enumerate(EDGE_CORNERS) if negative[a] != negative[b]}
        entries = triangles[row][triangles[row, :, 0] >= 0]
        used = {int(e) for e in entries.ravel() if e < CENTRE_CODE}
        assert used == crossed, row
        loops = {int(e) - CENTRE_CODE for e in entries.ravel() if e >= CENTRE_CODE}
        assert loops == {j for j in range(4) if centres[row, j]}, row
    assert (centres > 0).any()  # some ambiguous rows need a centre vertex


def test_faces_only_in_allocated_voxels(sphere_mesh):
    full = shell_voxels()
    half = full[(full[:, 2].double() + 0.5) * VOXEL_M > CENTRE[2]]
    m = extract_mesh(half, VOXEL_M, sphere_query, mesh_res=8)
    assert 0 < len(m.faces) < len(sphere_mesh.faces)
    assert not m.is_watertight and len(boundary_edges(m)) > 0
    allocated = {tuple(v) for v in half.tolist()}
    eps = 1e-9
    for c in m.triangles_center:  # the centroid lies in (the closure of) an allocated voxel
        candidates = {tuple(np.floor((c + d) / VOXEL_M).astype(int)) for d in (-eps, eps)}
        assert candidates & allocated
    # the faces are those of the fully allocated shell (up to the sub-micrometre sampling nudge)
    _, nearest = cKDTree(sphere_mesh.triangles_center).query(m.triangles_center)
    assert np.abs(sphere_mesh.triangles[nearest] - m.triangles).max() < 5e-5


def test_cells_with_invalid_corners_produce_nothing():
    def query(points):
        return sphere_query(points, valid=lambda p: p[:, 0] < float(CENTRE[0]))

    m = extract_mesh(shell_voxels(), VOXEL_M, query, mesh_res=8)
    assert len(m.faces) > 0 and not m.is_watertight
    assert m.vertices[:, 0].max() < CENTRE[0]
    assert m.vertices[:, 0].max() > CENTRE[0] - VOXEL_M / 8 - 1e-9  # up to the last valid cell

    def nan_right(points):
        sdf, rgb, ok = sphere_query(points)
        return torch.where(points[:, 0] < float(CENTRE[0]), sdf, torch.nan), rgb, ok

    assert np.array_equal(extract_mesh(shell_voxels(), VOXEL_M, nan_right).faces, m.faces)


def test_field_that_finds_voxels_by_floor_sees_every_sample(sphere_mesh):
    """Like the neural field: valid only where floor(p / v) is allocated, NaN SDF and black colour elsewhere.

    Samples and vertices on the far faces of the allocated region (or rounded across a face in float32)
    must still be looked up inside an allocated voxel, so nothing is lost at the region's borders.
    """
    voxels = shell_voxels()
    allocated = {tuple(v) for v in voxels.tolist()}

    def floor_field(points):
        sdf, rgb, _ = sphere_query(points, rgb=True)
        ijk = torch.floor(points.double() / VOXEL_M).long().tolist()
        valid = torch.tensor([tuple(v) in allocated for v in ijk])
        return torch.where(valid, sdf, torch.nan), rgb * valid[:, None], valid

    m = extract_mesh(voxels, VOXEL_M, floor_field)
    assert np.array_equal(m.faces, sphere_mesh.faces)
    np.testing.assert_allclose(m.vertices, sphere_mesh.vertices, atol=1e-6)
    assert np.array_equal(m.visual.vertex_colors, sphere_mesh.visual.vertex_colors)

    half = voxels[voxels[:, 0] < 0]  # cut through the sphere: x = 0 is the far face of the region
    allocated = {tuple(v) for v in half.tolist()}
    cut = extract_mesh(half, VOXEL_M, floor_field)
    reference = extract_mesh(half, VOXEL_M, lambda p: sphere_query(p, rgb=True))
    assert np.array_equal(cut.faces, reference.faces)
    assert cut.vertices[:, 0].max() == 0.0  # the cells touching the cut are there


def test_vertex_colours_come_from_the_colour_head(sphere_mesh):
    expected = np.clip((sphere_mesh.vertices + 1.0) / 2.0, 0, 1) * 255
    colours = sphere_mesh.visual.vertex_colors
    assert colours.dtype == np.uint8 and colours.shape == (len(sphere_mesh.vertices), 4)
    assert np.abs(colours[:, :3].astype(float) - expected).max() <= 0.51
    assert (colours[:, 3] == 255).all()
    grey = extract_mesh(box_voxels(0, 3), VOXEL_M, lambda p: sphere_query(p, [0.3] * 3, 0.2), mesh_res=2)
    assert len(grey.vertices) > 0 and (grey.visual.vertex_colors[:, :3] == GREY_RGB).all()


def test_chunking_and_voxel_order_do_not_change_the_mesh(sphere_mesh):
    voxels = shell_voxels()
    shuffled = torch.cat([voxels[torch.randperm(len(voxels), generator=torch.Generator().manual_seed(0))],
                          voxels[:10]])
    for chunk in (37, 5000):
        m = extract_mesh(shuffled, VOXEL_M, lambda p: sphere_query(p, rgb=True), chunk_points=chunk)
        assert np.array_equal(m.vertices, sphere_mesh.vertices)
        assert np.array_equal(m.faces, sphere_mesh.faces)
        assert np.array_equal(m.visual.vertex_colors, sphere_mesh.visual.vertex_colors)


def test_each_lattice_sample_is_queried_once_in_bounded_chunks():
    calls = []

    def query(points):
        calls.append(len(points))
        return sphere_query(points, [0.2, 0.1, 0.1], 0.15)

    ijk = np.array([[0, 0, 0], [1, 0, 0]])
    whole = extract_mesh(ijk, VOXEL_M, query, mesh_res=4, chunk_points=1000)
    n_lattice = (2 * 4 + 1) * 5 * 5
    assert sum(calls) == n_lattice + len(whole.vertices)  # samples once, then vertices for colour
    calls.clear()
    m = extract_mesh(ijk, VOXEL_M, query, mesh_res=4, chunk_points=100)
    assert max(calls) <= 100
    # one voxel per chunk: the 25 samples of the shared face are queried by both chunks, same mesh
    assert sum(calls) == n_lattice + 25 + len(m.vertices)
    assert np.array_equal(m.faces, whole.faces) and np.array_equal(m.vertices, whole.vertices)


def test_empty_inputs_give_an_empty_mesh():
    for ijk in (np.zeros((0, 3), dtype=np.int64), np.array([[20, 20, 20]])):
        m = extract_mesh(ijk, VOXEL_M, sphere_query)
        assert m.vertices.shape == (0, 3) and m.faces.shape == (0, 3)


def test_invalid_arguments_raise():
    ijk = box_voxels(0, 2)
    with pytest.raises(ShapeError):
        extract_mesh(torch.zeros(4, 2, dtype=torch.long), VOXEL_M, sphere_query)
    with pytest.raises(ValidationError, match="voxel_coords"):
        extract_mesh(ijk.float(), VOXEL_M, sphere_query)
    with pytest.raises(ValidationError, match="voxel_size_m"):
        extract_mesh(ijk, 0.0, sphere_query)
    with pytest.raises(ValidationError, match="mesh_res"):
        extract_mesh(ijk, VOXEL_M, sphere_query, mesh_res=0)
    with pytest.raises(ValidationError, match="chunk_points"):
        extract_mesh(ijk, VOXEL_M, sphere_query, chunk_points=0)
    with pytest.raises(ValidationError, match="voxel_coords"):
        extract_mesh(np.array([[0, 0, 0], [2**18, 0, 0]]), VOXEL_M, sphere_query)
    with pytest.raises(ShapeError, match="sdf"):
        extract_mesh(ijk, VOXEL_M, lambda p: (sphere_query(p)[0][:, None], None, sphere_query(p)[2]))
    with pytest.raises(ShapeError, match="rgb"):
        extract_mesh(ijk, VOXEL_M, lambda p: (sphere_query(p)[0], torch.zeros(len(p), 4), sphere_query(p)[2]))
    with pytest.raises(ValidationError, match="query_fn"):
        extract_mesh(ijk, VOXEL_M, lambda p: sphere_query(p)[0])


def test_ply_round_trip_is_binary_with_colours(sphere_mesh, tmp_path):
    path = export_mesh(sphere_mesh, tmp_path / "mesh.ply")
    data = path.read_bytes()
    header = data[: data.index(b"end_header")].decode()
    assert header.startswith("ply\nformat binary_little_endian 1.0")
    assert "property uchar red" in header and "property uchar alpha" in header
    back = trimesh.load(path, process=False)
    np.testing.assert_allclose(back.vertices, sphere_mesh.vertices, atol=1e-6)
    assert np.array_equal(back.faces, sphere_mesh.faces)
    assert np.array_equal(back.visual.vertex_colors, sphere_mesh.visual.vertex_colors)
    assert export_mesh(sphere_mesh, "ply") == data == mesh_bytes(sphere_mesh, ".PLY")


def test_glb_round_trip(sphere_mesh, tmp_path):
    data = mesh_bytes(sphere_mesh, "glb")
    assert data[:4] == b"glTF"
    back = trimesh.load(io.BytesIO(data), file_type="glb", force="mesh", process=False)
    np.testing.assert_allclose(back.vertices, sphere_mesh.vertices, atol=1e-6)
    assert np.array_equal(back.faces, sphere_mesh.faces)
    assert np.array_equal(back.visual.vertex_colors, sphere_mesh.visual.vertex_colors)
    assert export_mesh(sphere_mesh, tmp_path / "m.glb").read_bytes() == data


def test_obj_round_trip(sphere_mesh, tmp_path):
    path = export_mesh(sphere_mesh, tmp_path / "mesh.obj")
    back = trimesh.load(path, process=False)
    np.testing.assert_allclose(back.vertices, sphere_mesh.vertices, atol=1e-7)
    assert np.array_equal(back.faces, sphere_mesh.faces)
    assert np.abs(back.visual.vertex_colors.astype(int) - sphere_mesh.visual.vertex_colors).max() <= 1


def test_unknown_or_impossible_exports_raise(sphere_mesh, tmp_path):
    with pytest.raises(ValidationError, match="path"):
        export_mesh(sphere_mesh, tmp_path / "mesh.stl")
    with pytest.raises(ValidationError, match="fmt"):
        mesh_bytes(sphere_mesh, "fbx")
    empty = extract_mesh(np.zeros((0, 3), dtype=np.int64), VOXEL_M, sphere_query)
    with pytest.raises(ValidationError, match="mesh"):
        mesh_bytes(empty, "glb")
    assert mesh_bytes(empty, "ply").startswith(b"ply\n")


def test_two_level_extraction_matches_one_level_on_a_shuffled_irregular_map():
    """The coarse pass's near-surface cells feed the fine pass in any order; the mesh must equal the
    one-level mesh (regression: unsorted cells once lost a tenth of a room's faces)."""
    centre = torch.tensor([0.013, -0.021, 0.037])

    def field(p):  # a tilted plane 3 mm off the voxel borders, and a small sphere
        plane = (p.double() @ torch.tensor([0.05, -0.03, 1.0]).double()) / 1.0017 - 0.003
        ball = (p.double() - centre.double() - 0.3).norm(dim=1) - 0.12
        return torch.minimum(plane, ball).float(), None, torch.ones(len(p), dtype=torch.bool)

    ijk = box_voxels(-3, 4)
    keep = torch.from_numpy(np.random.default_rng(0).random(len(ijk)) < 0.8)
    ijk = ijk[keep][torch.randperm(int(keep.sum()), generator=torch.Generator().manual_seed(1))]
    one = extract_mesh(ijk, VOXEL_M, field, mesh_res=20, coarse_res=0)
    two = extract_mesh(ijk, VOXEL_M, field, mesh_res=20, chunk_points=5000)
    assert len(one.faces) > 10000
    assert len(two.faces) == len(one.faces)
    _, nearest = cKDTree(one.triangles_center).query(two.triangles_center)
    assert np.abs(one.triangles[nearest] - two.triangles).max() < 5e-5


@pytest.mark.parametrize("R", [1, 2, 5])
def test_each_cells_samples_are_named_by_the_owner_the_plain_rule_finds(R):
    """The per-cell owner rule (26 neighbours per cell, 27 kinds of sample) against the plain one (up to 8 searches
    per sample) on an irregular map: every sample of every cell, also where chunks split the cells."""
    from voxfusion.core.mesh.extract import _Cells

    g = torch.Generator().manual_seed(3)
    coords = torch.unique(torch.randint(-4, 4, (300, 3), generator=g), dim=0)  # sorted, with holes
    cells = _Cells(coords, R)
    for start, n in ((0, len(coords)), (17, 40), (len(coords) - 5, 5)):
        rows, offsets = cells.owned_samples(start, n)
        lattice = (coords[start:start + n, None, :] * R + cells.samples.local).view(-1, 3)
        expected = cells.owners(lattice)
        assert torch.equal(coords[rows.view(-1)], expected)
        assert torch.equal(expected * R + cells.samples.local[offsets.view(-1)], lattice)
    # a point shared by several cells gets one name from each of them
    rows, offsets = cells.owned_samples(0, len(coords))
    lattice = (coords[:, None, :] * R + cells.samples.local).view(-1, 3)
    names = rows.view(-1) * (R + 1) ** 3 + offsets.view(-1)
    assert len(torch.unique(names)) == len(torch.unique(lattice, dim=0))
