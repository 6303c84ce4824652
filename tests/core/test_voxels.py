"""Sparse voxel map: Morton codes, allocation, vertex sharing, growth with an optimizer, checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.map import (
    CORNER_OFFSETS,
    MORTON_MAX_COORD,
    MORTON_MIN_COORD,
    VoxelMap,
    morton_decode,
    morton_encode,
)
from voxfusion.core.map.index_grid import build_index_grid
from voxfusion.core.map.voxel_map import LEVEL0_GRID_ALIGN


def _reference_morton(x: int, y: int, z: int) -> int:
    """Bit-by-bit interleave of the offset coordinates (x in bit 0)."""
    code = 0
    for b in range(21):
        for a, c in enumerate((x, y, z)):
            code |= (((c + (1 << 20)) >> b) & 1) << (3 * b + a)
    return code


# ---------------------------------------------------------------- Morton codes
def test_morton_matches_bitwise_reference():
    g = torch.Generator().manual_seed(0)
    ijk = torch.randint(MORTON_MIN_COORD, MORTON_MAX_COORD + 1, (50, 3), generator=g)
    special = [[0, 0, 0], [-1, -1, -1], [MORTON_MIN_COORD] * 3, [MORTON_MAX_COORD] * 3,
               [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    ijk = torch.cat([ijk, torch.tensor(special)])
    codes = morton_encode(ijk)
    assert codes.dtype == torch.int64
    assert codes.tolist() == [_reference_morton(*row) for row in ijk.tolist()]
    assert (codes >= 0).all()


def test_morton_round_trip_including_negative_coordinates_and_batch_shapes():
    g = torch.Generator().manual_seed(1)
    ijk = torch.randint(MORTON_MIN_COORD, MORTON_MAX_COORD + 1, (4, 5, 3), generator=g)
    codes = morton_encode(ijk)
    assert codes.shape == (4, 5)
    assert torch.equal(morton_decode(codes), ijk)
    neg = torch.tensor([[-3, -7, -1], [-(1 << 20), 5, -2]])
    assert torch.equal(morton_decode(morton_encode(neg)), neg)


def test_morton_parent_is_code_shifted_by_three():
    ijk = torch.tensor([[5, -3, 8], [-1, -1, -1], [0, 7, -8]])
    parent = morton_decode(morton_encode(ijk) >> 3)
    # on the offset lattice: parent = floor((c + 2^20) / 2) - 2^20
    expected = torch.div(ijk + (1 << 20), 2, rounding_mode="floor") - (1 << 20)
    assert torch.equal(parent, expected)


def test_morton_range_and_shape_errors():
    with pytest.raises(ValidationError) as e:
        morton_encode(torch.tensor([[MORTON_MAX_COORD + 1, 0, 0]]))
    assert e.value.field == "ijk"
    with pytest.raises(ValidationError):
        morton_encode(torch.tensor([[0, MORTON_MIN_COORD - 1, 0]]))
    with pytest.raises(ShapeError):
        morton_encode(torch.zeros(4, 2, dtype=torch.int64))
    with pytest.raises(ValidationError):
        morton_encode(torch.zeros(4, 3))


# ---------------------------------------------------------------- allocation and lookup
def _random_points(n: int, seed: int, scale: float = 3.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g) - 0.5) * 2 * scale


@pytest.mark.parametrize("spread", [3, 40, 100_000])
def test_unique_codes_and_bounded_unique_match_torch_unique(spread: int):
    """The dense-occupancy uniques (allocation, surface cells) against ``torch.unique``: coordinates either
    side of zero in a small box, a frame-sized box, and a box too large for flags (the fallback); the
    bounded unique drops entries outside ``[0, bound)`` such as the -1 "no voxel" keys, on both paths."""
    from voxfusion.core.map.morton import morton_encode, unique_bounded, unique_codes

    g = torch.Generator().manual_seed(spread)
    ijk = torch.randint(-spread, spread, (5000, 3), generator=g)
    ijk[::7] = ijk[3]  # many duplicates
    torch.testing.assert_close(unique_codes(ijk), torch.unique(morton_encode(ijk)), rtol=0, atol=0)
    assert unique_codes(ijk[:0]).numel() == 0
    values = torch.randint(-3, 500, (4000,), generator=g)
    ref = torch.unique(values)
    ref = ref[(ref >= 0) & (ref < 400)]
    for max_dense in (1 << 24, 10):  # flags, and the torch.unique fallback
        torch.testing.assert_close(unique_bounded(values, 400, max_dense), ref, rtol=0, atol=0)
    assert unique_bounded(torch.full((5,), -1), 10).numel() == 0


def test_allocation_is_complete_deduplicated_and_idempotent():
    vm = VoxelMap(voxel_size_m=0.2, seed=0)
    pts = _random_points(2000, 0)
    expected = torch.unique(torch.floor(pts.double() / 0.2).long(), dim=0)
    n_new = vm.allocate(pts)
    assert n_new == vm.n_voxels == expected.shape[0]
    idx = vm.lookup_voxels(pts)
    assert (idx >= 0).all()
    assert torch.equal(vm.voxel_coords[idx], torch.floor(pts.double() / 0.2).long())
    assert torch.equal(vm.voxel_codes, morton_encode(vm.voxel_coords))
    assert vm.allocate(pts) == 0
    assert vm.allocate(pts[:10].flip(0)) == 0
    assert vm.n_voxels == expected.shape[0]
    # a far point is not in the map
    assert vm.lookup_voxels(torch.tensor([[50.0, 0.0, 0.0]])).tolist() == [-1]


def test_allocation_grows_without_bound_anywhere():
    vm = VoxelMap(voxel_size_m=0.05, seed=0)
    total = 0
    for k, centre in enumerate([(0.0, 0.0, 0.0), (-1000.0, 250.0, -3.0), (40000.0, -40000.0, 20.0)]):
        pts = _random_points(300, k, 0.5) + torch.tensor(centre, dtype=torch.float64)
        total += vm.allocate(pts)
        assert (vm.lookup_voxels(pts) >= 0).all()
    assert vm.n_voxels == total
    assert vm.voxel_centres_m.shape == (total, 3)
    # centres are within half a voxel of the points that allocated them (float32 centres: loose at 40 km)
    assert (vm.voxel_centres_m[vm.lookup_voxels(pts)].double() - pts).abs().max() <= 0.025 + 0.01


def test_count_new_voxels_does_not_allocate():
    vm = VoxelMap(0.2, seed=0)
    a = _random_points(500, 1, 1.0)
    b = _random_points(500, 2, 1.0) + 5.0
    vm.allocate(a)
    n_before = vm.n_voxels
    n_new, n_obs = vm.count_new_voxels(torch.cat([a, b]))
    assert vm.n_voxels == n_before
    assert n_obs == n_before
    assert n_new == vm.allocate(b)
    assert vm.count_new_voxels(b) == (0, n_new)
    c = _random_points(300, 3, 1.0) + 2.5  # new voxels; with a and b: the counting allocation says the same
    expected = vm.count_new_voxels(torch.cat([a, b, c]))
    assert vm.allocate_counting(torch.cat([a, b, c])) == expected and expected[0] > 0
    assert vm.count_new_voxels(c) == (0, expected[0])


def test_allocation_rejects_bad_points_naming_the_field():
    vm = VoxelMap(0.2)
    with pytest.raises(ShapeError) as e:
        vm.allocate(torch.zeros(5, 2))
    assert e.value.field == "points_world"
    with pytest.raises(ValidationError) as e:
        vm.allocate(torch.tensor([[0.0, float("nan"), 0.0]]))
    assert e.value.field == "points_world"
    with pytest.raises(ValidationError) as e:
        vm.allocate(torch.tensor([[0.0, 0.0, 300_000.0]], dtype=torch.float64))  # > 2^20 * 0.2 m
    assert e.value.field == "points_world"
    assert vm.n_voxels == 0
    # lookups never raise for far or non-finite points
    assert vm.lookup_voxels(torch.tensor([[float("inf"), 0.0, 0.0], [1e9, 0, 0]])).tolist() == [-1, -1]
    with pytest.raises(ValidationError):
        VoxelMap(voxel_size_m=0.0)


# ---------------------------------------------------------------- dense index grid
def _sorted_code_lookup(vm: VoxelMap, points: torch.Tensor) -> torch.Tensor:
    """Point -> voxel index through the sorted Morton codes only (the path the dense grid replaces)."""
    ijk = vm.points_to_voxel_coords(points)
    inside = ((ijk >= MORTON_MIN_COORD) & (ijk <= MORTON_MAX_COORD)).all(-1)
    idx = vm.lookup_codes(morton_encode(torch.where(inside[:, None], ijk, torch.zeros_like(ijk))))
    return torch.where(inside, idx, torch.full_like(idx, -1))


def _query_points(seed: int, centre: tuple[float, float, float], scale: float) -> torch.Tensor:
    """Points in and around a map: inside the box, beyond it, on voxel faces, non-finite, out of range."""
    c = torch.tensor(centre, dtype=torch.float64)
    inner = _random_points(3000, seed, scale).double() + c
    outer = _random_points(500, seed + 1, 3 * scale).double() + c
    faces = torch.round(inner[:300] / 0.2) * 0.2  # exactly on voxel planes (0.2 m voxels)
    special = torch.tensor([[float("nan"), 0.0, 0.0], [float("inf"), 1.0, 1.0], [-float("inf"), 0.0, 0.0],
                            [1e12, 0.0, 0.0], [0.0, -1e12, 0.0], [0.0, 0.0, 0.0], [-1e-9, -1e-9, -1e-9]],
                           dtype=torch.float64)
    return torch.cat([inner, outer, faces, special])


def test_index_grid_lookup_with_and_without_border_agrees_with_a_dictionary():
    """A grid with a border clamps cells outside onto its empty outer layer; one without tests each cell: both
    return each cell's value and -1 for every cell outside, on every side and far away."""
    g = torch.Generator().manual_seed(0)
    coords = torch.randint(-5, 6, (60, 3), generator=g)
    values = torch.arange(60)
    truth = {}
    for c, v in zip(coords.tolist(), values.tolist(), strict=True):
        truth[tuple(c)] = max(truth.get(tuple(c), -1), v)  # a cell keeps the largest value
    q = torch.cat([torch.randint(-9, 10, (4000, 3), generator=g), coords,
                   torch.tensor([[1 << 40, 0, 0], [0, -(1 << 40), 0], [0, 0, 1 << 40], [-7, 8, -9]])])
    want = torch.tensor([truth.get(tuple(c), -1) for c in q.tolist()])
    for border in (0, 1, 3):
        grid = build_index_grid(coords, values, level=0, border=border, max_cells=1 << 20)
        assert grid.border == border
        assert torch.equal(grid.lookup(q), want), border
        assert torch.equal(grid.lookup(q.reshape(-1, 2, 3)), want.reshape(-1, 2))  # any leading shape
        assert torch.equal(grid.lookup_xyz(*(c.contiguous() for c in q.unbind(-1))), want), border


