"""Renderer: camera rays, ray-voxel intersection (vs brute force), sampling, analytic-SDF rendering, grads."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import voxfusion.core.render.raycast as raycast_module
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import ConfigError, ShapeError
from voxfusion.core.geometry import backproject_depth, make_intrinsics
from voxfusion.core.map import VoxelMap
from voxfusion.core.map.field import FieldConfig, NeuralField, SDFDecoder
from voxfusion.core.render.volume import (
    RenderConfig,
    VoxelHits,
    camera_rays,
    image_chunk_rays,
    intersect_voxels,
    intersect_voxels_fixed,
    intersect_voxels_reference,
    render_depth_image,
    render_rays,
    render_rays_fixed,
    sample_along_hits,
)

K_TEST = make_intrinsics(60.0, 60.0, 15.5, 11.5)  # 32 x 24 image


def _se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """4x4 pose from a twist (rho, phi) via the matrix exponential (differentiable)."""
    A = torch.zeros(4, 4, dtype=xi.dtype)
    wx, wy, wz = xi[3], xi[4], xi[5]
    A = A.index_put((torch.tensor([0, 0, 1, 1, 2, 2]), torch.tensor([1, 2, 0, 2, 0, 1])),
                    torch.stack([-wz, wy, wz, -wx, -wy, wx]))
    A = A.index_put((torch.tensor([0, 1, 2]), torch.tensor([3, 3, 3])), xi[:3])
    return torch.linalg.matrix_exp(A)


# ---------------------------------------------------------------- brute-force reference
def brute_force_hits(vm: VoxelMap, o: torch.Tensor, d: torch.Tensor, d_max: float, max_hits: int):
    """Slab test of every ray against every voxel (float64); returns per-ray lists of (idx, t_in, t_out)."""
    lo = vm.voxel_coords.double() * vm.voxel_size_m  # [M, 3]
    hi = lo + vm.voxel_size_m
    o, d = o.double()[:, None, :], d.double()[:, None, :]
    nz = d != 0
    sd = torch.where(nz, d, torch.ones_like(d))
    ta, tb = (lo - o) / sd, (hi - o) / sd
    inside = (o >= lo) & (o <= hi)
    inf = torch.full_like(ta, math.inf)
    tmin = torch.where(nz, torch.minimum(ta, tb), torch.where(inside, -inf, inf)).max(-1).values
    tmax = torch.where(nz, torch.maximum(ta, tb), torch.where(inside, inf, -inf)).min(-1).values
    t_in, t_out = tmin.clamp(min=0), tmax.clamp(max=d_max)
    hit = t_out > t_in
    out = []
    for r in range(o.shape[0]):
        ids = torch.nonzero(hit[r]).squeeze(1)
        order = torch.argsort(t_in[r, ids])
        ids = ids[order][:max_hits]
        out.append((ids.tolist(), t_in[r, ids], t_out[r, ids]))
    return out


def _random_sparse_map(seed: int, voxel: float = 0.2) -> VoxelMap:
    g = torch.Generator().manual_seed(seed)
    coords = torch.stack(torch.meshgrid(*[torch.arange(-5, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keep = torch.rand(coords.shape[0], generator=g) < 0.25
    vm = VoxelMap(voxel, seed=seed)
    vm.allocate((coords[keep].double() + 0.5) * voxel)
    return vm


def _random_rays(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    o = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 4.0  # inside and outside the map
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d * (0.5 + torch.rand(n, 1, generator=g, dtype=torch.float64))  # non-unit lengths
    d[:20, 0] = 0.0  # axis-parallel components
    d[20:30, 1:] = 0.0
    return o, d


@pytest.mark.parametrize("impl", [intersect_voxels, intersect_voxels_reference])
@pytest.mark.parametrize("seed,max_hits", [(0, 1000), (1, 3)])
def test_intersection_matches_brute_force(seed, max_hits, impl):
    vm = _random_sparse_map(seed)
    o, d = _random_rays(300, seed + 10)
    d_max = 2.5
    hits = impl(vm, o, d, d_max, max_hits)
    ref = brute_force_hits(vm, o, d, d_max, max_hits)
    assert hits.voxel_idx.shape[1] <= max_hits
    n_hit_rays = 0
    for r, (ids, t_in, t_out) in enumerate(ref):
        got = hits.voxel_idx[r][hits.voxel_idx[r] >= 0].tolist()
        assert got == ids, f"ray {r}"
        k = len(ids)
        assert torch.allclose(hits.t_entry[r, :k], t_in, atol=1e-9)
        assert torch.allclose(hits.t_exit[r, :k], t_out, atol=1e-9)
        assert bool(hits.hit[r]) == (k > 0)
        n_hit_rays += k > 0
    assert 50 < n_hit_rays < 300  # the test exercises both hits and misses


@pytest.mark.parametrize("impl", [intersect_voxels, intersect_voxels_reference])
def test_intersection_chunking_does_not_change_the_result(monkeypatch, impl):
    vm = _random_sparse_map(8)
    o, d = _random_rays(200, 9)
    whole = impl(vm, o, d, 2.5, 1000)
    monkeypatch.setattr(raycast_module, "_EVENT_BUDGET", 300)  # a few rays per chunk
    chunked = impl(vm, o, d, 2.5, 1000)
    assert_same_hits(chunked, whole)


def test_a_gpu_walks_bigger_chunks_than_a_cpu(monkeypatch):
    """A chunk's fixed cost is launches and read-backs on a GPU: its budget is larger there, so the same rays make
    fewer chunks, each row in exactly one (the results do not depend on the chunking: the test above)."""
    cpu = raycast_module._event_budget(torch.device("cpu"))
    gpu = raycast_module._event_budget(torch.device("cuda"))
    assert cpu == raycast_module._EVENT_BUDGET and gpu == cpu * raycast_module._GPU_BUDGET_FACTOR > cpu
    planes = torch.randint(1, 40, (5000,), generator=torch.Generator().manual_seed(0))
    monkeypatch.setattr(raycast_module, "_EVENT_BUDGET", 3000)  # a few hundred rays per CPU chunk
    on_cpu = raycast_module._chunks(planes)
    monkeypatch.setattr(raycast_module, "_event_budget", lambda device: 3000 * raycast_module._GPU_BUDGET_FACTOR)
    as_on_gpu = raycast_module._chunks(planes)
    assert len(as_on_gpu) < len(on_cpu)
    for chunks in (on_cpu, as_on_gpu):
        rows = torch.cat([r for r, _ in chunks])
        assert torch.equal(rows.sort().values, torch.arange(planes.numel()))
        assert all(int(planes[r].max()) <= p_max for r, p_max in chunks)


# ---------------------------------------------------------------- fast intersection == reference
def assert_same_hits(got: VoxelHits, want: VoxelHits) -> None:
    """Same ordered voxel lists and bit-identical entry / exit times (the fast path is exact)."""
    for name in ("t_entry", "t_exit", "voxel_idx", "hit"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert torch.equal(a, b), f"{name}: {int((a != b).sum())} entries differ"


def _force_coarse_level(monkeypatch, level: int) -> None:
    """Make the fast path skip empty space with blocks of ``2**level`` voxels (0: never skip)."""
    monkeypatch.setattr(raycast_module, "_COARSE_LEVELS", (level,) if level else ())
    monkeypatch.setattr(raycast_module, "_COARSE_GAIN", math.inf)


@pytest.mark.parametrize("level", [0, 1, 2, 3])
@pytest.mark.parametrize("n_rays", [1, 7, 300])
def test_fast_intersection_equals_reference_on_random_rays(monkeypatch, level, n_rays):
    _force_coarse_level(monkeypatch, level)
    g = torch.Generator().manual_seed(n_rays)
    vm = _random_sparse_map(n_rays + level)
    o, d = _random_rays(max(n_rays, 30), n_rays + 20)
    o, d = o[-n_rays:], d[-n_rays:]  # small batches are oblique rays, the large one has axis-parallel ones
    t_far = torch.rand(n_rays, generator=g, dtype=torch.float64) * 3
    for max_hits, tf, dtype in ((1000, None, torch.float64), (1000, t_far, torch.float32), (3, t_far, torch.float64),
                                (1, None, torch.float32)):
        args = (vm, o.to(dtype), d.to(dtype), 2.5, max_hits, tf)
        assert_same_hits(intersect_voxels(*args), intersect_voxels_reference(*args))


def _lattice_map_and_rays(voxel: float, offset: int, n: int = 600):
    """A sparse map of voxels ``offset`` voxels from the origin, and ``n`` rays from lattice points, edge midpoints
    and face centres along integer-ratio directions (tied crossings), with tiny and zero components; returns the
    map, origins, directions and the generator for more draws."""
    g = torch.Generator().manual_seed(offset + 7)
    coords = torch.stack(torch.meshgrid(*[torch.arange(-6, 6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    vm = VoxelMap(voxel, seed=0)
    vm.allocate((coords[torch.rand(coords.shape[0], generator=g) < 0.15].double() + 0.5 + offset) * voxel)
    o = (torch.randint(-8, 8, (n, 3), generator=g).double() + offset) * voxel
    o[n // 2:] += torch.randint(0, 2, (n - n // 2, 3), generator=g).double() * voxel / 2
    d = torch.randint(-3, 4, (n, 3), generator=g).double()
    d[d.abs().sum(1) == 0] = 1.0
    d[:50] *= 0.1
    d[50:100, 0] = 1e-12
    return vm, o, d, g


@pytest.mark.parametrize("level", [0, 2])
@pytest.mark.parametrize("voxel,offset", [(0.25, 0), (0.2, -1234), (0.1, 300_000)])
def test_fast_intersection_equals_reference_on_lattice_aligned_rays(monkeypatch, level, voxel, offset):
    """Origins on grid planes, edges and corners; integer-ratio directions that cross edges and corners
    exactly (tied crossings); zero and tiny direction components; maps near and far from the origin."""
    _force_coarse_level(monkeypatch, level)
    vm, o, d, g = _lattice_map_and_rays(voxel, offset)
    n = o.shape[0]
    t_far = torch.rand(n, generator=g, dtype=torch.float64) * 5
    for d_max, max_hits in ((100.0, 1000), (3.0, 4)):
        for tf in (None, t_far):
            args = (vm, o, d, d_max, max_hits, tf)
            fast, ref = intersect_voxels(*args), intersect_voxels_reference(*args)
            assert_same_hits(fast, ref)
    assert 0 < int(ref.hit.sum()) < n


def _synthetic_room_map(voxel: float) -> tuple[VoxelMap, list]:
    cap = SyntheticCapture(SyntheticConfig(n_frames=12, width=64, height=48))
    vm = VoxelMap(voxel, seed=0)
    views = []
    for i in (0, 11):
        f = cap[i]
        vm.allocate(torch.as_tensor(backproject_depth(f.depth_m, f.K, f.T_world_cam)))
        views.append(f)
    return vm, views


@pytest.mark.parametrize("voxel", [0.2, 0.05])
def test_fast_intersection_equals_reference_on_synthetic_room(voxel):
    """Camera rays of the synthetic room, as mapping (t_far = depth + tr) and full-image rendering cast them;
    the automatic coarse level choice skips empty space for the fine map and not for the coarse one."""
    vm, views = _synthetic_room_map(voxel)
    cfg = RenderConfig()
    for f in views:
        o, d = camera_rays(f.K, f.T_world_cam, width=64, height=48, dtype=torch.float32)
        depth = torch.as_tensor(f.depth_m).reshape(-1)
        t_far = torch.where(depth > 0, depth + cfg.truncation_m, torch.full_like(depth, 1e-3))
        for tf, max_hits in ((t_far, cfg.max_hits_for(voxel)), (None, cfg.max_hits_for(voxel)), (None, 2)):
            args = (vm, o, d, cfg.max_distance_m, max_hits, tf)
            assert_same_hits(intersect_voxels(*args), intersect_voxels_reference(*args))
    o, d = camera_rays(views[0].K, views[0].T_world_cam, width=64, height=48, dtype=torch.float64)
    rays = raycast_module._clip_rays(vm, o, d, cfg.max_distance_m, None)
    mean_cells = float(((rays.t1 - rays.t0)[:, None] * rays.d.abs()).sum(-1)[rays.ok].mean()) / voxel
    assert (raycast_module._skip_grid(vm, mean_cells) is not None) == (voxel < 0.1)


def test_fast_intersection_walks_that_leave_the_dense_grid_are_exact(monkeypatch):
    """Rays clipped to a box larger than the dense grid step out of it: cells outside are no hits."""
    for level in (0, 2):
        _force_coarse_level(monkeypatch, level)
        vm = _random_sparse_map(5)
        lo, hi = vm.voxel_bounds
        monkeypatch.setattr(vm, "_bounds", (lo - 3, hi + 2))
        o, d = _random_rays(300, 15)
        for tf in (None, torch.rand(300, dtype=torch.float64) * 3):
            args = (vm, o * 1.5, d, 3.5, 1000, tf)
            assert_same_hits(intersect_voxels(*args), intersect_voxels_reference(*args))


def test_fast_intersection_without_dense_grid_uses_sorted_codes():
    """Maps whose bounding box exceeds the dense-grid budget (far-apart clusters) take the reference path."""
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(torch.tensor([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [2e4, 2e4, -2e4]], dtype=torch.float64))
    assert vm.index_grid() is None  # 1e5 voxels apart on each axis
    o = torch.tensor([[-1.0, 0.15, 0.15], [2e4 + 0.1, 2e4 + 0.1, -2e4 + 5.0]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    hits = intersect_voxels(vm, o, d, 100.0, 10)
    i0, i1, i2 = vm.lookup_voxels(torch.tensor([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [2e4, 2e4, -2e4]])).tolist()
    assert hits.voxel_idx.tolist() == [[i0, i1], [i2, -1]]
    assert_same_hits(hits, intersect_voxels_reference(vm, o, d, 100.0, 10))
    small = _random_sparse_map(6)
    o, d = _random_rays(200, 16)
    fast = intersect_voxels(small, o, d, 2.5, 1000)
    small.dense_grid_max_cells = 0
    assert small.index_grid() is None
    assert_same_hits(intersect_voxels(small, o, d, 2.5, 1000), fast)


def test_intersection_respects_per_ray_far_bound_and_empty_map():
    vm = _random_sparse_map(2)
    o, d = _random_rays(100, 3)
    t_far = torch.rand(100, dtype=torch.float64) * 2
    hits = intersect_voxels(vm, o, d, 2.5, 1000, t_far=t_far)
    ref = brute_force_hits(vm, o, d, 2.5, 1000)
    for r, (ids, t_in, _) in enumerate(ref):
        expect = [i for i, t in zip(ids, t_in.tolist(), strict=True) if t < t_far[r]]
        assert hits.voxel_idx[r][hits.voxel_idx[r] >= 0].tolist() == expect
    empty = intersect_voxels(VoxelMap(0.2), o, d, 2.5, 10)
    assert empty.voxel_idx.shape == (100, 0) and not empty.hit.any()
    with pytest.raises(ShapeError):
        intersect_voxels(vm, o, d[:, :2], 2.5, 10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_fast_intersection_on_cuda_equals_reference():
    vm, views = _synthetic_room_map(0.05)
    f = views[0]
    o, d = camera_rays(f.K, f.T_world_cam, width=64, height=48)
    t_far = torch.as_tensor(f.depth_m).reshape(-1) + 0.1
    cpu = intersect_voxels_reference(vm, o, d, 10.0, 100, t_far)
    vm.to("cuda")
    for tf in (None, t_far.cuda()):
        fast = intersect_voxels(vm, o.cuda(), d.cuda(), 10.0, 100, tf)
        assert_same_hits(fast, intersect_voxels_reference(vm, o.cuda(), d.cuda(), 10.0, 100, tf))
    assert torch.equal(fast.voxel_idx.cpu(), cpu.voxel_idx)
    torch.testing.assert_close(fast.t_entry.cpu(), cpu.t_entry, atol=1e-9, rtol=0)


# ---------------------------------------------------------------- fixed-shape walk == fast intersection
def assert_fixed_walk_exact(vm: VoxelMap, o: torch.Tensor, d: torch.Tensor, d_max: float, max_hits: int) -> None:
    """The fixed walk's hits are the fast path's (bit-identical) plus padding columns that hold nothing, and it
    has no doubt about them."""
    fast = intersect_voxels(vm, o, d, d_max, max_hits)
    fixed, doubt = intersect_voxels_fixed(vm, o, d, d_max, max_hits)
    assert not bool(doubt)
    m = fast.voxel_idx.shape[1]
    assert fixed.voxel_idx.shape[1] >= m
    assert_same_hits(VoxelHits(fixed.t_entry[:, :m], fixed.t_exit[:, :m], fixed.voxel_idx[:, :m], fixed.hit), fast)
    assert (fixed.voxel_idx[:, m:] == -1).all() and (fixed.t_entry[:, m:] == 0).all()
    assert (fixed.t_exit[:, m:] == 0).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fixed_walk_equals_fast_intersection_on_random_rays(seed):
    vm = _random_sparse_map(seed)
    o, d = _random_rays(300, seed + 30)
    o[5], d[6], d[7] = math.nan, math.inf, 0.0  # rays without a walk get no hits, and do not upset the others
    for max_hits, dtype in ((1000, torch.float64), (3, torch.float32), (1, torch.float64)):
        assert_fixed_walk_exact(vm, o.to(dtype), d.to(dtype), 2.5, max_hits)
    hits, _ = intersect_voxels_fixed(vm, o, d, 2.5, 1000)
    assert not hits.hit[5:8].any() and hits.hit.any()


@pytest.mark.parametrize("voxel,offset", [(0.25, 0), (0.2, -1234), (0.1, 300_000)])
def test_fixed_walk_equals_fast_intersection_on_lattice_aligned_rays(voxel, offset):
    """Origins on grid planes, edges and corners, tied crossings, tiny direction components, maps far out."""
    vm, o, d, _ = _lattice_map_and_rays(voxel, offset)
    for d_max, max_hits in ((100.0, 1000), (3.0, 4)):
        assert_fixed_walk_exact(vm, o, d, d_max, max_hits)


@pytest.mark.parametrize("voxel", [0.2, 0.05])
def test_fixed_walk_equals_fast_intersection_on_synthetic_room(voxel):
    vm, views = _synthetic_room_map(voxel)
    cfg = RenderConfig()
    for f in views:
        o, d = camera_rays(f.K, f.T_world_cam, width=64, height=48, dtype=torch.float32)
        assert_fixed_walk_exact(vm, o, d, cfg.max_distance_m, cfg.max_hits_for(voxel))


def test_fixed_walk_splits_its_rows_by_the_event_budget(monkeypatch):
    vm = _random_sparse_map(4)
    o, d = _random_rays(200, 41)
    whole, _ = intersect_voxels_fixed(vm, o, d, 2.5, 1000)
    monkeypatch.setattr(raycast_module, "_EVENT_BUDGET", 300)  # a few rays per chunk
    chunked, doubt = intersect_voxels_fixed(vm, o, d, 2.5, 1000)
    assert_same_hits(chunked, whole)
    assert not bool(doubt)


def test_a_map_too_long_for_the_fixed_walk_renders_through_the_fast_walk(monkeypatch):
    """Every ray walks the whole box's crossings in the fixed walk: past a box length it leaves the image to the
    data-dependent walk (which skips empty space), with the same image."""
    cfg = RenderConfig(step_ratio=0.05, max_distance_m=5.0)
    vm = _band_map(sphere_sdf, 0.2, 1.0, 0.35)
    o, d = camera_rays(K_TEST, torch.eye(4), width=32, height=24, dtype=torch.float32)
    planes = raycast_module.fixed_walk_planes(vm.index_grid())
    assert intersect_voxels_fixed(vm, o, d, 5.0, 100) is not None
    monkeypatch.setattr(raycast_module, "_FIXED_WALK_MAX_PLANES", planes - 1)
    assert intersect_voxels_fixed(vm, o, d, 5.0, 100) is None and render_rays_fixed(vm, sphere_sdf, o, d, cfg) is None
    got = render_depth_image(vm, sphere_sdf, K_TEST, torch.eye(4), 32, 24, cfg, fixed_walk=True)
    want = render_depth_image(vm, sphere_sdf, K_TEST, torch.eye(4), 32, 24, cfg, fixed_walk=False)
    assert got.valid.any() and all(torch.equal(a, b) for a, b in zip(got, want, strict=True))


def test_fixed_walk_doubts_walks_it_cannot_vouch_for_and_the_image_falls_back():
    """Rays clipped to a box larger than the dense grid (the walk leaves it), or a first-plane search cut short:
    the walk says so on the device, and the image renders through the fast path instead, unchanged."""
    cfg = RenderConfig(step_ratio=0.05, max_distance_m=5.0)
    T = torch.eye(4)
    vm = _band_map(sphere_sdf, 0.2, 1.0, 0.35)
    want = render_depth_image(vm, sphere_sdf, K_TEST, T, 32, 24, cfg, fixed_walk=False)
    o, d = camera_rays(K_TEST, T, width=32, height=24, dtype=torch.float32)
    lo, hi = vm.voxel_bounds
    wide = VoxelMap(0.2, seed=0)
    wide.allocate(torch.as_tensor(vm.voxel_coords).double().add(0.5).mul(0.2))
    wide._bounds = (lo - 20, hi + 20)  # beyond the grid's border and alignment
    assert bool(intersect_voxels_fixed(wide, o, d, 5.0, 100)[1])
    assert render_rays_fixed(wide, sphere_sdf, o, d, cfg) is None
    got = render_depth_image(wide, sphere_sdf, K_TEST, T, 32, 24, cfg, fixed_walk=True)
    for a, b in zip(got, render_depth_image(wide, sphere_sdf, K_TEST, T, 32, 24, cfg, fixed_walk=False), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(render_depth_image(vm, sphere_sdf, K_TEST, T, 32, 24, cfg, fixed_walk=True), want, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("block", [1, 4])
def test_first_plane_search_in_fixed_rounds_is_the_search_until_settled(block):
    """Two correction rounds (the fixed walk's) give what correcting until nothing moves gives, and say they
    settled; a round that still moved is reported (the walk then doubts its result)."""
    g = torch.Generator().manual_seed(block)
    vm = _random_sparse_map(3)
    o, d = _random_rays(400, 3)
    rays = raycast_module._clip_rays(vm, o, d, 5.0, None)
    o, d, t0, t1 = rays.o[rays.ok], rays.d[rays.ok], rays.t0[rays.ok], rays.t1[rays.ok]
    ts = t0 + (t1 - t0) * torch.rand(t0.shape[0], generator=g, dtype=torch.float64)
    lo, hi = vm.voxel_bounds
    cell0 = torch.floor((o + d * t0[:, None]) / 0.2).clamp(lo.double(), hi.double()).to(torch.int64)
    w = raycast_module._Walk(o, d, torch.where(d != 0, d, torch.ones_like(d)), torch.sign(d).to(torch.int64),
                             cell0, t0, t1, ts, t1)
    q_ref, entry_ref, none = raycast_module._first_planes(w, block, 0.2)
    q, entry, unsettled = raycast_module._first_planes(w, block, 0.2, rounds=2)
    assert none is None and not bool(unsettled)
    assert torch.equal(q, q_ref) and torch.equal(entry, entry_ref)
    q1, _, moved = raycast_module._first_planes(w, block, 0.2, rounds=1)
    assert torch.equal(q1, q_ref) or bool(moved)


def test_an_image_renders_the_same_with_the_fixed_walk_and_depth_alone_skips_colour():
    """The fixed walk (a GPU's default) changes the read-backs, not the image; ``with_color=False`` gives the same
    depth (the colour head skipped; the SDF row alone differs by float rounding) and no colour."""
    vm, views = _synthetic_room_map(0.2)
    decoder = SDFDecoder(FieldConfig(use_color=True))
    cfg = RenderConfig()
    f = views[0]
    for field in (decoder, sphere_sdf):
        for with_color in (True, False):
            args = (vm, field, f.K, f.T_world_cam, 64, 48, cfg)
            plain = render_depth_image(*args, with_color=with_color, fixed_walk=False)
            fixed = render_depth_image(*args, with_color=with_color, fixed_walk=True)
            for a, b in zip(plain, fixed, strict=True):
                assert (a is None and b is None) or torch.equal(a, b)
            assert (plain.color is None) == (not with_color)
        full = render_depth_image(*args, with_color=True)
        torch.testing.assert_close(plain.depth, full.depth, atol=1e-5, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_fixed_walk_on_cuda_renders_the_fast_paths_image_with_fewer_waits():
    """On a GPU the image goes through the fixed walk by default (it applies here), renders what the fast path
    renders there (and, within float rounding, on the CPU), and waits for the device fewer times."""
    import warnings

    vm, views = _synthetic_room_map(0.2)
    decoder = SDFDecoder(FieldConfig(use_color=True)).requires_grad_(False)
    cfg = RenderConfig()
    f = views[0]
    cpu = render_depth_image(vm, decoder, f.K, f.T_world_cam, 64, 48, cfg, fixed_walk=False)
    vm.to("cuda")
    decoder.cuda()
    o, d = camera_rays(f.K, f.T_world_cam, width=64, height=48, dtype=torch.float32)
    assert render_rays_fixed(vm, decoder, o.cuda(), d.cuda(), cfg) is not None  # no doubt, no fall-back
    for with_color in (True, False):
        args = (vm, decoder, f.K, f.T_world_cam, 64, 48, cfg)
        fixed = render_depth_image(*args, with_color=with_color)
        plain = render_depth_image(*args, with_color=with_color, fixed_walk=False)
        for a, b in zip(fixed, plain, strict=True):
            assert (a is None and b is None) or torch.equal(a, b)
    torch.testing.assert_close(fixed.depth.cpu(), cpu.depth, atol=1e-4, rtol=0)

    def waits(fixed_walk: bool) -> int:
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                render_depth_image(vm, decoder, f.K, f.T_world_cam, 64, 48, cfg, with_color=False,
                                   fixed_walk=fixed_walk)
            finally:
                torch.cuda.set_sync_debug_mode("default")
        return sum("synchroniz" in str(w.message) for w in caught)

    assert waits(True) < waits(False)


# ---------------------------------------------------------------- rays and sampling
def test_camera_rays_have_unit_z_and_reproduce_backprojection():
    g = torch.Generator().manual_seed(0)
    xi = torch.randn(6, generator=g, dtype=torch.float64) * 0.3
    T = _se3_exp(xi)
    o, d = camera_rays(K_TEST, T, width=32, height=24, dtype=torch.float64)
    assert o.shape == d.shape == (32 * 24, 3)
    d_cam = d @ T[:3, :3]
    assert torch.allclose(d_cam[:, 2], torch.ones(32 * 24, dtype=torch.float64))
    depth = np.random.default_rng(0).uniform(0.5, 3.0, (24, 32)).astype(np.float32)
    pts = backproject_depth(depth, K_TEST, T.numpy())
    ours = o + d * torch.from_numpy(depth.reshape(-1, 1).astype(np.float64))
    assert np.allclose(ours.numpy(), pts, atol=1e-6)
    uv = torch.tensor([[3.0, 7.0], [15.5, 11.5]])
    o2, d2 = camera_rays(torch.from_numpy(K_TEST), T, pixels_uv=uv, dtype=torch.float64)
    assert torch.allclose(d2[0], d[7 * 32 + 3]) and torch.allclose(d2[1], T[:3, 2])
    with pytest.raises(ShapeError):
        camera_rays(K_TEST, torch.eye(3), width=4, height=4)


def test_sampling_covers_hit_segments_at_the_step():
    vm = _random_sparse_map(4)
    o, d = _random_rays(200, 5)
    hits = intersect_voxels(vm, o, d, 2.5, 1000)
    dn = d.norm(dim=-1)
    step = 0.02
    smp = sample_along_hits(hits, dn, step, training=False)
    seg_len = ((hits.t_exit - hits.t_entry) * (hits.voxel_idx >= 0)).sum(1) * dn
    assert torch.equal(smp.mask.sum(1), torch.ceil(seg_len / step - 1e-9).long())
    t = torch.where(smp.mask, smp.t, torch.full_like(smp.t, math.inf))
    # every sample lies inside the hit segment of its voxel, ascending along the ray
    rows, cols = torch.nonzero(smp.mask, as_tuple=True)
    seg = (hits.voxel_idx[rows] == smp.voxel_idx[rows, cols][:, None]).double().argmax(1)
    assert (smp.t[rows, cols] >= hits.t_entry[rows, seg] - 1e-12).all()
    assert (smp.t[rows, cols] <= hits.t_exit[rows, seg] + 1e-12).all()
    assert (t[:, 1:] >= t[:, :-1]).all()
    # training: seeded jitter, reproducible and different from the midpoints
    a = sample_along_hits(hits, dn, step, True, torch.Generator().manual_seed(1))
    b = sample_along_hits(hits, dn, step, True, torch.Generator().manual_seed(1))
    assert torch.equal(a.t, b.t) and torch.equal(a.mask, smp.mask) and not torch.equal(a.t, smp.t)


# ---------------------------------------------------------------- rendering analytic SDFs
def _band_map(sdf_fn, voxel: float, extent: float, band: float) -> VoxelMap:
    """Allocate every voxel whose centre is within ``band`` of the zero set of ``sdf_fn``."""
    n = int(round(2 * extent / voxel))
    ax = (torch.arange(n, dtype=torch.float64) + 0.5) * voxel - extent
    c = torch.stack(torch.meshgrid(ax, ax, ax + 2.0, indexing="ij"), -1).reshape(-1, 3)
    s, _ = sdf_fn(c, None)
    vm = VoxelMap(voxel, seed=0)
    vm.allocate(c[s.abs() <= band])
    return vm


def plane_sdf(p, _idx):
    """Plane z = 2.0 facing the camera at the origin; metres."""
    return 2.0 - p[:, 2], None


_TILT_N = torch.tensor([0.0, 0.6, -0.8], dtype=torch.float64)  # unit normal facing the camera


def tilted_plane_sdf(p, _idx):
    """Plane through (0, 0, 2) tilted by 37 degrees about the x axis."""
    return (p - torch.tensor([0.0, 0.0, 2.0], dtype=p.dtype)) @ _TILT_N.to(p.dtype), None


def sphere_sdf(p, _idx):
    centre = torch.tensor([0.1, -0.05, 2.2], dtype=p.dtype)
    return (p - centre).norm(dim=-1) - 0.5, torch.full((p.shape[0], 3), 0.25, dtype=p.dtype)


def test_an_image_renders_the_same_in_one_call_or_in_chunks():
    """The device's chunk (one call of 65536 rays on a GPU, 4096 on a CPU) changes the calls, not the image."""
    cfg = RenderConfig(step_ratio=0.05, max_distance_m=5.0)
    T = torch.eye(4)
    vm = _band_map(sphere_sdf, 0.2, 1.0, 0.35)
    assert image_chunk_rays(torch.device("cpu")) == 4096 and image_chunk_rays(torch.device("cuda")) == 65536
    whole = render_depth_image(vm, sphere_sdf, K_TEST, T, 32, 24, cfg)  # 768 rays: one call
    parts = render_depth_image(vm, sphere_sdf, K_TEST, T, 32, 24, cfg, chunk=100)
    assert whole.valid.any()
    for a, b in zip(whole, parts, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("fixed_walk", [False, True])
def test_an_image_render_records_no_autograd_graph(monkeypatch, fixed_walk):
    """A whole image (occlusion, evaluation) is inference: its field queries build no autograd graph, even on a map
    and decoder that are training (the CPU path was 10-40 % slower with one)."""
    from voxfusion.core.render import volume as render_module

    vm = VoxelMap(0.2, 4)
    vm.allocate(torch.tensor([[0.1, 0.1, 0.5], [0.3, 0.1, 0.5]]))
    decoder = SDFDecoder(FieldConfig(embed_dim=4, sdf_hidden=8, color_hidden=8))
    assert vm.embeddings.requires_grad and next(decoder.parameters()).requires_grad
    seen = []
    composite = render_module.composite

    def spy(sdf, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen.append((torch.is_grad_enabled(), sdf.requires_grad))
        return composite(sdf, *args, **kwargs)

    monkeypatch.setattr(render_module, "composite", spy)
    image = render_depth_image(vm, decoder, K_TEST, torch.eye(4), 16, 12, RenderConfig(), fixed_walk=fixed_walk)
    assert seen and all(flags == (False, False) for flags in seen)
    assert not image.depth.requires_grad


def test_rendered_depth_of_analytic_planes_and_sphere_is_within_millimetres():
    cfg = RenderConfig(step_ratio=0.05, max_distance_m=5.0)
    T = torch.eye(4)
    o, d = camera_rays(K_TEST, T, width=32, height=24, dtype=torch.float64)
    for fn in (plane_sdf, tilted_plane_sdf, sphere_sdf):
        vm = _band_map(fn, 0.2, 1.0, 0.35)
        img = render_depth_image(vm, fn, K_TEST, T, 32, 24, cfg, chunk=200)
        # exact ray-surface depth and cosine of the incidence angle
        if fn is sphere_sdf:
            c = torch.tensor([0.1, -0.05, 2.2], dtype=torch.float64)
            a, b = (d * d).sum(-1), -2 * (d * c).sum(-1)
            disc = b * b - 4 * a * ((c * c).sum() - 0.25)
            exact = (-b - disc.clamp(min=0).sqrt()) / (2 * a)
            normal = (d * exact[:, None] - c) / 0.5
            hit = disc > 0
        else:
            normal = _TILT_N if fn is tilted_plane_sdf else torch.tensor([0.0, 0.0, -1.0]).double()
            exact = (2.0 * normal[2]) / (d @ normal)
            normal = normal.expand_as(d)
            hit = torch.ones(32 * 24, dtype=torch.bool)
        cos = -(normal * d).sum(-1) / d.norm(dim=-1)
        valid = img.valid.reshape(-1)
        err = (img.depth.reshape(-1).double() - exact).abs()
        # the weights' intrinsic bias grows on curved surfaces seen at grazing angles
        assert valid[hit & (cos > 0.3)].all(), fn.__name__
        assert err[hit & (cos > 0.5)].max() < 5e-3, (fn.__name__, float(err[hit & (cos > 0.5)].max()))
        assert err[hit & (cos > 0.8)].max() < 1e-3, (fn.__name__, float(err[hit & (cos > 0.8)].max()))
        if fn is sphere_sdf:
            assert torch.allclose(img.color.reshape(-1, 3)[valid], torch.full((int(valid.sum()), 3), 0.25))
            assert not valid[disc < -0.05].any()
        else:
            assert img.color is None


def test_samples_behind_first_crossing_plus_truncation_get_no_weight():
    # a 0.6 m thick slab [2.0, 2.6]: front face at 2.0, back face (- to +) at 2.6
    def slab(p, _idx):
        return (p[:, 2] - 2.3).abs() - 0.3, None

    def flipped(p, _idx):
        return 0.3 - (p[:, 2] - 2.3).abs(), None

    vm = _band_map(slab, 0.2, 0.6, 0.5)
    o, d = camera_rays(K_TEST, torch.eye(4), pixels_uv=torch.tensor([[15.5, 11.5], [5.0, 5.0]]))
    cfg = RenderConfig(step_ratio=0.05, max_distance_m=4.0)
    out = render_rays(vm, slab, o, d, cfg)
    assert torch.allclose(out.depth, torch.full((2,), 2.0), atol=2e-3)
    beyond = out.t > 2.0 + cfg.truncation_m / out.dir_norm[:, None] + 0.02
    assert (out.weights[beyond] == 0).all() and (out.sample_mask & beyond).any()
    assert out.surface.all()
    # an SDF with no front-facing crossing keeps all samples (no surface found)
    out2 = render_rays(vm, flipped, o, d, cfg)
    assert not out2.surface.any() and out2.hit.all()


def test_rays_missing_the_map_render_nothing():
    vm = _band_map(plane_sdf, 0.2, 0.4, 0.3)
    o = torch.zeros(3, 3)
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = render_rays(vm, plane_sdf, o, d, RenderConfig())
    assert out.hit.tolist() == [False, False, True]
    assert out.depth[:2].tolist() == [0.0, 0.0] and out.weight_sum[:2].tolist() == [0.0, 0.0]
    empty = render_rays(VoxelMap(0.2), plane_sdf, o, d, RenderConfig())
    assert not empty.hit.any() and empty.depth.shape == (3,)


def test_gradients_flow_to_embeddings_decoder_and_pose():
    vm = _band_map(plane_sdf, 0.2, 0.6, 0.3)
    dec = SDFDecoder()
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    T = _se3_exp(xi)
    uv = torch.rand(64, 2, generator=torch.Generator().manual_seed(0)) * torch.tensor([31.0, 23.0])
    o, d = camera_rays(K_TEST, T, pixels_uv=uv)
    gen = torch.Generator().manual_seed(0)
    out = render_rays(vm, dec, o, d, RenderConfig(), training=True, generator=gen)
    assert out.hit.all()
    (out.depth.sum() + out.color.sum()).backward()
    assert xi.grad is not None and xi.grad.abs().sum() > 0
    assert vm.embeddings.grad is not None and vm.embeddings.grad.abs().sum() > 0
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in dec.parameters())
    # NeuralField and a raw decoder render identically
    with torch.no_grad():
        a = render_rays(vm, dec, o.detach(), d.detach(), RenderConfig())
        b = render_rays(vm, NeuralField(vm, dec), o.detach(), d.detach(), RenderConfig())
    assert torch.equal(a.depth, b.depth)


def test_render_config_validation_and_max_hits_derivation():
    assert RenderConfig(max_distance_m=10.0).max_hits_for(0.2) == math.floor(math.sqrt(3) * 50) + 4
    assert RenderConfig(max_hits=7).max_hits_for(0.2) == 7
    for bad in ({"truncation_m": 0.0}, {"step_ratio": 1.5}, {"max_hits": 0}, {"max_distance_m": -1.0}):
        with pytest.raises(ConfigError):
            RenderConfig(**bad)


def test_voxel_hits_dataclass_shapes_are_consistent():
    vm = _random_sparse_map(6)
    o, d = _random_rays(50, 7)
    h = intersect_voxels(vm, o.float(), d.float(), 2.5, 5)
    assert isinstance(h, VoxelHits)
    assert h.t_entry.dtype == torch.float32
    assert h.t_entry.shape == h.t_exit.shape == h.voxel_idx.shape
    assert ((h.voxel_idx >= 0).sum(1) > 0).eq(h.hit).all()


# ---------------------------------------------------------------- the mapping renderer (fixed samples per ray)
def test_band_samples_are_sorted_strata_in_front_of_and_inside_the_band():
    from voxfusion.core.render.volume import band_samples

    depth = torch.tensor([2.0, 0.15, 3.0], dtype=torch.float64)
    dn = torch.tensor([1.0, 1.0, 1.3], dtype=torch.float64)
    tr, rng = 0.1, 0.4
    for training in (False, True):
        t = band_samples(depth, dn, 10, 6, tr, rng, training, torch.Generator().manual_seed(0))
        assert t.shape == (3, 16) and (t >= 0).all()
        assert (t[:, 1:] >= t[:, :-1]).all()
        dist = (depth[:, None] - t) * dn[:, None]  # metres in front of the observed surface
        assert (dist[:, 6:].abs() <= tr + 1e-9).all()  # the band
        assert (dist[[0, 2], :6] >= tr - 1e-9).all() and (dist[[0, 2], :6] <= tr + rng + 1e-9).all()
        assert (t[1, :6] <= 0.15 - tr + 1e-9).all()  # squeezed in front of the camera, never behind it
    mid = band_samples(depth, dn, 10, 6, tr, rng, False)
    torch.testing.assert_close(mid[0, 6:], 2.0 - tr + (torch.arange(10, dtype=torch.float64) + 0.5) * 0.02)


def _analytic_band_scenes():
    """The band renderer's analytic scenes: ``(cfg, fn, voxel_map, origins, dirs, exact_depth)`` for the
    fronto-parallel and the tilted plane 2 m away, seen by a 32x24 camera at the identity pose."""
    cfg = RenderConfig(step_ratio=0.05, max_distance_m=5.0)
    o, d = camera_rays(K_TEST, torch.eye(4), width=32, height=24, dtype=torch.float64)
    for fn in (plane_sdf, tilted_plane_sdf):
        normal = _TILT_N if fn is tilted_plane_sdf else torch.tensor([0.0, 0.0, -1.0]).double()
        yield cfg, fn, _band_map(fn, 0.2, 1.0, 0.35), o, d, (2.0 * normal[2]) / (d @ normal)


def test_band_renderer_matches_the_voxel_renderer_on_analytic_surfaces():
    """The fixed-shape mapping renderer against the reference (``render_rays``) where depth is known: at the
    strata midpoints the same surfaces within a millimetre of each other and of the exact depth; jittered
    (training) within a millimetre on average."""
    from voxfusion.core.render.volume import render_band

    for cfg, fn, vm, o, d, exact in _analytic_band_scenes():
        ref = render_rays(vm, fn, o, d, cfg)
        for training in (False, True):
            out = render_band(vm, fn, o, d, exact, cfg, n_free=6, free_range_m=0.4, training=training,
                              generator=torch.Generator().manual_seed(0))
            assert out.hit.all() and out.surface.all(), fn.__name__
            assert out.t.shape == (32 * 24, 6 + 20)  # 2 tr / step = 20 band samples: a fixed shape
            err = (out.depth.double() - exact).abs()
            if training:  # jittered strata: unbiased, a few millimetres of noise per ray
                assert err.mean() < 1e-3 and err.max() < 5e-3, (fn.__name__, float(err.mean()), float(err.max()))
            else:
                assert err.max() < 1e-3, (fn.__name__, float(err.max()))
                torch.testing.assert_close(out.depth, ref.depth, atol=1e-3, rtol=0)


def test_band_renderer_with_fewer_band_strata_stays_unbiased():
    """``n_band`` (the CPU preset's ``mapping.band_samples: 5``, 4 cm strata for a 1 cm weight scale): the
    shape follows it, the strata midpoints still render the plane within 2 mm, and jittered strata are noisier
    per ray (centimetres) but unbiased over the rays."""
    from voxfusion.core.render.volume import render_band

    for cfg, fn, vm, o, d, exact in _analytic_band_scenes():
        for training in (False, True):
            out = render_band(vm, fn, o, d, exact, cfg, n_free=4, free_range_m=0.4, training=training,
                              generator=torch.Generator().manual_seed(0), n_band=5)
            assert out.t.shape == (32 * 24, 4 + 5) and out.surface.all(), fn.__name__
            err = out.depth.double() - exact
            if training:
                assert abs(float(err.mean())) < 1.5e-3 and err.abs().max() < 0.04, (fn.__name__, float(err.mean()))
            else:
                assert err.abs().max() < 2e-3, (fn.__name__, float(err.abs().max()))


def test_band_renderer_masks_samples_outside_the_map_and_trains_the_map():
    """Samples outside allocated voxels get no weight and no gradient; the rest reach the embeddings."""
    from voxfusion.core.render.volume import render_band

    vm = _band_map(plane_sdf, 0.2, 0.4, 0.15)  # a thin sheet of voxels around z = 2
    dec = SDFDecoder()
    o, d = camera_rays(K_TEST, torch.eye(4), pixels_uv=torch.tensor([[15.5, 11.5], [16.0, 12.0]]))
    depth = torch.tensor([2.0, 2.0])
    out = render_band(vm, dec, o, d, depth, RenderConfig(), n_free=6, free_range_m=2.0, training=True,
                      generator=torch.Generator().manual_seed(0))
    far_free = (depth[:, None] - out.t) > 0.45  # more than one voxel in front of the sheet: outside the map
    assert far_free.any() and not out.sample_mask[far_free].any()
    assert (out.weights[~out.sample_mask] == 0).all() and (out.sdf[~out.sample_mask] == 0).all()
    out.depth.sum().backward()
    assert vm.embeddings.grad is not None and vm.embeddings.grad.abs().sum() > 0


def test_band_renderer_on_an_empty_map_renders_nothing():
    from voxfusion.core.render.volume import render_band

    o, d = camera_rays(K_TEST, torch.eye(4), pixels_uv=torch.tensor([[15.5, 11.5]]))
    out = render_band(VoxelMap(0.2), SDFDecoder(), o, d, torch.tensor([2.0]), RenderConfig(), 6, 0.4)
    assert not out.hit.any() and out.depth.tolist() == [0.0]


def test_band_renderer_evaluates_only_samples_inside_the_map_with_the_same_results():
    """``compact`` (the CPU default: only samples inside allocated voxels go through the field) against the
    fixed-shape path that evaluates every sample and masks: the same outputs and the same gradients of a
    training loss for the embeddings, the decoder and the rays, on rays whose free-space samples mostly
    leave the map."""
    from voxfusion.core.losses import compute_losses
    from voxfusion.core.render.volume import render_band

    vm = _band_map(plane_sdf, 0.2, 0.4, 0.15)  # a thin sheet of voxels around z = 2
    torch.manual_seed(0)
    dec = SDFDecoder()
    pix = torch.rand(64, 2, generator=torch.Generator().manual_seed(1)) * torch.tensor([31.0, 23.0])
    depth = 2.0 + 0.05 * torch.rand(64, generator=torch.Generator().manual_seed(2))
    color = torch.rand(64, 3, generator=torch.Generator().manual_seed(3))
    results = []
    for compact in (True, False):
        o, d = camera_rays(K_TEST, torch.eye(4), pixels_uv=pix)
        o.requires_grad_(True)
        vm.embeddings.grad = None
        dec.zero_grad(set_to_none=True)
        out = render_band(vm, dec, o, d, depth, RenderConfig(), n_free=6, free_range_m=2.0, training=True,
                          generator=torch.Generator().manual_seed(0), compact=compact)
        compute_losses(out, depth, color).total.backward()
        results.append([out.depth, out.color, out.sdf, out.weights, vm.embeddings.grad.clone(), o.grad,
                        *[p.grad for p in dec.parameters()]])
    inside = float(out.sample_mask.float().mean())
    assert 0.2 < inside < 0.9  # both kinds of samples are there
    for got, want in zip(*results, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
