"""Ray-voxel intersection: each ray's first ``M_h`` allocated voxels, in order, with entry/exit ``t``.

Two implementations that return identical results (same voxels in the same order, bit-identical
``t``), both vectorised over rays (no per-ray Python loops), on CPU and CUDA:

* :func:`intersect_voxels_reference` - the plain one. An Amanatides-Woo DDA in which every grid-plane
  crossing of every ray (up to ``t1``) is generated at once, sorted per ray, and the cell sequence is the
  cumulative sum of the crossing steps; membership is a ``searchsorted`` of the cells' Morton codes in
  the map's sorted codes.
* :func:`intersect_voxels` - the fast one, used by the renderer. Membership is one gather from the map's
  dense index grid (:meth:`~.map.VoxelMap.index_grid`) with the cell's flat index carried along the
  walk by the same cumulative sum; and long rays first march a coarse occupancy grid (blocks of
  ``2**level`` voxels, the implicit octree) so the fine walk only covers the runs of occupied blocks.
  It falls back to the reference when the map is too large for a dense grid.

Why the fast walk is exact: a crossing time is always computed as ``(plane * v - o) / d`` in float64
(``plane`` an integer lattice plane, coarse planes being the fine planes at multiples of ``2**level``),
exactly as in the reference, and times along one axis increase with the plane index. The cell occupied
just after any time ``T`` is therefore ``cell0 + step * #{crossings <= T}`` in both, whether the walk
starts at the ray's ``t0`` or later: a walk started at ``T`` finds its first plane per axis from the
position at ``T`` and corrects it against those exact crossing times, and the entry of its first cell is
the last crossing at or before ``T``. Coarse blocks are unions of voxels whose boundaries are crossings
of the same planes, so every voxel the ray spends a positive length in lies inside one occupied block's
interval; each run of occupied blocks is walked once and keeps the voxels entered before its end.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..errors import ShapeError, ValidationError
from ..map import VoxelMap
from ..map.index_grid import VoxelIndexGrid
from ..map.morton import morton_encode_planar

__all__ = ["VoxelHits", "intersect_voxels", "intersect_voxels_fixed", "intersect_voxels_reference", "fixed_walk_planes"]

_EVENT_BUDGET = 1 << 20
"""Grid-plane crossings per intersection chunk on a CPU (~150 B each at peak: a chunk's work stays in cache)."""
_GPU_BUDGET_FACTOR = 4
"""On a GPU a chunk takes this many times :data:`_EVENT_BUDGET` (~600 MB at peak): each chunk costs ~130 operators
(launches) and 4 read-backs whatever its size, and a 256x192 occlusion image of the synthetic room (0.2 m voxels) is
walked in one chunk instead of three, ~260 operators and 8 read-backs fewer (the same depth image; counted on a CPU
with the budget raised)."""
_COARSE_LEVELS = (1, 2, 3)
"""Octree levels considered for empty-space skipping (blocks of ``2**level`` voxels per axis)."""
_COARSE_GAIN = 0.85
"""Skip empty space only when the cost model predicts at most this fraction of the single walk's cost."""
_WINDOW_COST_CELLS = 3.0
"""Cost model: fixed cost of one walked window (first-plane search, partial cells), in voxel crossings."""


def _event_budget(device: torch.device) -> int:
    """Crossings per chunk on ``device`` (:data:`_EVENT_BUDGET`, :data:`_GPU_BUDGET_FACTOR`)."""
    return _EVENT_BUDGET if device.type == "cpu" else _EVENT_BUDGET * _GPU_BUDGET_FACTOR


@dataclass
class VoxelHits:
    """Ordered ray-voxel hits. ``M <= M_h`` columns (trimmed to the most hits any ray has).

    Attributes:
        t_entry, t_exit: ``[N, M]`` entry / exit ``t`` of each hit voxel, ascending per ray (0 padded).
        voxel_idx: ``[N, M]`` int64 voxel index, -1 padded (valid hits come first).
        hit: ``[N]`` bool, the ray hits at least one allocated voxel within range.
    """

    t_entry: torch.Tensor
    t_exit: torch.Tensor
    voxel_idx: torch.Tensor
    hit: torch.Tensor


class _Rays(NamedTuple):
    """Rays clipped to the map's bounding box (float64): ``o, d [N, 3]``, ``t0, t1 [N]``, ``ok [N]``."""

    o: torch.Tensor
    d: torch.Tensor
    t0: torch.Tensor
    t1: torch.Tensor
    ok: torch.Tensor


def _slab(o: torch.Tensor, d: torch.Tensor, lo: torch.Tensor,
          hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray/box slab test (float64): ``t_near, t_far`` ``[N]`` (empty when near >= far). Handles d == 0."""
    nz = d != 0
    sd = torch.where(nz, d, torch.ones_like(d))
    ta, tb = (lo - o) / sd, (hi - o) / sd
    inside = (o >= lo) & (o <= hi)
    inf = torch.full_like(o, math.inf)
    t_min = torch.where(nz, torch.minimum(ta, tb), torch.where(inside, -inf, inf))
    t_max = torch.where(nz, torch.maximum(ta, tb), torch.where(inside, inf, -inf))
    return t_min.max(-1).values, t_max.min(-1).values


def _check_rays(origins: torch.Tensor, dirs: torch.Tensor) -> None:
    if origins.dim() != 2 or origins.shape[1] != 3:
        raise ShapeError("origins", tuple(origins.shape), "[N, 3]")
    if dirs.shape != origins.shape:
        raise ShapeError("dirs", tuple(dirs.shape), f"{tuple(origins.shape)}")


def _clip_rays(voxel_map: VoxelMap, origins: torch.Tensor, dirs: torch.Tensor, max_distance_m: float,
               t_far: torch.Tensor | None) -> _Rays:
    """Clip rays to the bounding box of the allocated voxels, ``D_max`` and ``t_far`` (map not empty)."""
    n = origins.shape[0]
    dev = voxel_map.device
    bmin, bmax = voxel_map.voxel_bounds
    v = voxel_map.voxel_size_m
    o = origins.detach().to(dev, torch.float64)
    d = dirs.detach().to(dev, torch.float64)
    t_near, t_max = _slab(o, d, bmin.double() * v, (bmax + 1).double() * v)
    t1 = torch.clamp(t_max, max=float(max_distance_m))
    if t_far is not None:
        if t_far.shape != (n,):
            raise ShapeError("t_far", tuple(t_far.shape), f"({n},)")
        t1 = torch.minimum(t1, t_far.detach().to(dev, torch.float64))
    t0 = torch.clamp(t_near, min=0.0)
    ok = (t1 > t0) & torch.isfinite(o).all(-1) & torch.isfinite(d).all(-1)
    t0 = torch.where(ok, t0, torch.zeros_like(t0))
    t1 = torch.where(ok, t1, torch.zeros_like(t1))
    return _Rays(o, d, t0, t1, ok)


def _walk_clipped(voxel_map: VoxelMap, origins: torch.Tensor, dirs: torch.Tensor, max_distance_m: float,
                  t_far: torch.Tensor | None, walk: Callable[[_Rays], tuple[torch.Tensor, ...]]) -> VoxelHits:
    """What both intersections share around their walk: checked rays, none hit in an empty map, the rays clipped
    (:func:`_clip_rays`), then ``walk(rays) -> (t_entry, t_exit, voxel_idx, hit)`` and ``t`` in ``origins``'
    dtype."""
    _check_rays(origins, dirs)
    n = origins.shape[0]
    out_dtype = origins.dtype if origins.is_floating_point() else torch.float32
    if voxel_map.voxel_bounds is None or n == 0:
        return _empty_hits(n, out_dtype, voxel_map.device)
    t_entry, t_exit, vidx, hit = walk(_clip_rays(voxel_map, origins, dirs, max_distance_m, t_far))
    return VoxelHits(t_entry.to(out_dtype), t_exit.to(out_dtype), vidx, hit)


def _empty_hits(n: int, dtype: torch.dtype, dev: torch.device) -> VoxelHits:
    z = torch.zeros(n, 0, dtype=dtype, device=dev)
    return VoxelHits(z, z.clone(), torch.full((n, 0), -1, dtype=torch.int64, device=dev),
                     torch.zeros(n, dtype=torch.bool, device=dev))


def _chunks(planes: torch.Tensor) -> list[tuple[torch.Tensor, int]]:
    """Split rows into chunks of similar ``planes`` (crossings per axis) within :func:`_event_budget` events.

    Returns ``(rows, max planes of the chunk)`` pairs covering every row once.
    """
    n = planes.shape[0]
    budget = _event_budget(planes.device)
    order = torch.argsort(planes)  # chunk rays of similar length together
    planes_sorted = planes[order].tolist()
    out = []
    start = 0
    while start < n:
        # rays sorted by length: size the chunk so that its longest ray stays within the event budget
        size0 = max(1, budget // (3 * max(1, planes_sorted[start]) + 1))
        size = max(1, budget // (3 * max(1, planes_sorted[min(n, start + size0) - 1]) + 1))
        out.append((order[start:start + size], max(1, planes_sorted[min(n, start + size) - 1])))
        start += size
    return out


# ---------------------------------------------------------------- reference
def _dda_chunk(vmap: VoxelMap, o: torch.Tensor, d: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor,
               ok: torch.Tensor, n_planes: int, bmin: torch.Tensor, bmax: torch.Tensor,
               max_hits: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Vectorised Amanatides-Woo over ``n`` rays (float64). Returns entry, exit, idx, count (unpadded M)."""
    v = vmap.voxel_size_m
    n = o.shape[0]
    dev = o.device
    p0 = o + d * t0[:, None]
    cell0 = torch.floor(p0 / v).clamp(bmin.double(), bmax.double()).to(torch.int64)  # [n, 3]
    step = torch.sign(d).to(torch.int64)
    nz = d != 0
    sd = torch.where(nz, d, torch.ones_like(d))
    k = torch.arange(n_planes, device=dev, dtype=torch.int64)
    plane = (cell0 + (step > 0).to(torch.int64))[:, :, None] + step[:, :, None] * k  # [n, 3, P]
    t_ev = (plane.to(torch.float64) * v - o[:, :, None]) / sd[:, :, None]
    t_ev = torch.where(nz[:, :, None] & (t_ev < t1[:, None, None]), t_ev, torch.full_like(t_ev, math.inf))
    t_sorted, order = torch.sort(t_ev.reshape(n, 3 * n_planes), dim=1)
    finite = torch.isfinite(t_sorted)
    axis = torch.div(order, n_planes, rounding_mode="floor")
    # cells after each crossing, axis-first [3, n, E + 1] (contiguous per axis for the bit tricks)
    moves = torch.stack([torch.cumsum(((axis == a) & finite).to(torch.int64), 1) * step[:, a:a + 1]
                         for a in range(3)])  # [3, n, E]
    c0 = cell0.t()[:, :, None]
    cells = torch.cat([c0, c0 + moves], 2)
    inf_col = torch.full((n, 1), math.inf, dtype=t_sorted.dtype, device=dev)
    entry = torch.cat([t0[:, None], t_sorted], 1)
    exit_ = torch.cat([t_sorted, inf_col], 1)
    lo, hi = t0[:, None], t1[:, None]
    entry = torch.minimum(torch.maximum(entry, lo), hi)
    exit_ = torch.minimum(torch.maximum(exit_, lo), hi)
    inside = ((cells >= bmin[:, None, None]) & (cells <= bmax[:, None, None])).all(0)
    valid = ok[:, None] & (exit_ > entry) & inside
    codes = morton_encode_planar(cells)  # cells lie within the map's bounds (or are masked by `inside`)
    idx = vmap.lookup_codes(codes)
    is_hit = valid & (idx >= 0)
    rank = torch.cumsum(is_hit.to(torch.int64), 1) - 1
    keep = is_hit & (rank < max_hits)
    count = keep.sum(1)
    m = int(count.max()) if n else 0
    out_e = torch.zeros(n, m, dtype=torch.float64, device=dev)
    out_x = torch.zeros(n, m, dtype=torch.float64, device=dev)
    out_i = torch.full((n, m), -1, dtype=torch.int64, device=dev)
    r, c = torch.nonzero(keep, as_tuple=True)
    col = rank[r, c]
    out_e[r, col] = entry[r, c]
    out_x[r, col] = exit_[r, c]
    out_i[r, col] = idx[r, c]
    return out_e, out_x, out_i, count


def _pad_cols(x: torch.Tensor, m: int, value: float) -> torch.Tensor:
    if x.shape[1] == m:
        return x
    return torch.cat([x, x.new_full((x.shape[0], m - x.shape[1]), value)], 1)


def _intersect_reference(voxel_map: VoxelMap, rays: _Rays, max_hits: int) -> tuple[torch.Tensor, ...]:
    o, d, t0, t1, ok = rays
    n = o.shape[0]
    dev = o.device
    bmin, bmax = voxel_map.voxel_bounds
    v = voxel_map.voxel_size_m
    # grid planes each ray can cross per axis, plus one for the partial first cell
    planes = torch.ceil((t1 - t0)[:, None] * d.abs() / v).max(-1).values + 1
    planes = torch.where(ok, planes, torch.zeros_like(planes)).to(torch.int64)
    parts = [(rows, *_dda_chunk(voxel_map, o[rows], d[rows], t0[rows], t1[rows], ok[rows], p_max, bmin, bmax,
                                max_hits))
             for rows, p_max in _chunks(planes)]
    m = max(int(part[1].shape[1]) for part in parts)
    t_entry = torch.zeros(n, m, dtype=torch.float64, device=dev)
    t_exit = torch.zeros(n, m, dtype=torch.float64, device=dev)
    vidx = torch.full((n, m), -1, dtype=torch.int64, device=dev)
    hit = torch.zeros(n, dtype=torch.bool, device=dev)
    for rows, e, x, i, c in parts:
        t_entry[rows] = _pad_cols(e, m, 0.0)
        t_exit[rows] = _pad_cols(x, m, 0.0)
        vidx[rows] = _pad_cols(i, m, -1)
        hit[rows] = c > 0
    return t_entry, t_exit, vidx, hit


@torch.no_grad()
def intersect_voxels_reference(voxel_map: VoxelMap, origins: torch.Tensor, dirs: torch.Tensor,
                               max_distance_m: float, max_hits: int,
                               t_far: torch.Tensor | None = None) -> VoxelHits:
    """:func:`intersect_voxels` by the plain all-crossings DDA with Morton-code membership.

    The specification the fast path is tested against; same arguments and result.
    """
    return _walk_clipped(voxel_map, origins, dirs, max_distance_m, t_far,
                         lambda rays: _intersect_reference(voxel_map, rays, max_hits))


# ---------------------------------------------------------------- fast path
class _Walk(NamedTuple):
    """Sub-rays to walk over one grid (float64 / int64, ``S`` rows, each a window ``[ts, te]`` of a ray).

    ``o, d, sd [S, 3]`` origin, direction, direction with zeros replaced by 1; ``step [S, 3]`` sign of
    ``d``; ``cell0 [S, 3]`` the ray's first voxel (as in the reference); ``t0, t1 [S]`` the ray's clipped
    range; ``ts, te [S]`` the window.
    """

    o: torch.Tensor
    d: torch.Tensor
    sd: torch.Tensor
    step: torch.Tensor
    cell0: torch.Tensor
    t0: torch.Tensor
    t1: torch.Tensor
    ts: torch.Tensor
    te: torch.Tensor

    def take(self, rows: torch.Tensor) -> _Walk:
        return _Walk(*(x[rows] for x in self))


def _plane_t(planes: torch.Tensor, block: int, v: float, o: torch.Tensor, sd: torch.Tensor) -> torch.Tensor:
    """Crossing time of integer lattice planes (in units of ``block`` voxels), as the reference computes it."""
    p = planes if block == 1 else planes * block
    return (p.to(torch.float64) * v - o) / sd


def _first_planes(w: _Walk, block: int, v: float,
                  rounds: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Per sub-ray and axis, the first plane (in units of ``block`` voxels) crossed after ``ts``.

    Returns ``q [S, 3]`` int64 (the next plane along ``step``; the reference's first plane when none was
    crossed yet), ``entry0 [S]``, the last crossing at or before ``ts`` over all axes (-inf when
    there is none: the first cell is then entered at ``t0``), and ``unsettled``. Estimated from the position at
    ``ts``, then corrected against the exact crossing times (the estimate is off by at most one plane, so one
    correction settles it and a second one moves nothing): until nothing moves (a read-back per round) when
    ``rounds`` is None (``unsettled`` is then None), else exactly ``rounds`` corrections and ``unsettled``, a bool
    scalar on the device, says whether the last one still moved a plane (the caller must not trust ``q`` then).
    """
    if rounds is not None and rounds < 1:
        raise ValidationError("rounds", f"must be >= 1 (or None), got {rounds}")
    nz = w.d != 0
    up = w.step > 0
    cell = torch.div(w.cell0, block, rounding_mode="floor") if block > 1 else w.cell0
    first = cell + up.to(torch.int64)  # the reference's first plane per axis
    ts = w.ts[:, None]
    pos = (w.o + w.d * ts) / (v * block)
    q = torch.where(up, torch.maximum(first, torch.floor(pos).to(torch.int64) + 1),
                    torch.where(w.step < 0, torch.minimum(first, torch.ceil(pos).to(torch.int64) - 1), first))
    unsettled = None
    for _ in range(8 if rounds is None else rounds):
        back = nz & (q != first) & (_plane_t(q - w.step, block, v, w.o, w.sd) > ts)
        q = q - w.step * back
        fwd = nz & (_plane_t(q, block, v, w.o, w.sd) <= ts)
        q = q + w.step * fwd
        unsettled = (back | fwd).any()
        if rounds is None and not bool(unsettled):
            unsettled = None
            break
    if rounds is None and unsettled is not None:  # pragma: no cover - crossing times increase with the plane index
        raise RuntimeError("ray marching: the first plane after ts did not converge")
    crossed = nz & (q != first)
    t_prev = torch.where(crossed, _plane_t(q - w.step, block, v, w.o, w.sd), torch.full_like(w.o, -math.inf))
    return q, t_prev.max(-1).values, unsettled


class _Crossings(NamedTuple):
    """One walk's grid-plane crossings (:func:`_crossings`), ``S`` sub-rays, ``E = 3 * n_planes`` crossings each.

    ``t_sorted [S, E]`` float64 crossing times, ascending (inf for the planes at or beyond ``t1``); ``flat [S, E +
    1]`` int64 flat grid index of the cell entered at ``ts`` and after each crossing; ``tt [S, E + 2]`` the entry
    time of each of those cells (``tt[:, c]``; its exit is ``tt[:, c + 1]``): ``entry0``, the crossings, inf;
    ``rel0, rel1 [S, 3]`` the first and the last cell (after every live crossing) relative to the grid's origin;
    ``live [S, 3, n_planes]``, ``order [S, E]`` which planes lie before ``t1`` and the sort's permutation;
    ``unsettled``: :func:`_first_planes`'.
    """

    t_sorted: torch.Tensor
    flat: torch.Tensor
    tt: torch.Tensor
    rel0: torch.Tensor
    rel1: torch.Tensor
    live: torch.Tensor
    order: torch.Tensor
    unsettled: torch.Tensor | None


def _crossings(grid: VoxelIndexGrid, v: float, w: _Walk, n_planes: int, rounds: int | None = None) -> _Crossings:
    """``n_planes`` crossings per axis of each sub-ray from the first one after ``ts`` (both walks' first half)."""
    block = 1 << grid.level
    s = w.o.shape[0]
    dev = w.o.device
    q, entry0, unsettled = _first_planes(w, block, v, rounds)
    k = torch.arange(n_planes, device=dev, dtype=torch.int64)
    t_ev = _plane_t(q[:, :, None] + w.step[:, :, None] * k, block, v, w.o[:, :, None], w.sd[:, :, None])
    live = (w.d != 0)[:, :, None] & (t_ev < w.t1[:, None, None])
    t_ev = torch.where(live, t_ev, torch.full_like(t_ev, math.inf))
    t_sorted, order = torch.sort(t_ev.reshape(s, 3 * n_planes), dim=1, stable=True)
    # flat grid index of the cell after each crossing: one cumulative sum of per-crossing strides
    strides = grid.strides_tensor
    delta = torch.where(live, (w.step * strides)[:, :, None], torch.zeros_like(q)[:, :, None])
    moves = torch.cumsum(torch.gather(delta.reshape(s, 3 * n_planes), 1, order), 1)
    rel0 = q - (w.step > 0).to(torch.int64) - grid.origin  # cell just after ts, relative to the grid
    flat0 = (rel0 * strides).sum(-1, keepdim=True)
    flat = torch.cat([flat0, flat0 + moves], 1)  # [S, E + 1]
    rel1 = rel0 + w.step * live.sum(-1)
    inf_col = torch.full((s, 1), math.inf, dtype=torch.float64, device=dev)
    tt = torch.cat([entry0[:, None], t_sorted, inf_col], 1)  # entry of cell c = tt[c]
    return _Crossings(t_sorted, flat, tt, rel0, rel1, live, order, unsettled)


def _in_grid(grid: VoxelIndexGrid, rel0: torch.Tensor, rel1: torch.Tensor) -> torch.Tensor:
    """``[S]`` bool: the walk's first and last cells lie in ``grid`` (a walk is monotone per axis, so then all of
    its cells do)."""
    return ((rel0 >= 0) & (rel0 < grid.size) & (rel1 >= 0) & (rel1 < grid.size)).all(-1)


def _walk_chunk(grid: VoxelIndexGrid, v: float, w: _Walk,
                n_planes: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Walk ``S`` sub-rays through ``grid`` from ``ts``; return the cells with a value entered before ``te``.

    ``n_planes`` crossings per axis are generated from the first one after ``ts`` (enough to pass ``te``).
    Returns ``(row, entry, exit, value)`` of each kept cell, ordered by row then entry; ``entry`` and
    ``exit`` are clamped to the ray's ``[t0, t1]`` exactly as in the reference, and only cells of
    positive length are kept.
    """
    s = w.o.shape[0]
    dev = w.o.device
    c = _crossings(grid, v, w, n_planes)
    # candidates: cells entered before te (the first one always is)
    cand = torch.cat([torch.ones_like(c.flat[:, :1], dtype=torch.bool), c.t_sorted < w.te[:, None]], 1)
    if not bool(_in_grid(grid, c.rel0, c.rel1).all()):
        eye = torch.eye(3, dtype=torch.bool, device=dev)
        axis_of = (c.live[None] & eye[:, None, :, None]).reshape(3, s, 3 * n_planes).to(torch.int64)
        moves_axis = torch.cumsum(torch.gather(axis_of, 2, c.order.expand(3, s, 3 * n_planes)), 2)  # [3, S, E]
        rel = c.rel0.t()[:, :, None] + torch.cat([torch.zeros_like(moves_axis[:, :, :1]), moves_axis], 2) \
            * w.step.t()[:, :, None]
        cand &= ((rel >= 0) & (rel < grid.size[:, None, None])).all(0)
    flat = torch.where(cand, c.flat, torch.zeros_like(c.flat)).reshape(-1)
    val = grid.table.index_select(0, flat)
    pos = torch.nonzero((val >= 0) & cand.reshape(-1)).squeeze(1)  # row-major: by sub-ray, then along it
    r = torch.div(pos, c.t_sorted.shape[1] + 1, rounding_mode="floor")
    tt = c.tt.reshape(-1)
    lo, hi = w.t0[r], w.t1[r]
    entry = torch.minimum(torch.maximum(tt.index_select(0, pos + r), lo), hi)
    exit_ = torch.minimum(torch.maximum(tt.index_select(0, pos + r + 1), lo), hi)
    keep = torch.nonzero((exit_ > entry) & (entry < w.te[r])).squeeze(1)
    return r[keep], entry[keep], exit_[keep], val[pos[keep]].to(torch.int64)


def _walk(grid: VoxelIndexGrid, v: float, w: _Walk) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_walk_chunk` over all sub-rays in event-budget chunks; rows ordered by sub-ray then entry."""
    block = 1 << grid.level
    if w.o.shape[0] == 0:
        empty = w.ts.new_zeros(0)
        return empty.to(torch.int64), empty, empty.clone(), empty.to(torch.int64)
    # planes per axis that cover [ts, te], plus the partial first block and the first crossing after te
    planes = (torch.ceil((w.te - w.ts)[:, None] * w.d.abs() / (v * block)).max(-1).values + 2).to(torch.int64)
    parts = []
    for rows, p_max in _chunks(planes):
        r, e, x, val = _walk_chunk(grid, v, w.take(rows), p_max)
        parts.append((rows[r], e, x, val))
    sub = torch.cat([p[0] for p in parts])
    order = torch.sort(sub, stable=True).indices  # chunks hold disjoint sub-rays, each in entry order
    return sub[order], torch.cat([p[1] for p in parts])[order], torch.cat([p[2] for p in parts])[order], \
        torch.cat([p[3] for p in parts])[order]


def _occupied_runs(w: _Walk, coarse: VoxelIndexGrid, v: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Windows ``[ts, te]`` of each ray's runs of consecutive occupied coarse blocks: ``(ray, ts, te)``."""
    sub, e, x, _ = _walk(coarse, v, w)
    if sub.numel() == 0:
        return sub, e, x
    new = torch.ones_like(sub, dtype=torch.bool)
    new[1:] = (sub[1:] != sub[:-1]) | (e[1:] != x[:-1])
    starts = torch.nonzero(new).squeeze(1)
    ends = torch.cat([starts[1:] - 1, starts.new_tensor([sub.numel() - 1])])
    return sub[starts], e[starts], x[ends]


def _skip_grid(voxel_map: VoxelMap, mean_cells: float) -> VoxelIndexGrid | None:
    """The coarse occupancy grid worth marching first, or None (walk the voxels directly).

    Cost model, in voxel crossings per ray: a direct walk costs ``mean_cells``; skipping with blocks of
    ``B = 2**level`` voxels costs ``mean_cells / B`` for the coarse march plus about ``occupancy *
    mean_cells`` inside occupied blocks (``occupancy`` = occupied fraction of the blocks in the bounding
    box) plus a fixed cost per window. Sparse maps of fine voxels skip; coarse, dense ones do not.
    """
    best, best_cost = None, _COARSE_GAIN * mean_cells
    for level in _COARSE_LEVELS:
        grid = voxel_map.index_grid(level)
        if grid is None:
            continue
        inner = math.prod(s - 2 for s in grid.shape)  # without the one-block border
        cost = mean_cells * (2.0 ** -level + grid.n_occupied / max(1, inner)) + _WINDOW_COST_CELLS
        if cost < best_cost:
            best, best_cost = grid, cost
    return best


def _intersect_grid(voxel_map: VoxelMap, grid: VoxelIndexGrid, rays: _Rays,
                    max_hits: int) -> tuple[torch.Tensor, ...]:
    o, d, t0, t1, ok = rays
    n = o.shape[0]
    dev = o.device
    v = voxel_map.voxel_size_m
    bmin, bmax = voxel_map.voxel_bounds
    ids = torch.nonzero(ok).squeeze(1)
    if ids.numel() == 0:
        return _intersect_reference(voxel_map, rays, max_hits)  # nothing to walk: all-empty result
    o, d, t0, t1 = o[ids], d[ids], t0[ids], t1[ids]
    cell0 = torch.floor((o + d * t0[:, None]) / v).clamp(bmin.double(), bmax.double()).to(torch.int64)
    sd = torch.where(d != 0, d, torch.ones_like(d))
    walk = _Walk(o, d, sd, torch.sign(d).to(torch.int64), cell0, t0, t1, t0, t1)
    ray = torch.arange(ids.numel(), device=dev)
    coarse = _skip_grid(voxel_map, float(((t1 - t0)[:, None] * d.abs()).sum(-1).mean()) / v)
    if coarse is not None:
        ray, ts, te = _occupied_runs(walk, coarse, v)
        walk = walk.take(ray)._replace(ts=ts, te=te)
    sub, e, x, idx = _walk(grid, v, walk)
    ray = ray[sub]  # windows are ordered by ray then t, so hits are too
    count = torch.bincount(ray, minlength=ids.numel())
    rank = torch.arange(ray.numel(), device=dev) - (torch.cumsum(count, 0) - count)[ray]
    keep = rank < max_hits
    m = min(int(count.max()), max_hits)
    t_entry = torch.zeros(n, m, dtype=torch.float64, device=dev)
    t_exit = torch.zeros(n, m, dtype=torch.float64, device=dev)
    vidx = torch.full((n, m), -1, dtype=torch.int64, device=dev)
    rows, cols = ids[ray[keep]], rank[keep]
    t_entry[rows, cols] = e[keep]
    t_exit[rows, cols] = x[keep]
    vidx[rows, cols] = idx[keep]
    hit = torch.zeros(n, dtype=torch.bool, device=dev)
    hit[ids] = count > 0
    return t_entry, t_exit, vidx, hit


@torch.no_grad()
def intersect_voxels(voxel_map: VoxelMap, origins: torch.Tensor, dirs: torch.Tensor, max_distance_m: float,
                     max_hits: int, t_far: torch.Tensor | None = None) -> VoxelHits:
    """First ``max_hits`` allocated voxels along each ray within ``0 <= t <= min(max_distance_m, t_far)``.

    Args:
        origins, dirs: ``[N, 3]`` world-frame rays (``dirs`` need not be unit; no gradient flows).
        max_distance_m: ``D_max`` in t-units.
        max_hits: ``M_h`` (see :meth:`~.volume.RenderConfig.max_hits_for`).
        t_far: optional ``[N]`` per-ray upper bound on ``t`` (e.g. ``D_gt + tr`` while mapping).

    Returns:
        :class:`VoxelHits` with ``t`` in ``origins``' dtype. A voxel counts as hit when the ray spends a
        positive length inside it (grazing an edge or corner exactly is not a hit). Identical to
        :func:`intersect_voxels_reference`.
    """
    grid = voxel_map.index_grid()
    return _walk_clipped(voxel_map, origins, dirs, max_distance_m, t_far,
                         lambda rays: _intersect_reference(voxel_map, rays, max_hits) if grid is None
                         else _intersect_grid(voxel_map, grid, rays, max_hits))


# ---------------------------------------------------------------- fixed shapes
_FIXED_WALK_MAX_PLANES = 128
"""Longest map box (in crossings per axis, :func:`fixed_walk_planes`) the fixed-shape walk takes on: every ray walks
that many crossings per axis whatever its length, where the data-dependent walk covers each ray's own length and
skips empty space in coarse blocks; beyond it (a map over ~125 voxels long: 25 m at 0.2 m voxels, 6 m at 5 cm) the
fixed walk's work and memory (~3 * 128 crossings a ray) outweigh the read-backs it saves."""
_FIXED_PLANE_ROUNDS = 2
"""Corrections of the first-plane estimate in the fixed-shape walk: the estimate is off by at most one plane, so the
first settles it and the second confirms (it moving a plane makes the result doubtful, see :func:`_first_planes`)."""


def fixed_walk_planes(grid: VoxelIndexGrid) -> int:
    """Crossings per axis that cover any ray clipped to the occupied box of ``grid`` (a level-0 grid whose box is
    the map's :attr:`~.map.VoxelMap.voxel_bounds`): a ray crosses at most ``box + 1`` planes of an axis inside
    a box ``box`` cells long, the walk adds the first crossing after ``t1``, and one more absorbs rounding."""
    return max(grid.box_shape) + 3


def grid_walk_planes(grid: VoxelIndexGrid) -> int | None:
    """Crossings per axis that cover any ray inside the whole of ``grid`` (its box with the border and the alignment of
    a level-0 grid): a bound that holds while the map grows inside the grid, for a walk whose shapes must outlast the
    map (a CUDA graph's); None beyond :data:`_FIXED_WALK_MAX_PLANES`."""
    n = max(grid.shape) + 3
    return n if n <= _FIXED_WALK_MAX_PLANES else None


def _walk_fixed(grid: VoxelIndexGrid, v: float, w: _Walk, ok: torch.Tensor, n_planes: int,
                max_hits: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_walk_chunk` over whole rays (``ts = t0``, ``te = t1``) with every shape fixed and no read-back.

    Returns ``entry, exit [S, max_hits]`` float64 (0 padded), ``value [S, max_hits]`` int64 (-1 padded): each
    row's first ``max_hits`` cells with a value, in order, exactly as the chunked walk and the reference find them;
    and ``doubt``, a bool scalar on the device: a row ``ok`` marks left the grid or needed more than ``n_planes``
    crossings of an axis, or the first-plane search had not settled (the result must then not be used). Rows
    ``ok`` does not mark get no cells (their origin and direction may be anything, non-finite too).
    """
    s = w.o.shape[0]
    c = _crossings(grid, v, w, n_planes, rounds=_FIXED_PLANE_ROUNDS)
    # doubtful: a row left the grid, needed more crossings than were generated (its last plane still lies before
    # t1), or the first-plane search had not settled
    short = c.live[:, :, -1].any(-1)
    doubt = c.unsettled | (ok & (short | ~_in_grid(grid, c.rel0, c.rel1))).any()
    # cells entered before t1 (the first one always is), on a ray that has any
    cand = torch.cat([ok[:, None], (c.t_sorted < w.te[:, None]) & ok[:, None]], 1)
    flat = torch.where(cand, c.flat, torch.zeros_like(c.flat)).clamp(0, grid.n_cells - 1)  # rows left out: anything
    val = grid.table.index_select(0, flat.reshape(-1)).reshape(flat.shape)
    lo, hi = w.t0[:, None], w.t1[:, None]
    entry = torch.minimum(torch.maximum(c.tt[:, :-1], lo), hi)
    exit_ = torch.minimum(torch.maximum(c.tt[:, 1:], lo), hi)
    keep = (val >= 0) & cand & (exit_ > entry) & (entry < w.te[:, None])
    # the k-th kept cell of a row goes to column k; cells past max_hits to a spare column, dropped
    rank = torch.cumsum(keep.to(torch.int64), 1) - 1
    slot = torch.where(keep & (rank < max_hits), rank, torch.full_like(rank, max_hits))
    out_e = entry.new_zeros(s, max_hits + 1).scatter_(1, slot, entry)[:, :max_hits]
    out_x = entry.new_zeros(s, max_hits + 1).scatter_(1, slot, exit_)[:, :max_hits]
    out_v = torch.full((s, max_hits + 1), -1, dtype=torch.int64, device=entry.device)
    out_v = out_v.scatter_(1, slot, val.to(torch.int64))[:, :max_hits]
    return out_e, out_x, out_v, doubt


@torch.no_grad()
def intersect_voxels_fixed(voxel_map: VoxelMap, origins: torch.Tensor, dirs: torch.Tensor, max_distance_m: float,
                           max_hits: int, n_planes: int | None = None) -> tuple[VoxelHits, torch.Tensor] | None:
    """:func:`intersect_voxels` with every shape fixed by the map and no read-back (a GPU's occlusion render).

    The fast path reads the device back ~8 times (rays to walk, their lengths, chunk sizes, hit counts); here
    every ray walks the same number of crossings, :func:`fixed_walk_planes` (known to the host from the map's
    index grid), in row chunks of the device's event budget, and the hits fill ``min(max_hits, 3 * planes + 1)``
    columns (a walk never has more cells), 0 / -1 padded beyond each ray's own.

    Returns:
        ``(hits, doubt)``: hits in ``origins``' dtype, identical to :func:`intersect_voxels`' apart from the padding
        columns, and ``doubt``, a bool scalar on the device that is True where the fixed walk's assumptions failed
        (read it with whatever the caller reads next; when True use :func:`intersect_voxels`). None where the map
        is empty, has no dense index grid or is longer than :data:`_FIXED_WALK_MAX_PLANES` crossings
        (:func:`intersect_voxels` then).

    ``n_planes``: crossings per axis to walk (None: :func:`fixed_walk_planes`); more give the same hits in more
    padding columns, fewer make the walk doubt rays that need them. A caller that keeps shapes across maps (a CUDA
    graph) passes one bound for all of them.
    """
    _check_rays(origins, dirs)
    grid = voxel_map.index_grid() if voxel_map.voxel_bounds is not None else None
    if grid is None or origins.shape[0] == 0:
        return None
    n_planes = fixed_walk_planes(grid) if n_planes is None else n_planes
    if n_planes > _FIXED_WALK_MAX_PLANES:
        return None
    out_dtype = origins.dtype if origins.is_floating_point() else torch.float32
    o, d, t0, t1, ok = _clip_rays(voxel_map, origins, dirs, max_distance_m, None)
    v = voxel_map.voxel_size_m
    bmin, bmax = voxel_map.voxel_bounds
    # rays left out (t0 = t1 = 0) walk from a finite stand-in: no non-finite value reaches the integer casts
    o = torch.where(ok[:, None], o, torch.zeros_like(o))
    d = torch.where(ok[:, None], d, torch.ones_like(d))
    cell0 = torch.floor((o + d * t0[:, None]) / v).clamp(bmin.double(), bmax.double()).to(torch.int64)
    sd = torch.where(d != 0, d, torch.ones_like(d))
    walk = _Walk(o, d, sd, torch.sign(d).to(torch.int64), cell0, t0, t1, t0, t1)
    columns = min(max_hits, 3 * n_planes + 1)
    rows = max(1, _event_budget(o.device) // (3 * n_planes + 1))
    parts = [_walk_fixed(grid, v, walk.take(slice(a, a + rows)), ok[a:a + rows], n_planes, columns)
             for a in range(0, o.shape[0], rows)]
    t_entry, t_exit, vidx = (torch.cat([p[k] for p in parts]) if len(parts) > 1 else parts[0][k] for k in range(3))
    doubt = torch.stack([p[3] for p in parts]).any() if len(parts) > 1 else parts[0][3]
    hit = (vidx >= 0).any(1)
    return VoxelHits(t_entry.to(out_dtype), t_exit.to(out_dtype), vidx, hit), doubt