@pytest.mark.parametrize("budget", [1 << 26, 8])
def test_allocated_lookup_per_axis_matches_the_stacked_one(budget):
    """Coordinates given per axis and as ``[..., 3]`` both find exactly the allocated voxels (a dictionary of
    their coordinates), inactive ones included, through the dense grid and (a budget too small for any grid)
    through the sorted codes."""
    vm = VoxelMap(0.2, seed=0)
    vm.dense_grid_max_cells = budget
    vm.allocate(_random_points(400, 20, 1.5).double())
    vm.set_active(torch.arange(vm.n_voxels) % 3 != 0)
    g = torch.Generator().manual_seed(4)
    lo, hi = vm.voxel_bounds
    q = torch.stack([torch.randint(int(lo[a]) - 3, int(hi[a]) + 4, (3000,), generator=g) for a in range(3)], -1)
    q = torch.cat([q, vm.voxel_coords])
    q = q[: q.shape[0] // 7 * 7].reshape(-1, 7, 3)  # any leading shape
    index = {tuple(c): i for i, c in enumerate(vm.voxel_coords.tolist())}  # the allocated voxels, independently
    want = torch.tensor([index.get(tuple(c), -1) for c in q.reshape(-1, 3).tolist()]).reshape(q.shape[:-1])
    assert torch.equal(vm.lookup_allocated_cells(q), want)
    assert torch.equal(vm.lookup_allocated_xyz(*(c.contiguous() for c in q.unbind(-1))), want)
    assert int((want >= 0).sum()) > 0 and int((want[want >= 0] % 3 == 0).sum()) > 0  # inactive voxels are found too


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (-3000.0, 250.5, -7.3), (150_000.0, -150_000.0, 0.0)])
def test_lookup_via_dense_grid_equals_sorted_codes(centre):
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(_random_points(800, 20, 1.5).double() + torch.tensor(centre, dtype=torch.float64))
    grid = vm.index_grid()
    assert grid is not None and grid.n_occupied == vm.n_voxels and grid.level == 0
    lo, hi = vm.voxel_bounds
    # the box: at least a one-cell border, corners on multiples of LEVEL0_GRID_ALIGN
    a = LEVEL0_GRID_ALIGN
    assert torch.equal(grid.origin, torch.div(lo - 1, a, rounding_mode="floor") * a)
    assert torch.equal(grid.origin + grid.size, (torch.div(hi + 1, a, rounding_mode="floor") + 1) * a)
    q = _query_points(21, centre, 1.5)
    for pts in (q, q.float()):
        got = vm.lookup_voxels(pts)
        want = _sorted_code_lookup(vm, pts)
        assert torch.equal(got, want)
        assert 0 < int((got >= 0).sum()) < pts.shape[0]
    # the dense table holds exactly the allocated voxels
    assert torch.equal(grid.lookup(vm.voxel_coords), torch.arange(vm.n_voxels))
    assert int((grid.table >= 0).sum()) == vm.n_voxels


