"""Per-voxel observation evidence: space that rays have mostly seen as empty never renders a surface.

Why: a voxel is allocated as soon as one depth point falls in it (paper §4.4). When that point was a
sensor outlier (speckle, a flying pixel), or when a real surface was seen only by a few pixels while many
more rays passed straight through the same voxel, the voxel holds almost no surface and lots of free
space, but its embeddings are barely trained: the decoder can put a zero crossing anywhere in it, and the
renderer (which composites the first surface along a ray) then shows a phantom surface in front of the real
one. The free-space loss only pushes such a voxel towards "empty" for the few rays mapping happens to
sample, and never while tracking. A depth filter (:mod:`.depth_filter`) removes most outliers, but it
cannot help a voxel that real, sparse observations allocated.

What is measured (every integrated frame, :func:`observe_frame`), in **pixel-equivalents** so the two
counters are comparable whatever the sampling strides:

* ``hits``: depth points that fell in the voxel (the allocation points, each worth ``stride**2`` pixels,
  ``MappingConfig.stride_for``);
* ``free``: camera rays (every ``s``-th pixel per axis, ``s`` chosen for about ``free_rays`` rays per
  frame, each ray worth ``s**2`` pixels) that crossed the voxel *entirely* at least ``margin_m`` (camera
  depth) in front of their own observed depth: such a ray proves the part of the voxel it crossed is
  empty. The voxel that contains the point ``margin_m`` in front of the observed surface, and everything
  behind it, gets nothing from that ray, so sensor noise and the surface's own voxel never count as free.

The decision (:func:`evidence_active`): a voxel is **inactive** once it has at least ``min_free_px`` of
free-space evidence and its hits are less than ``min_hit_ratio`` of all its evidence,
``hits < min_hit_ratio * (hits + free)``, i.e. fewer than 1 % of the rays that reached the voxel ended on
a surface inside it, and its depth points fell in fewer than ``min_surface_cells`` of its 1.25 cm surface
cells (isolated points, not an extended surface: see that option).

The ratio was measured on the first frame of each dev capture and the synthetic room with 2 % random
near-range outliers and the depth filter off: voxels allocated only by outliers have a median ratio of
0.004-0.006 (90 % below 0.005-0.02), voxels holding real surface a median of 0.1-0.6; a few % of the real
voxels fall below 0.02: they hold a sliver of a surface (a counter's edge, a few rows of pixels) at the border
of a voxel that rays mostly cross as free space. The threshold was first 0.02; over a 100-frame run of the
synthetic room that masked enough slivers to cut holes along voxel borders (mesh completion ratio 95.3 %
against 99.1 % with the evidence off); at 0.01 it is 99.4 %, and the outlier probes (which the depth filter
also guards) still pass. Slivers below 1 % are still masked: the surface usually continues in a
neighbouring voxel, more views add hits (which re-activate the voxel), and an almost empty voxel is exactly
where a barely trained field draws phantom surfaces.

An inactive voxel is kept in the map but read as empty by raycasting, rendering, training, queries and
mesh extraction (see :class:`~.voxel_map.VoxelMap`); its counters keep growing, so enough later hits make it
active again. The counters and the mask are part of the map's ``state_dict`` and so of checkpoints.

We chose a mask over pruning: removing voxels would have to compact the voxel tables, drop orphaned
vertices, shrink the embedding Parameter and every optimiser's state, and the evidence would be lost when
the next outlier re-allocates the voxel; a mask keeps every table and invariant as it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import ConfigError, ShapeError, ValidationError
from ..framedata import FrameData
from .voxel_map import VoxelMap

__all__ = ["EvidenceConfig", "EvidenceUpdate", "free_space_voxels", "free_space_voxels_many", "evidence_active",
           "observe_frame", "observe_frames"]

_SAMPLE_BUDGET = 1 << 20
"""Ray samples handled at once by :func:`free_space_voxels` (bounds its memory, ~100 MB peak)."""


@dataclass(frozen=True)
class EvidenceConfig:
    """Options of the per-voxel observation evidence (module docstring)."""

    enabled: bool = True
    """Accumulate evidence at integration and deactivate voxels it says are empty (False: every voxel
    stays active, as before this mechanism existed)."""
    free_rays: int = 4096
    """About this many free-space rays per frame: every ``s``-th pixel per axis with
    ``s = max(1, floor(sqrt(H * W / free_rays)))`` (:meth:`ray_stride_px`; 640 x 480 -> s = 8, 4,800 rays,
    ~10 ms on one CPU core; 256 x 192 -> s = 3, 5,461 rays). A 0.2 m voxel 3 m away still gets ~25 rays
    from a Kinect-class frame."""
    margin_m: float = 0.1
    """A ray counts as free space only for voxels it leaves this far (camera depth, metres) in front of its
    observed depth: several times the depth noise of Kinect-class and LiDAR sensors at 3 m (~2 cm), and
    the renderer's default truncation band."""
    sample_step_ratio: float = 0.5
    """Spacing of the samples that find the voxels a ray crosses, as a fraction of the voxel edge. A ray that
    clips a voxel by less than a step may miss its count (never the reverse), so evidence errs towards
    keeping: 0.5 finds ~80 % of the exact ray-voxel crossings (the rest are short corner clips), 0.25 ~90 %,
    0.125 ~95 % (tested against the exact DDA), at proportionally more samples."""
    min_hit_ratio: float = 0.01
    """A voxel is inactive when ``hits < min_hit_ratio * (hits + free)``. 1 % sits above most voxels that
    isolated outliers allocate (median 0.4-0.6 %) and below almost every voxel of a real surface (median
    10-60 %; see the module docstring for the slivers and why 0.02 was too high)."""
    min_free_px: float = 64.0
    """...and it has at least this much free-space evidence (pixel-equivalents), so a voxel is never
    judged on a handful of rays."""
    min_surface_cells: int = 12
    """...and fewer than this many of its 4096 surface cells (1.25 cm at 0.2 m voxels,
    :meth:`~.voxel_map.VoxelMap.add_surface_points`) ever held a depth point. A real surface is extended: even
    a sliver of floor grazing a voxel's border fills dozens of cells (14-64 measured with 2.5 cm cells on the
    synthetic room, where a floor 2 mm above a voxel border made 40 such slivers that the ratio alone masked,
    cutting mesh completion to 91 %; a surface crosses about four times as many 1.25 cm cells, not
    re-measured), while isolated outliers fill one cell each (1-9 measured with 2.5 cm cells)."""

    def __post_init__(self) -> None:
        if self.free_rays < 1:
            raise ConfigError("free_rays", f"must be >= 1, got {self.free_rays}")
        for name in ("margin_m", "min_free_px"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(name, f"must be a finite number >= 0, got {v}")
        if not (math.isfinite(self.sample_step_ratio) and 0 < self.sample_step_ratio <= 1):
            raise ConfigError("sample_step_ratio", f"must be in (0, 1], got {self.sample_step_ratio}")
        if not (math.isfinite(self.min_hit_ratio) and 0 <= self.min_hit_ratio < 1):
            raise ConfigError("min_hit_ratio", f"must be in [0, 1), got {self.min_hit_ratio}")

    def ray_stride_px(self, height: int, width: int) -> int:
        """Pixel stride per axis of the free-space rays for a ``width x height`` depth image."""
        return max(1, int(math.floor(math.sqrt(height * width / self.free_rays))))


@dataclass(frozen=True)
class EvidenceUpdate:
    """What one :func:`observe_frame` call did: evidence added (pixel-equivalents) and the mask change."""

    hit_px: float
    free_px: float
    changed: int
    """Voxels whose active state changed."""
    n_inactive: int
    """Inactive voxels in the map afterwards."""


@torch.no_grad()
def free_space_voxels(voxel_map: VoxelMap, depth_m: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                      ray_stride_px: int, margin_m: float, step_m: float) -> torch.Tensor:
    """Allocated voxels that camera rays crossed as free space (one entry per ray and voxel).

    A ray through pixel ``(u, v)`` (every ``ray_stride_px``-th pixel per axis with valid depth ``D``) is
    sampled every ``step_m`` metres from the camera centre to camera depth ``D - margin_m``; the voxels of
    its samples, in order, are the voxels it crossed there (a ray never re-enters a voxel, so consecutive
    duplicates are the only ones). The voxel holding the end point is dropped: only voxels the ray left
    ``margin_m`` or more in front of its surface count. Inactive voxels are included.

    Args:
        voxel_map: the map (read only).
        depth_m: ``[H, W]`` float camera z-depth in metres, 0 = invalid (already filtered).
        K: ``[3, 3]`` intrinsics for ``(W, H)``.
        T_world_cam: ``[4, 4]`` camera-to-world pose (OpenCV axes, metres).
        ray_stride_px: pixel stride per axis; margin_m: camera-depth margin (m); step_m: sample spacing
            along the ray (m).

    Returns:
        ``[F]`` int64 voxel indices (repeats = several rays crossed the voxel).
    """
    return free_space_voxels_many(voxel_map, [(depth_m, K, T_world_cam)], ray_stride_px, margin_m, step_m)


@torch.no_grad()
def free_space_voxels_many(voxel_map: VoxelMap, views: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
                           ray_stride_px: int, margin_m: float, step_m: float) -> torch.Tensor:
    """:func:`free_space_voxels` of several posed depth images ``(depth_m, K, T_world_cam)`` at one pixel stride,
    their rays sampled together (a realtime round's frames): each image's entries, in another order.

    Returns:
        ``[F]`` int64 voxel indices (repeats = several rays crossed the voxel).
    """
    if not step_m > 0:
        raise ValidationError("step_m", f"must be > 0, got {step_m}")
    for depth_m, _, _ in views:
        if depth_m.dim() != 2:
            raise ShapeError("depth_m", tuple(depth_m.shape), "[H, W]")
    dev = voxel_map.device
    empty = torch.empty(0, dtype=torch.int64, device=dev)
    if voxel_map.n_voxels == 0:
        return empty
    s = int(ray_stride_px)
    ends, ray_dirs, origins = [], [], []
    for depth_m, K, T_world_cam in views:
        d = depth_m[::s, ::s].to(dev)
        rows, cols = torch.nonzero(d > margin_m, as_tuple=True)
        if rows.numel() == 0:
            continue
        ends.append(d[rows, cols].to(torch.float64) - margin_m)  # camera depth of each ray's last free point
        Kd = K.to(dev, torch.float64)
        T = T_world_cam.detach().to(dev, torch.float64)
        x = (cols.to(torch.float64) * s - Kd[0, 2]) / Kd[0, 0]
        y = (rows.to(torch.float64) * s - Kd[1, 2]) / Kd[1, 1]
        ray_dirs.append(torch.stack([x, y, torch.ones_like(x)], -1) @ T[:3, :3].T)  # [R, 3], camera z component 1
        origins.append(T[:3, 3].float().expand(rows.numel(), 3))
    if not ends:
        return empty
    t_end, dirs, origin_rays = torch.cat(ends), torch.cat(ray_dirs), torch.cat(origins).T.contiguous()  # [3, R]
    dt = step_m / dirs.norm(dim=-1)  # camera-depth step of each ray
    n_steps = torch.ceil(t_end / dt).to(torch.int64)  # samples 0..n_steps, the last one at t_end
    order = torch.argsort(n_steps)  # chunk rays of similar length together
    steps_sorted = n_steps[order].tolist()
    # float32 from here: a sample that lands in the neighbouring voxel only shifts one count. Per axis, so
    # every elementwise operation runs over a contiguous [r, width] block (a [r, width, 3] layout costs
    # ~2.5x as much on a CPU: broadcasts and int64 conversions over an inner dimension of 3)
    dirs_xyz = dirs.float().T.contiguous()  # [3, R]
    dt, t_end = dt.float(), t_end.float()
    inv_v = 1.0 / voxel_map.voxel_size_m
    out = []
    start, n_rays = 0, len(steps_sorted)
    while start < n_rays:
        # size the chunk so that its longest (last, as sorted) ray stays within the sample budget
        size0 = max(1, _SAMPLE_BUDGET // (steps_sorted[start] + 1))
        size = max(1, _SAMPLE_BUDGET // (steps_sorted[min(n_rays, start + size0) - 1] + 1))
        stop = min(n_rays, start + size)
        ids = order[start:stop]
        width = steps_sorted[stop - 1] + 1
        k = torch.arange(width, device=dev, dtype=torch.float32)
        t = torch.minimum(k[None, :] * dt[ids, None], t_end[ids, None])  # [r, width], padded with t_end
        cell_xyz = (torch.floor((dirs_xyz[a, ids, None] * t + origin_rays[a, ids, None]) * inv_v).to(torch.int64)
                    for a in range(3))
        idx = voxel_map.lookup_allocated_xyz(*cell_xyz)  # [r, width], -1 where nothing is allocated
        first = torch.ones_like(idx, dtype=torch.bool)
        first[:, 1:] = idx[:, 1:] != idx[:, :-1]  # a ray never re-enters a voxel
        keep = first & (idx >= 0) & (idx != idx[:, -1:])  # the last column is each ray's end point
        out.append(idx[keep])
        start = stop
    return torch.cat(out) if out else empty


def evidence_active(hits: torch.Tensor, free: torch.Tensor, config: EvidenceConfig,
                    surface_cells: torch.Tensor | None = None) -> torch.Tensor:
    """``[M]`` bool active mask from the counters ``hits [M]``, ``free [M]`` and the observed surface cells
    per voxel ``surface_cells [M]`` (None: not used) (module docstring's rule)."""
    empty = (free >= config.min_free_px) & (hits < config.min_hit_ratio * (hits + free))
    if surface_cells is not None:
        empty &= surface_cells < config.min_surface_cells
    return ~empty


@torch.no_grad()
def observe_frame(voxel_map: VoxelMap, frame: FrameData, T_world_cam: torch.Tensor, points_world: torch.Tensor,
                  config: EvidenceConfig, point_weight: float = 1.0,
                  point_voxels: torch.Tensor | None = None) -> EvidenceUpdate:
    """Add one posed frame's evidence to ``voxel_map`` and update its active mask.

    Call after the frame's points were allocated.

    Args:
        voxel_map: the map to update.
        frame: the frame (its filtered depth casts the free-space rays).
        T_world_cam: ``[4, 4]`` its camera-to-world pose.
        points_world: ``[N, 3]`` the frame's back-projected depth points (world metres), e.g. the
            allocation points.
        config: :class:`EvidenceConfig`.
        point_weight: pixels each point stands for (``stride**2``, ``MappingConfig.stride_for``).
        point_voxels: ``[N]`` int64 the allocated voxel of each point (-1: none) when the caller has looked
            them up already (:meth:`~.voxel_map.VoxelMap.locate_surface_points`); None: looked up here.
    """
    return observe_frames(voxel_map, [(frame, T_world_cam)], points_world, config, point_weight, point_voxels)


def observe_frames(voxel_map: VoxelMap, frames: list[tuple[FrameData, torch.Tensor]], points_world: torch.Tensor,
                   config: EvidenceConfig, point_weight: float = 1.0,
                   point_voxels: torch.Tensor | None = None) -> EvidenceUpdate:
    """:func:`observe_frame` for several posed frames at once (a realtime mapper fusing the frames it caught up on):
    their depth points' and free-space rays' evidence added together, then the active mask updated once. The
    evidence is the frames' in turn (sums of counts) except that each frame's rays also count as free space the
    voxels the later frames of the batch allocated, and the mask is not updated between the frames.

    Args:
        frames: ``(frame, T_world_cam [4, 4])`` pairs, after all their points were allocated.
        points_world: ``[N, 3]`` all the frames' depth points, concatenated; the rest as :func:`observe_frame`.
    """
    if not frames:
        raise ValidationError("frames", "needs at least one (frame, T_world_cam) pair")
    if points_world.dim() != 2 or points_world.shape[-1] != 3:
        raise ShapeError("points_world", tuple(points_world.shape), "[N, 3]")
    if point_voxels is None:
        point_voxels = voxel_map.lookup_allocated_cells(voxel_map.points_to_voxel_coords(points_world))
    elif point_voxels.shape != points_world.shape[:1]:
        raise ShapeError("point_voxels", tuple(point_voxels.shape), f"[{points_world.shape[0]}]")
    hit_idx = point_voxels[point_voxels >= 0]
    by_stride: dict[int, list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]] = {}  # the frames' ray strides
    for frame, T_world_cam in frames:
        by_stride.setdefault(config.ray_stride_px(frame.height, frame.width), []).append(
            (frame.depth_m, frame.K, T_world_cam))
    free_px = 0.0
    for i, (stride, views) in enumerate(by_stride.items()):  # a ray stands for stride**2 pixels
        free_idx = free_space_voxels_many(voxel_map, views, stride, config.margin_m,
                                          config.sample_step_ratio * voxel_map.voxel_size_m)
        free_weight = float(stride ** 2)
        voxel_map.add_evidence(hit_idx if i == 0 else hit_idx[:0], free_idx, point_weight, free_weight)
        free_px += float(free_idx.numel()) * free_weight
    changed = voxel_map.set_active(evidence_active(voxel_map.voxel_hits, voxel_map.voxel_free, config,
                                                   voxel_map.surface_cell_counts()))
    return EvidenceUpdate(hit_px=float(hit_idx.numel()) * point_weight, free_px=free_px, changed=changed,
                          n_inactive=voxel_map.n_voxels - voxel_map.n_active)