def test_far_apart_voxels_fall_back_to_sorted_codes():
    """A bounding box beyond the dense-grid budget (clusters ~100 km apart) gets no grid; lookups still work."""
    vm = VoxelMap(0.2, seed=0)
    a = _random_points(300, 22, 1.0).double()
    b = a + torch.tensor([1e5, -1e5, 5e4], dtype=torch.float64)
    vm.allocate(torch.cat([a, b]))
    assert vm.index_grid() is None and vm.index_grid(2) is None  # ~10^16 cells
    q = torch.cat([_query_points(23, (0.0, 0.0, 0.0), 1.0), _query_points(24, (1e5, -1e5, 5e4), 1.0)])
    got = vm.lookup_voxels(q)
    assert torch.equal(got, _sorted_code_lookup(vm, q))
    assert (vm.lookup_voxels(torch.cat([a, b])) >= 0).all()
    # a budget of 0 disables the grid of a small map too, with the same answers
    small = VoxelMap(0.2, seed=0)
    small.allocate(a)
    q = _query_points(25, (0.0, 0.0, 0.0), 1.0)
    with_grid = small.lookup_voxels(q)
    assert small.index_grid() is not None
    small.dense_grid_max_cells = 0
    assert small.index_grid() is None
    assert torch.equal(small.lookup_voxels(q), with_grid)
    with pytest.raises(ValidationError):
        small.dense_grid_max_cells = -1


def test_coarse_index_grid_marks_occupied_octree_blocks():
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(_random_points(400, 26, 2.0))
    for level in (1, 2, 3):
        grid = vm.index_grid(level)
        blocks = torch.unique(torch.div(vm.voxel_coords, 2**level, rounding_mode="floor"), dim=0)
        # the block of a voxel is its Morton parent `level` levels up
        parents = torch.unique(vm.voxel_codes >> (3 * level))
        shift = (1 << 20) - (1 << (20 - level))  # the parent code keys the offset block coordinate
        assert torch.equal(torch.unique(morton_decode(parents) + shift, dim=0), blocks)
        assert blocks.shape[0] == grid.n_occupied
        assert (grid.lookup(blocks) == 0).all()
        everything = torch.stack(torch.meshgrid(*[torch.arange(o, o + s) for o, s in
                                                 zip(grid.origin_xyz, grid.shape, strict=True)],
                                                indexing="ij"), -1).reshape(-1, 3)
        assert int((grid.lookup(everything) >= 0).sum()) == blocks.shape[0]
    with pytest.raises(ValidationError):
        vm.index_grid(-1)
    assert VoxelMap(0.2).index_grid() is None  # empty map


def test_build_index_grid_budget_and_errors():
    ijk = torch.tensor([[0, 0, 0], [3, -2, 5], [-4, 1, 1]])
    g = build_index_grid(ijk, torch.arange(3), level=0, border=2, max_cells=10_000)
    assert g.shape == (12, 8, 10) and g.n_cells == 960 and g.nbytes == 960 * 4
    assert g.lookup(torch.cat([ijk, torch.tensor([[9, 9, 9], [1, 1, 1]])])).tolist() == [0, 1, 2, -1, -1]
    assert build_index_grid(ijk, torch.arange(3), level=0, border=2, max_cells=959) is None
    assert build_index_grid(ijk, torch.zeros(3), level=1, border=0, max_cells=100).shape == (4, 2, 3)
    with pytest.raises(ShapeError):
        build_index_grid(ijk[:, :2], torch.arange(3), level=0, border=1, max_cells=100)
    with pytest.raises(ShapeError):
        build_index_grid(ijk, torch.arange(2), level=0, border=1, max_cells=100)
    with pytest.raises(ShapeError):
        g.lookup(ijk[:, :2])


def test_index_grid_is_rebuilt_on_growth_and_snapshots_keep_theirs():
    vm = VoxelMap(0.2, seed=0)
    a = _random_points(300, 27, 1.0)
    b = _random_points(300, 28, 1.0) + 4.0  # grows the bounding box
    vm.allocate(a)
    snap = vm.snapshot()
    grid = vm.index_grid()
    assert snap.index_grid() is grid  # built before the snapshot, shared
    table_before = grid.table.clone()
    vm.allocate(b)
    assert vm.index_grid() is not grid
    assert torch.equal(grid.table, table_before)  # never modified in place
    assert snap.index_grid() is grid
    assert (snap.lookup_voxels(b) == -1).all() and (snap.lookup_voxels(a) >= 0).all()
    assert (vm.lookup_voxels(b) >= 0).all()
    assert torch.equal(vm.lookup_voxels(torch.cat([a, b])), _sorted_code_lookup(vm, torch.cat([a, b])))
    # growth inside the box rebuilds too
    c = a[:50] + 0.2
    vm.allocate(c)
    assert torch.equal(vm.lookup_voxels(c), _sorted_code_lookup(vm, c))
    # loading a checkpoint and moving devices drop the old grids
    other = VoxelMap(0.2, seed=1)
    other.allocate(b)
    other.index_grid()
    other.load_state_dict(vm.state_dict())
    assert torch.equal(other.lookup_voxels(torch.cat([a, b, c])), vm.lookup_voxels(torch.cat([a, b, c])))
    rep = vm.memory_report()
    assert rep.index_bytes >= vm.index_grid().nbytes + vm.voxel_codes.numel() * 8


# ---------------------------------------------------------------- vertices
def test_neighbouring_voxels_share_vertices():
    vm = VoxelMap(1.0, seed=0)
    centres = torch.tensor([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [1.5, 1.5, 0.5], [1.5, 1.5, 1.5],
                            [5.5, 5.5, 5.5]])
    vm.allocate(centres)
    vid = vm.voxel_vertex_ids
    idx = vm.lookup_voxels(centres).tolist()

    def shared(a: int, b: int) -> int:
        return len(set(vid[idx[a]].tolist()) & set(vid[idx[b]].tolist()))

    assert shared(0, 1) == 4  # face
    assert shared(0, 2) == 2  # edge
    assert shared(0, 3) == 1  # corner
    assert shared(0, 4) == 0
    assert vm.n_vertices == len(set(vid.flatten().tolist()))
    # each voxel's corner c holds the vertex at coords + CORNER_OFFSETS[c]
    assert torch.equal(vm.vertex_codes[vid], morton_encode(vm.voxel_coords[:, None, :] + CORNER_OFFSETS))
    assert torch.equal(vm.vertex_coords[vid], vm.voxel_coords[:, None, :] + CORNER_OFFSETS)


def test_new_embeddings_are_small_seeded_and_only_for_new_vertices():
    a, b = VoxelMap(0.2, seed=7), VoxelMap(0.2, seed=7)
    pts = _random_points(400, 3, 1.0)
    a.allocate(pts)
    b.allocate(pts)
    assert torch.equal(a.embeddings, b.embeddings)
    assert a.embeddings.shape == (a.n_vertices, 16)
    assert 0.005 < float(a.embeddings.detach().std()) < 0.02
    assert a.embeddings.is_leaf and a.embeddings.requires_grad


# ---------------------------------------------------------------- growth + optimizer
def test_growth_keeps_old_embeddings_and_adam_state():
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(_random_points(200, 4, 0.6))
    opt = torch.optim.Adam([vm.embeddings], lr=1e-2)
    for _ in range(3):
        opt.zero_grad()
        (vm.embeddings ** 2).sum().backward()
        opt.step()
    old = vm.embeddings.detach().clone()
    old_state = {k: v.clone() for k, v in opt.state[vm.embeddings].items()}
    n_old = vm.n_vertices

    n_new = vm.allocate(_random_points(200, 5, 0.6) + 2.0, optimizer=opt)
    assert n_new > 0 and vm.n_vertices > n_old
    assert torch.equal(vm.embeddings[:n_old].detach(), old)
    assert opt.param_groups[0]["params"][0] is vm.embeddings
    st = opt.state[vm.embeddings]
    for key in ("exp_avg", "exp_avg_sq"):
        assert st[key].shape == vm.embeddings.shape
        assert torch.equal(st[key][:n_old], old_state[key])
        assert (st[key][n_old:] == 0).all()
    assert torch.equal(st["step"], old_state["step"])
    # the optimizer keeps working on the grown table
    opt.zero_grad()
    (vm.embeddings ** 2).sum().backward()
    opt.step()
    assert not torch.equal(vm.embeddings[n_old:].detach(), torch.zeros_like(vm.embeddings[n_old:]))


def test_grow_optimizer_state_after_several_growths():
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(_random_points(50, 6, 0.4))
    opt = torch.optim.Adam([{"params": [vm.embeddings], "lr": 1e-2}])
    opt.zero_grad()
    vm.embeddings.sum().backward()
    opt.step()
    n0 = vm.n_vertices
    vm.allocate(_random_points(50, 7, 0.4) + 1.0)
    vm.allocate(_random_points(50, 8, 0.4) - 1.0)
    assert vm.grow_optimizer_state(opt) == 1
    assert vm.grow_optimizer_state(opt) == 0
    assert opt.state[vm.embeddings]["exp_avg"].shape == (vm.n_vertices, 16)
    assert (opt.state[vm.embeddings]["exp_avg"][:n0] != 0).all()


# ---------------------------------------------------------------- checkpoints, memory, device
def test_state_dict_round_trip_is_exact():
    vm = VoxelMap(0.1, embed_dim=8, seed=3)
    vm.allocate(_random_points(300, 9, 1.0))
    vm.allocate(_random_points(300, 10, 1.0) + 1.5)
    sd = vm.state_dict()
    vm2 = VoxelMap.from_state_dict(sd)
    assert vm2.voxel_size_m == 0.1 and vm2.embed_dim == 8
    for name in ("voxel_codes", "voxel_coords", "voxel_vertex_ids", "vertex_codes", "embeddings"):
        assert torch.equal(getattr(vm2, name), getattr(vm, name)), name
    q = _random_points(500, 11, 2.5)
    assert torch.equal(vm2.lookup_voxels(q), vm.lookup_voxels(q))
    # loading continues to allocate consistently
    p = _random_points(100, 12, 1.0) - 3.0
    assert vm2.allocate(p) == vm.allocate(p)
    assert torch.equal(vm2.voxel_vertex_ids, vm.voxel_vertex_ids)
    assert torch.equal(vm2.embeddings, vm.embeddings)  # the seeded generator's state travels too
    bad = dict(sd, voxel_vertex_ids=sd["voxel_vertex_ids"][:-1])
    with pytest.raises(ShapeError):
        VoxelMap.from_state_dict(bad)
    with pytest.raises(ValidationError):
        VoxelMap.from_state_dict({k: v for k, v in sd.items() if k != "embeddings"})


def test_memory_report_and_device_move():
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(_random_points(100, 13, 0.5))
    dec = torch.nn.Linear(16, 4)
    rep = vm.memory_report(dec)
    assert rep.n_voxels == vm.n_voxels and rep.n_vertices == vm.n_vertices
    assert rep.embedding_bytes == vm.n_vertices * 16 * 4
    assert rep.decoder_bytes == (16 * 4 + 4) * 4
    assert rep.total_bytes == rep.embedding_bytes + rep.index_bytes + rep.decoder_bytes
    assert vm.to("cpu") is vm and vm.device.type == "cpu"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_map_matches_cpu_map():
    pts = _random_points(1000, 14, 2.0)
    cpu, gpu = VoxelMap(0.2, seed=1), VoxelMap(0.2, seed=1, device="cuda")
    cpu.allocate(pts)
    gpu.allocate(pts.cuda())
    assert torch.equal(gpu.voxel_codes.cpu(), cpu.voxel_codes)
    assert torch.equal(gpu.embeddings.detach().cpu(), cpu.embeddings.detach())
    assert torch.equal(gpu.lookup_voxels(pts.cuda()).cpu(), cpu.lookup_voxels(pts))
    moved = VoxelMap.from_state_dict(cpu.state_dict()).to("cuda")
    assert torch.equal(moved.lookup_voxels(pts.cuda()).cpu(), cpu.lookup_voxels(pts))


def test_pack_flags_matches_numpy_packbits_little_endian():
    """The surface mask's bit packing (eight flags per multiply, no loop over bits) against numpy's reference."""
    from voxfusion.core.map.voxel_map import _pack_flags

    g = torch.Generator().manual_seed(0)
    for n, p in ((8, 0.5), (64, 0.1), (3 * 4096, 0.3), (4096, 1.0), (4096, 0.0)):
        flags = torch.rand(n, generator=g) < p
        want = np.packbits(flags.numpy(), bitorder="little")
        assert np.array_equal(_pack_flags(flags).numpy(), want), (n, p)
    assert _pack_flags(torch.ones(16, dtype=torch.bool)).tolist() == [255, 255]
    assert _pack_flags(torch.arange(16) == 9).tolist() == [0, 2]  # flag 9: byte 1, bit 1


def test_popcount_rows_matches_the_byte_table():
    """The surface counts' popcount (SWAR on int64 words, whose shifts are arithmetic) against a per-byte table,
    with bytes whose top bit is set (negative words) included."""
    from voxfusion.core.map.voxel_map import _popcount_rows, _popcount_rows_reference

    g = torch.Generator().manual_seed(0)
    rows = torch.randint(0, 256, (37, 512), generator=g).to(torch.uint8)
    rows[0] = 255  # every bit: 4096
    rows[1] = 0
    rows[2] = 128  # only the top bit of every byte
    got = _popcount_rows(rows)
    assert torch.equal(got, _popcount_rows_reference(rows))
    assert got[:3].tolist() == [4096, 0, 512]
    assert torch.equal(got[3:], torch.tensor([bin(int(b)).count("1") for b in rows[3:].flatten()]).view(34, 512).sum(1))
    assert _popcount_rows(torch.zeros(0, 512, dtype=torch.uint8)).shape == (0,)


@pytest.mark.parametrize("max_dense", [1 << 22, 64])  # the dense box, and the sort of pairs it falls back to
def test_tagged_unique_codes_are_the_distinct_pairs_by_code_then_tag(max_dense):
    from voxfusion.core.map.morton import morton_encode, unique_codes, unique_codes_tagged

    g = torch.Generator().manual_seed(2)
    ijk = torch.randint(-6, 6, (500, 3), generator=g)
    tag = torch.randint(0, 4, (500,), generator=g)
    codes, tags = unique_codes_tagged(ijk, tag, 4, max_dense)
    want = torch.unique(torch.stack([morton_encode(ijk), tag], 1), dim=0)  # sorted by code, then tag
    assert torch.equal(codes, want[:, 0]) and torch.equal(tags, want[:, 1])
    plain, zeros = unique_codes_tagged(ijk, None, 1, max_dense)
    assert torch.equal(plain, unique_codes(ijk)) and not zeros.any()


def test_allocating_several_point_sets_at_once_counts_as_allocating_them_in_turn():
    g = torch.Generator().manual_seed(3)
    sets = [(torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * s + c
            for s, c in ((1.0, 0.0), (1.0, 0.3), (0.5, 2.0))]
    sets.append(sets[0][100:200])  # seen before in the same batch
    turn, once = VoxelMap(0.1, seed=0), VoxelMap(0.1, seed=0)
    turn.allocate(sets[0][:50])
    once.allocate(sets[0][:50])
    counts = [turn.allocate_counting(p) for p in sets]
    assert once.allocate_counting_batch(sets) == counts
    assert counts[3][0] == 0 and counts[2][1] == 0 and counts[1][0] > 0  # nothing new, nothing seen, some of each
    assert sorted(turn.voxel_codes.tolist()) == sorted(once.voxel_codes.tolist())
    assert torch.equal(once.voxel_codes[50:].sort().values, once.voxel_codes[50:])  # new ones in Morton order
    assert once.allocate_counting_batch(sets) == [(0, c[0] + c[1]) for c in counts]  # idempotent
    with pytest.raises(ValidationError):
        once.allocate_counting_batch([sets[0], torch.full((2, 3), float("nan"), dtype=torch.float64)])
