"""Volume renderer over the sparse voxel map (paper section 3.1, eq. 1-4).

Pipeline (all batched over rays, no per-ray Python loops):

1. :func:`camera_rays` - pixel rays with ``dir_cam = ((u - cx) / fx, (v - cy) / fy, 1)``, so the ray
   parameter ``t`` **is camera z-depth** (metres) and rendered depth compares directly to depth maps.
   Differentiable w.r.t. ``T_world_cam``.
2. :func:`~.raycast.intersect_voxels` - each ray's first ``M_h`` allocated voxels within ``t <= D_max``,
   in order of entry, by a vectorised Amanatides-Woo DDA over the map's dense index grid that skips
   runs of empty octree blocks (see :mod:`.raycast`; :func:`~.raycast.intersect_voxels_reference` is
   the plain version it is tested against). Rays are clipped to the bounding box of the allocated
   voxels first.
3. :func:`sample_along_hits` - samples every ``step_ratio * voxel_size_m`` metres (metric, along the
   ray) over the union of hit segments: stratified with jitter in training, midpoints in inference.
4. :func:`render_rays` - evaluates an :data:`~.field.SDFField` at the samples and composites depth
   and colour with ``w = sigmoid(s / b) * sigmoid(-s / b)``; samples beyond the first front-facing
   zero crossing plus the truncation ``tr`` get weight 0 (paper: no negative truncation, mask instead).

Units: ``t`` / depth in t-units (camera z-depth metres for :func:`camera_rays` rays; metres along the
ray for unit directions); SDF, truncation and step in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from ..errors import ConfigError, ShapeError, ValidationError
from ..map import VoxelMap
from ..map.field import NeuralField, SDFDecoder, SDFField
from .raycast import (
    VoxelHits,
    grid_walk_planes,
    intersect_voxels,
    intersect_voxels_fixed,
    intersect_voxels_reference,
)

__all__ = [
    "RenderConfig",
    "image_chunk_rays",
    "camera_rays",
    "camera_directions",
    "VoxelHits",
    "intersect_voxels",
    "intersect_voxels_reference",
    "RaySamples",
    "sample_along_hits",
    "RenderOutput",
    "render_rays",
    "render_rays_fixed",
    "composite",
    "first_surface",
    "band_samples",
    "band_jitter",
    "band_sample_count",
    "render_band",
    "band_field_samples",
    "BandSamples",
    "RenderedImage",
    "render_depth_image",
]

@dataclass(frozen=True)
class RenderConfig:
    """Renderer options.

    Example: 0.2 m voxels, ``step_ratio=0.1`` -> a sample every 2 cm; ``max_distance_m=10`` with no
    ``max_hits`` -> ``M_h = floor(sqrt(3) * 10 / 0.2) + 4 = 90``.
    """

    truncation_m: float = 0.1
    """Paper ``tr``: samples more than ``tr`` (metres along the ray) behind the first zero crossing get no
    weight; the losses' free-space target and SDF band (Vox-Fusion's 0.1 m)."""
    weight_scale_m: float = 0.01
    """Scale ``b`` in ``w = sigmoid(s / b) * sigmoid(-s / b)``. The paper writes ``tr`` here, but
    Vox-Fusion's code divides an SDF already in units of ``tr`` by ``tr`` again, so its effective scale
    is ``tr**2 / 1 m`` = 0.01 m for ``tr`` = 0.1 m; a scale of ``tr`` itself would bias depth by
    centimetres because the weights are cut asymmetrically behind the surface. Keep the sample step
    (``step_ratio * voxel_size_m``) at most about ``2 b`` so the weight peak is always sampled."""
    step_ratio: float = 0.1
    """Sample spacing as a fraction of the voxel edge (paper 0.05-0.1; Vox-Fusion's code 0.1)."""
    max_distance_m: float = 10.0
    """``D_max``: no samples beyond ``t = D_max`` (t-units: camera z-depth for camera rays)."""
    max_hits: int | None = None
    """``M_h`` override; None derives it from ``D_max`` (see :meth:`max_hits_for`)."""
    cuda_graphs: bool = False
    """A session's occlusion renders on a CUDA device replay a CUDA graph of the whole image
    (:class:`~.render_graphs.OcclusionGraphs`: one launch and one read-back per image instead of ~350 operators and
    two read-backs; the same image up to float rounding). Off until measured on a GPU: ``make bench-gpu``'s render
    section times it beside the eager render."""

    def __post_init__(self) -> None:
        for name in ("truncation_m", "weight_scale_m", "step_ratio", "max_distance_m"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val > 0):
                raise ConfigError(name, f"must be a positive finite number, got {val}")
        if self.step_ratio > 1:
            raise ConfigError("step_ratio", f"must be <= 1 (fraction of a voxel), got {self.step_ratio}")
        if self.max_hits is not None and self.max_hits < 1:
            raise ConfigError("max_hits", f"must be >= 1 or None, got {self.max_hits}")

    def max_hits_for(self, voxel_size_m: float) -> int:
        """``M_h``: ``max_hits`` if set, else the most voxels a segment of length ``D_max`` can cross.

        A segment crosses at most ``ceil(|L_a| / v)`` grid planes of axis ``a``, so it visits at most
        ``1 + sum_a ceil(|L_a| / v) <= 4 + sqrt(3) * L / v`` cells; with ``L = D_max`` that is
        ``floor(sqrt(3) * D_max / v) + 4``. The nearest voxels always come first, so a smaller override
        only drops the far ones (and their compute).
        """
        if self.max_hits is not None:
            return self.max_hits
        return int(math.floor(math.sqrt(3.0) * self.max_distance_m / voxel_size_m)) + 4


def _as_tensor(x: torch.Tensor | np.ndarray, field: str, shape: tuple[int, ...],
               device: torch.device | None = None) -> torch.Tensor:
    t = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x, dtype=np.float64))
    if tuple(t.shape) != shape:
        raise ShapeError(field, tuple(t.shape), str(shape))
    if not t.is_floating_point():
        t = t.to(torch.float64)
    return t if device is None else t.to(device)


def camera_directions(K: torch.Tensor, pixels_uv: torch.Tensor) -> torch.Tensor:
    """Camera-frame ray directions ``[N, 3]`` float64 through pixels ``[N, 2]`` ``(u, v)`` of intrinsics
    ``K [3, 3]``: ``((u - cx) / fx, (v - cy) / fy, 1)`` (z component 1, so ``t`` along the ray is camera depth;
    :func:`camera_rays` turns them into the world)."""
    Kt = K.to(pixels_uv.device, torch.float64)
    uv = pixels_uv.to(torch.float64)
    x = (uv[:, 0] - Kt[0, 2]) / Kt[0, 0]
    y = (uv[:, 1] - Kt[1, 2]) / Kt[1, 1]
    return torch.stack([x, y, torch.ones_like(x)], -1)


def camera_rays(K: torch.Tensor | np.ndarray, T_world_cam: torch.Tensor | np.ndarray,
                pixels_uv: torch.Tensor | None = None, width: int | None = None, height: int | None = None,
                dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """World-frame rays through pixels.

    Args:
        K: ``[3, 3]`` intrinsics for the image resolution the pixels refer to.
        T_world_cam: ``[4, 4]`` camera-to-world (OpenCV axes); a torch tensor keeps the autograd graph.
        pixels_uv: ``[N, 2]`` pixel coordinates ``(u, v)`` (column, row; integer = pixel index, the
            convention of :func:`~.geometry.backproject_depth`); None -> every pixel of a
            ``width x height`` image in row-major order (``N = H * W``).
        dtype: floating dtype of the outputs.

    Returns:
        ``origins [N, 3]`` (camera centre) and ``dirs [N, 3]`` (world frame, NOT unit: camera-frame
        z component 1, so ``origins + t * dirs`` is at camera depth ``t``).
    """
    T = _as_tensor(T_world_cam, "T_world_cam", (4, 4))
    Kt = _as_tensor(K, "K", (3, 3), T.device).to(torch.float64)
    if pixels_uv is None:
        if width is None or height is None or width < 1 or height < 1:
            raise ValidationError("width/height", "give pixels_uv or a positive width and height")
        v, u = torch.meshgrid(torch.arange(height, device=T.device, dtype=torch.float64),
                              torch.arange(width, device=T.device, dtype=torch.float64), indexing="ij")
        uv = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    else:
        if pixels_uv.dim() != 2 or pixels_uv.shape[1] != 2:
            raise ShapeError("pixels_uv", tuple(pixels_uv.shape), "[N, 2]")
        uv = pixels_uv.to(T.device, torch.float64)
    return rays_from_directions(camera_directions(Kt, uv), T, dtype)


def rays_from_directions(d_cam: torch.Tensor, T_world_cam: torch.Tensor,
                         dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`camera_rays` from camera-frame directions ``d_cam [N, 3]`` (:func:`camera_directions`) and a pose
    ``T_world_cam [4, 4]`` tensor on their device: ``origins [N, 3]`` and world ``dirs [N, 3]`` in ``dtype``. Only
    device arithmetic (a CUDA graph can hold it, the pose copied into its input between replays)."""
    dirs = d_cam.to(T_world_cam.dtype) @ T_world_cam[:3, :3].transpose(0, 1)
    origins = T_world_cam[:3, 3].expand_as(dirs)
    return origins.to(dtype), dirs.to(dtype)


@dataclass
class RaySamples:
    """Samples along rays: ``t [N, S]`` (t-units, ascending, 0 where masked), ``voxel_idx [N, S]`` int64
    (-1 where masked), ``mask [N, S]`` bool. ``S`` is the most samples any ray of the batch needs."""

    t: torch.Tensor
    voxel_idx: torch.Tensor
    mask: torch.Tensor


@torch.no_grad()
def sample_along_hits(hits: VoxelHits, dir_norm: torch.Tensor, step_m: float, training: bool,
                      generator: torch.Generator | None = None) -> RaySamples:
    """Sample the union of each ray's hit segments every ``step_m`` metres (metric, along the ray).

    A ray whose hit segments total ``L`` metres gets ``n = ceil(L / step_m)`` samples, one per stratum
    of length ``L / n <= step_m`` laid over the segments end to end: uniformly jittered in a stratum
    when ``training`` (drawn from ``generator``, which may live on the CPU), at its midpoint otherwise.

    Args:
        hits: from :func:`intersect_voxels`.
        dir_norm: ``[N]`` Euclidean length of each ray direction (metres per unit ``t``).
    """
    if not step_m > 0:
        raise ValidationError("step_m", f"must be > 0, got {step_m}")
    n, m = hits.voxel_idx.shape
    dev = hits.t_entry.device
    dtype = hits.t_entry.dtype
    if m == 0:
        return RaySamples(torch.zeros(n, 0, dtype=dtype, device=dev),
                          torch.full((n, 0), -1, dtype=torch.int64, device=dev),
                          torch.zeros(n, 0, dtype=torch.bool, device=dev))
    lengths, cum, count = _sample_counts(hits, dir_norm, step_m)
    return _place_samples(hits, dir_norm, lengths, cum, count, int(count.max()), training, generator)


def _sample_counts(hits: VoxelHits, dir_norm: torch.Tensor,
                   step_m: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`sample_along_hits`' first half (``M >= 1`` hit columns): each hit segment's length ``[N, M]``
    (metres, float64, 0 for padding), their running sum ``[N, M]`` and each ray's sample count ``[N]`` int64."""
    n, m = hits.voxel_idx.shape
    dn = dir_norm.to(hits.t_entry.device, torch.float64)[:, None]
    seg_valid = hits.voxel_idx >= 0
    lengths = torch.where(seg_valid, (hits.t_exit - hits.t_entry).to(torch.float64).clamp(min=0) * dn,
                          torch.zeros_like(dn).expand(n, m))
    cum = torch.cumsum(lengths, 1)
    total = cum[:, -1]
    count = torch.ceil(total / step_m - 1e-9).clamp(min=0).to(torch.int64)
    count = torch.where(total > 0, count.clamp(min=1), torch.zeros_like(count))
    return lengths, cum, count


def _place_samples(hits: VoxelHits, dir_norm: torch.Tensor, lengths: torch.Tensor, cum: torch.Tensor,
                   count: torch.Tensor, s: int, training: bool, generator: torch.Generator | None) -> RaySamples:
    """:func:`sample_along_hits`' second half: ``s`` (the largest ``count``) sample columns laid over the segments."""
    n, m = hits.voxel_idx.shape
    dev = hits.t_entry.device
    dtype = hits.t_entry.dtype
    dn = dir_norm.to(dev, torch.float64)[:, None]
    total = cum[:, -1]
    j = torch.arange(s, device=dev, dtype=torch.float64)
    if training:
        gdev = generator.device if generator is not None else dev
        jitter = torch.rand(n, s, generator=generator, device=gdev, dtype=torch.float64).to(dev)
    else:
        jitter = torch.full((n, s), 0.5, dtype=torch.float64, device=dev)
    u = (j + jitter) * (total / count.clamp(min=1))[:, None]
    mask = j[None, :] < count[:, None]
    seg = torch.searchsorted(cum.contiguous(), u.contiguous(), right=True).clamp(max=m - 1)
    start = (cum - lengths).gather(1, seg)
    te = hits.t_entry.to(torch.float64).gather(1, seg)
    tx = hits.t_exit.to(torch.float64).gather(1, seg)
    t = torch.minimum(torch.maximum(te + (u - start) / dn, te), tx)
    t = torch.where(mask, t, torch.zeros_like(t)).to(dtype)
    vidx = torch.where(mask, hits.voxel_idx.gather(1, seg), torch.full_like(seg, -1))
    return RaySamples(t, vidx, mask)


@dataclass
class RenderOutput:
    """What :func:`render_rays` returns. ``N`` rays, ``S`` samples per ray.

    Attributes:
        depth: ``[N]`` rendered depth in t-units (camera z-depth for camera rays); 0 where no hit.
        color: ``[N, 3]`` RGB in [0, 1], or None when the field has no colour.
        weight_sum: ``[N]`` sum of unnormalised weights (0 where no hit; about
            ``b / (step * cos(incidence))`` for one clean surface).
        hit: ``[N]`` bool, the ray hit an allocated voxel (has samples).
        surface: ``[N]`` bool, a front-facing zero crossing (+ to -) was found among the samples.
        t: ``[N, S]`` sample parameters (no gradient). sdf: ``[N, S]`` SDF in metres (0 where masked).
        weights: ``[N, S]`` normalised compositing weights. sample_mask: ``[N, S]`` bool.
        dir_norm: ``[N]`` metres per unit ``t``. truncation_m: the ``tr`` used (losses reuse it).
    """

    depth: torch.Tensor
    color: torch.Tensor | None
    weight_sum: torch.Tensor
    hit: torch.Tensor
    surface: torch.Tensor
    t: torch.Tensor
    sdf: torch.Tensor
    weights: torch.Tensor
    sample_mask: torch.Tensor
    dir_norm: torch.Tensor
    truncation_m: float


def render_rays(voxel_map: VoxelMap, field: SDFField | SDFDecoder, origins: torch.Tensor, dirs: torch.Tensor,
                config: RenderConfig, training: bool = False, generator: torch.Generator | None = None,
                t_far: torch.Tensor | None = None, with_color: bool = True) -> RenderOutput:
    """Render depth (and colour) along rays (paper eq. 1-4).

    Args:
        voxel_map: the sparse map (decides where samples go).
        field: an :class:`~.field.SDFDecoder` (wrapped as ``NeuralField(voxel_map, decoder)``) or any
            :data:`~.field.SDFField` callable, e.g. an analytic SDF.
        origins, dirs: ``[N, 3]`` world rays (e.g. from :func:`camera_rays`); gradients flow to both
            through the sample points ``origins + t * dirs`` (``t`` itself is not differentiated).
        config: :class:`RenderConfig`.
        training: stratified jittered samples (True) or deterministic midpoints (False).
        generator: RNG for the jitter.
        t_far: optional ``[N]`` per-ray cap on ``t`` in addition to ``D_max``.
        with_color: False skips a neural field's colour head (``color`` is then None; depth-only callers).
    """
    origins, dirs, dn = _rays_on_map(voxel_map, origins, dirs)
    hits = intersect_voxels(voxel_map, origins, dirs, config.max_distance_m,
                            config.max_hits_for(voxel_map.voxel_size_m), t_far)
    smp = sample_along_hits(hits, dn, config.step_ratio * voxel_map.voxel_size_m, training, generator)
    return _shade(voxel_map, field, origins, dirs, dn, smp, hits.hit, config, with_color)[0]


def _rays_on_map(voxel_map: VoxelMap, origins: torch.Tensor,
                 dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Checked rays in the map's device and dtype, and each direction's length ``[N]`` (metres per unit ``t``)."""
    if origins.dim() != 2 or origins.shape[1] != 3:
        raise ShapeError("origins", tuple(origins.shape), "[N, 3]")
    if dirs.shape != origins.shape:
        raise ShapeError("dirs", tuple(dirs.shape), f"{tuple(origins.shape)}")
    dtype = voxel_map.embeddings.dtype
    origins = origins.to(voxel_map.device, dtype)
    dirs = dirs.to(voxel_map.device, dtype)
    return origins, dirs, dirs.detach().norm(dim=-1)


def _shade(voxel_map: VoxelMap, field: SDFField | SDFDecoder, origins: torch.Tensor, dirs: torch.Tensor,
           dn: torch.Tensor, smp: RaySamples, hit: torch.Tensor, config: RenderConfig,
           with_color: bool, queries: int | None = None) -> tuple[RenderOutput, torch.Tensor | None]:
    """The field at the samples inside the map and :func:`composite`. ``queries`` None: exactly those samples (one
    read-back: which they are); else at most that many, picked without waiting for the device, and with the output
    a bool scalar on the device that says whether more were inside (the output must then not be used)."""
    if isinstance(field, SDFDecoder):
        field = NeuralField(voxel_map, field)
    # the samples under the mask lie in hit voxels (index >= 0): the neural field skips its check (a read-back)
    neural = isinstance(field, NeuralField)
    evaluate = field.evaluate_unchecked if neural else field
    t, mask = smp.t, smp.mask
    n, s = t.shape
    pts = origins[:, None, :] + dirs[:, None, :] * t[:, :, None]  # [N, S, 3]
    flat = mask.reshape(-1)
    overflow = None
    if queries is None:
        inside = torch.nonzero(flat).squeeze(1)  # one read-back for both gathers
        rows = inside
    else:  # a fixed count: the padding points at a spare slot past the samples, and reads the last sample
        inside = torch.nonzero_static(flat, size=queries, fill_value=n * s).squeeze(1)
        overflow = flat.sum() > queries
        rows = inside.clamp(max=n * s - 1)
    vidx = smp.voxel_idx.reshape(-1).index_select(0, rows)
    args = (pts.reshape(-1, 3).index_select(0, rows), vidx if queries is None else vidx.clamp(min=0))
    sdf_v, rgb_v = evaluate(*args, with_color=False) if neural and not with_color else evaluate(*args)
    rgb_v = rgb_v if with_color else None
    if queries is None:
        sdf = sdf_v.new_zeros(n, s).masked_scatter(mask, sdf_v)
        rgb = None if rgb_v is None else rgb_v.new_zeros(n, s, 3).masked_scatter(mask[:, :, None].expand(n, s, 3),
                                                                                  rgb_v)
    else:
        sdf = sdf_v.new_zeros(n * s + 1).index_copy_(0, inside, sdf_v)[:-1].reshape(n, s)
        rgb = None if rgb_v is None else rgb_v.new_zeros(n * s + 1, 3).index_copy_(0, inside, rgb_v)[:-1].reshape(
            n, s, 3)
    return composite(sdf, rgb, t, mask, dn, hit, config), overflow


@torch.no_grad()
def render_rays_fixed(voxel_map: VoxelMap, field: SDFField | SDFDecoder, origins: torch.Tensor, dirs: torch.Tensor,
                      config: RenderConfig, with_color: bool = True) -> RenderOutput | None:
    """:func:`render_rays` in inference mode (midpoint samples, no ``t_far``) with the ray walk of fixed shapes
    (:func:`~.raycast.intersect_voxels_fixed`): two read-backs in all (the sample count together with the walk's
    doubt flag, then the samples inside the map) where :func:`render_rays` has ~10, for a GPU, where each one
    waits for the device. The same result (the walk's padding adds nothing); None where the fixed walk does not
    apply (no dense index grid, a map too long for it) or doubts its result: call :func:`render_rays` then."""
    origins, dirs, dn = _rays_on_map(voxel_map, origins, dirs)
    got = intersect_voxels_fixed(voxel_map, origins, dirs, config.max_distance_m,
                                 config.max_hits_for(voxel_map.voxel_size_m))
    if got is None:
        return None
    hits, doubt = got
    lengths, cum, count = _sample_counts(hits, dn, config.step_ratio * voxel_map.voxel_size_m)
    s, doubtful = torch.stack([count.max(), doubt.to(torch.int64)]).tolist()  # the walk's one read-back
    if doubtful:
        return None
    smp = _place_samples(hits, dn, lengths, cum, count, s, training=False, generator=None)
    return _shade(voxel_map, field, origins, dirs, dn, smp, hits.hit, config, with_color)[0]


@dataclass(frozen=True)
class RenderBudget:
    """Fixed sizes of :func:`render_rays_static` (host integers, chosen from an earlier render of the same map):
    ``samples`` per ray, ``queries`` of the field in all (samples inside the map), ``planes``: crossings per axis of
    the ray walk (:func:`~.raycast.fixed_walk_planes` or more)."""

    samples: int
    queries: int
    planes: int

    def __post_init__(self) -> None:
        for name in ("samples", "queries", "planes"):
            if getattr(self, name) < 1:
                raise ValidationError(name, f"must be >= 1, got {getattr(self, name)}")


@torch.no_grad()
def render_rays_static(voxel_map: VoxelMap, field: SDFField | SDFDecoder, origins: torch.Tensor, dirs: torch.Tensor,
                       config: RenderConfig, budget: RenderBudget,
                       with_color: bool = True) -> tuple[RenderOutput, torch.Tensor] | None:
    """:func:`render_rays_fixed` with every size fixed by ``budget`` and no read-back at all: what a CUDA graph of an
    occlusion render holds (:mod:`.render_graphs`). Returns the output (``[N, budget.samples]`` sample columns, those
    past each ray's own masked) and ``doubt``, a bool scalar on the device, True where the output must not be used:
    the walk doubts itself (:func:`~.raycast.intersect_voxels_fixed`), a ray needs more samples or the rays more field
    queries than the budget holds (render again with :func:`render_rays_fixed`, and a larger budget). Within its
    budget the same depth and colour as :func:`render_rays_fixed` up to float rounding (sums over more, empty
    columns). None where the fixed walk does not apply (no dense index grid, a map too long for it)."""
    origins, dirs, dn = _rays_on_map(voxel_map, origins, dirs)
    got = intersect_voxels_fixed(voxel_map, origins, dirs, config.max_distance_m,
                                 config.max_hits_for(voxel_map.voxel_size_m), n_planes=budget.planes)
    if got is None:
        return None
    hits, doubt = got
    lengths, cum, count = _sample_counts(hits, dn, config.step_ratio * voxel_map.voxel_size_m)
    smp = _place_samples(hits, dn, lengths, cum, count, budget.samples, training=False, generator=None)
    out, overflow = _shade(voxel_map, field, origins, dirs, dn, smp, hits.hit, config, with_color, budget.queries)
    return out, doubt | (count.max() > budget.samples) | overflow


def render_budget(voxel_map: VoxelMap, out: RenderOutput, headroom: float = 1.25) -> RenderBudget | None:
    """A :class:`RenderBudget` for later renders of maps like ``voxel_map`` (a snapshot of the same session), from a
    render of it (``out``, :func:`render_rays_fixed`'s): the samples per ray and the field queries it needed times
    ``headroom`` (rounded up to multiples of 8 and 4096), the walk's planes from the index grid's whole box, so a map
    that grows inside the grid needs no new budget (:func:`~.raycast.grid_walk_planes`). None where the map has no
    dense index grid or is too long for the fixed walk. Reads ``out`` back."""
    grid = voxel_map.index_grid() if voxel_map.voxel_bounds is not None else None
    planes = None if grid is None else grid_walk_planes(grid)
    if planes is None:
        return None
    samples, queries = out.t.shape[1], int(out.sample_mask.sum())

    def up(x: float, m: int) -> int:
        return max(m, int(math.ceil(x * headroom / m)) * m)

    return RenderBudget(samples=up(samples, 8), queries=up(queries, 4096), planes=planes)


def first_surface(sdf: torch.Tensor, t: torch.Tensor, mask: torch.Tensor, dir_norm: torch.Tensor, truncation_m: float
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each ray's first front-facing zero crossing (+ to -, between two samples inside the map) and the samples the
    compositing keeps: ``(surface [N] bool, keep [N, S] bool)``, ``keep`` False behind the crossing plus the
    truncation (every sample of a ray without one). ``sdf [N, S]`` (0 outside ``mask``), ``t [N, S]`` ascending,
    ``dir_norm [N]`` metres per unit ``t``. No gradient, no host synchronisation; :func:`composite` and the mapper's
    fused losses (:func:`~..losses.band_losses`) share it."""
    n, s = t.shape
    cross = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0) & mask[:, :-1] & mask[:, 1:]
    surface = cross.any(1)
    if s > 1:
        t_cross = t.gather(1, cross.to(torch.int8).argmax(1, keepdim=True))
    else:
        t_cross = t.new_zeros(n, 1)
    return surface, ~surface[:, None] | (t <= t_cross + truncation_m / dir_norm.clamp(min=1e-12)[:, None])


def composite(sdf: torch.Tensor, rgb: torch.Tensor | None, t: torch.Tensor, mask: torch.Tensor,
              dir_norm: torch.Tensor, hit: torch.Tensor, config: RenderConfig) -> RenderOutput:
    """Depth and colour from the field at each ray's samples (paper eq. 1-4), the stage every sampler shares.

    Args:
        sdf: ``[N, S]`` metres (anything where ``mask`` is False; it gets no weight); rgb: ``[N, S, 3]`` or None.
        t: ``[N, S]`` ascending sample parameters (t-units); mask: ``[N, S]`` bool, samples the field covers.
        dir_norm: ``[N]`` metres per unit ``t``; hit: ``[N]`` bool, rays that have samples.

    Weights ``w = sigmoid(s / b) sigmoid(-s / b)``, zero beyond the first front-facing zero crossing plus
    the truncation. Fixed shapes and no host synchronisation.
    """
    sdf = torch.where(mask, sdf, torch.zeros_like(sdf))
    b = config.weight_scale_m
    w = torch.sigmoid(sdf / b) * torch.sigmoid(-sdf / b) * mask
    with torch.no_grad():
        surface, keep = first_surface(sdf.detach(), t, mask, dir_norm, config.truncation_m)
    w = w * keep
    w_sum = w.sum(1)
    weights = w / w_sum.clamp(min=1e-20)[:, None]
    depth = (weights * t).sum(1)
    color = None
    if rgb is not None:
        # per channel over [N, S] columns: the same sums to the bit as ``(weights[:, :, None] * rgb).sum(1)``, where
        # PyTorch's CPU kernels broadcast over an inner dimension of 3 slowly (forward and backward at 1024 x 7
        # samples, 2-core AMD EPYC: ~0.5 against ~0.8 ms; the backward's sums round differently)
        rgb = torch.where(mask[:, :, None].expand(-1, -1, 3).contiguous(), rgb, torch.zeros_like(rgb))
        color = torch.stack([(weights * rgb[:, :, c]).sum(1) for c in range(3)], 1)
    return RenderOutput(depth=depth, color=color, weight_sum=w_sum, hit=hit, surface=surface, t=t,
                        sdf=sdf, weights=weights, sample_mask=mask, dir_norm=dir_norm,
                        truncation_m=config.truncation_m)


def band_samples(depth: torch.Tensor, dir_norm: torch.Tensor, n_band: int, n_free: int, truncation_m: float,
                 free_range_m: float, training: bool, generator: torch.Generator | None = None,
                 jitter: torch.Tensor | None = None) -> torch.Tensor:
    """A fixed number of samples per ray around an observed depth (for rays with known depth: mapping).

    ``n_free`` strata over the ``free_range_m`` metres in front of the truncation band, then ``n_band``
    strata over the band ``|D - t| |d| <= tr`` itself; jittered when ``training``, midpoints otherwise.

    Args:
        depth: ``[N]`` observed depth ``D`` in t-units (> 0); dir_norm: ``[N]`` metres per unit ``t``.
        jitter: ``[N, n_free + n_band]`` uniform ``[0, 1)`` positions in the strata, drawn by the caller
            (:func:`band_jitter`, the same draw as ``training`` with ``generator``), so that a compiled caller
            keeps the random draw outside its graph; None: drawn here.

    Returns ``t [N, n_free + n_band]``, ascending per ray, >= 0 (a free stratum that would start behind
    the camera is squeezed into ``[0, D - tr / |d|]``).
    """
    if n_band < 1 or n_free < 0:
        raise ValidationError("n_band/n_free", f"need n_band >= 1 and n_free >= 0, got {n_band}/{n_free}")
    n = depth.shape[0]
    dev, dtype = depth.device, depth.dtype
    dn = dir_norm.to(dev, dtype).clamp(min=1e-12)
    band_lo = (depth - truncation_m / dn).clamp(min=0)
    band_hi = depth + truncation_m / dn
    free_lo = (band_lo - free_range_m / dn).clamp(min=0)
    k = n_free + n_band
    if jitter is not None:
        u = jitter
    else:
        u = (band_jitter(n, k, dev, dtype, generator) if training
             else torch.full((n, k), 0.5, dtype=dtype, device=dev))
    j = torch.arange(k, device=dev, dtype=dtype)
    in_band = j >= n_free
    lo = torch.where(in_band, band_lo[:, None], free_lo[:, None])
    width = torch.where(in_band, (band_hi - band_lo)[:, None] / n_band, (band_lo - free_lo)[:, None] / max(n_free, 1))
    pos = torch.where(in_band, j - n_free, j)
    return lo + (pos + u) * width


def band_jitter(n: int, k: int, device: torch.device, dtype: torch.dtype,
                generator: torch.Generator | None = None) -> torch.Tensor:
    """``[n, k]`` uniform ``[0, 1)`` stratum positions for :func:`band_samples`, drawn from ``generator`` (on its own
    device, then moved to ``device``)."""
    gdev = generator.device if generator is not None else device
    return torch.rand(n, k, generator=generator, device=gdev, dtype=dtype).to(device)


def band_sample_count(config: RenderConfig, voxel_size_m: float, n_free: int, n_band: int | None) -> tuple[int, int]:
    """``(n_band, n_free + n_band)``: the band strata :func:`render_band` uses (``n_band``, or the renderer's step
    when None) and the samples per ray."""
    if n_band is None:
        step = config.step_ratio * voxel_size_m
        n_band = max(1, math.ceil(2 * config.truncation_m / step - 1e-9))
    return n_band, n_free + n_band


class BandSamples(NamedTuple):
    """The field at :func:`render_band`'s samples, before compositing: ``sdf [N, S]`` metres (0 where ``mask`` is
    False), ``rgb [N, S, 3]`` or None, ``t [N, S]`` ascending sample parameters (t-units, no gradient), ``mask [N, S]``
    bool (the sample lies in an allocated voxel), ``dir_norm [N]`` metres per unit ``t``."""

    sdf: torch.Tensor
    rgb: torch.Tensor | None
    t: torch.Tensor
    mask: torch.Tensor
    dir_norm: torch.Tensor


def render_band(voxel_map: VoxelMap, field: SDFDecoder | SDFField, origins: torch.Tensor, dirs: torch.Tensor,
                depth: torch.Tensor, config: RenderConfig, n_free: int, free_range_m: float,
                training: bool = True, generator: torch.Generator | None = None,
                n_band: int | None = None, compact: bool | None = None,
                jitter: torch.Tensor | None = None) -> RenderOutput:
    """Render rays of known depth from a fixed number of samples per ray (:func:`band_samples`): the
    mapping renderer. Same compositing and outputs as :func:`render_rays`, but every shape is fixed by
    ``N`` and the config (``n_band``, default ``ceil(2 tr / step)``, keeps :func:`render_rays`' sample spacing
    in the band). :func:`band_field_samples` then :func:`composite`; arguments as there."""
    s = band_field_samples(voxel_map, field, origins, dirs, depth, config, n_free, free_range_m, training, generator,
                           n_band, compact, jitter)
    return composite(s.sdf, s.rgb, s.t, s.mask, s.dir_norm, s.mask.any(1), config)


def band_field_samples(voxel_map: VoxelMap, field: SDFDecoder | SDFField, origins: torch.Tensor, dirs: torch.Tensor,
                       depth: torch.Tensor, config: RenderConfig, n_free: int, free_range_m: float,
                       training: bool = True, generator: torch.Generator | None = None,
                       n_band: int | None = None, compact: bool | None = None,
                       jitter: torch.Tensor | None = None) -> BandSamples:
    """:func:`render_band`'s samples and the field at them (:class:`BandSamples`), what :func:`composite` (or the
    mapper's fused compositing and losses, :func:`~..losses.band_losses`) takes.

    Samples outside allocated voxels get no weight and no loss, so their field values are never used. With
    ``compact`` False they are evaluated anyway, at a clamped voxel index, and masked: nothing waits for the
    host, so a step can be captured (CUDA graphs, ``torch.compile``). With ``compact`` True only the samples
    inside the map are evaluated (their count is read back: free on a CPU, a wait on a GPU) and scattered
    into place; on the synthetic room ~30 % of a mapping iteration's samples (two thirds of the free-space
    ones) are outside the map. Both give the same output and gradients (tested). None: compact on a CPU.

    Args:
        field: an :class:`~.field.SDFDecoder` over ``voxel_map`` or any :data:`~.field.SDFField`.
        depth: ``[N]`` observed depth in t-units (> 0 for every ray).
        n_free, free_range_m: free-space strata and the metres in front of the band they cover.
        n_band: strata inside the band (None: the renderer's step, ``config.step_ratio``).
        compact: evaluate only the samples inside the map (above; None: on a CPU).
        jitter: the stratum positions, drawn by the caller (:func:`band_samples`); None: drawn here.
    """
    if origins.dim() != 2 or origins.shape[1] != 3:
        raise ShapeError("origins", tuple(origins.shape), "[N, 3]")
    if dirs.shape != origins.shape or depth.shape != origins.shape[:1]:
        raise ShapeError("dirs/depth", (tuple(dirs.shape), tuple(depth.shape)), f"{tuple(origins.shape)} / [N]")
    dtype = voxel_map.embeddings.dtype
    origins = origins.to(voxel_map.device, dtype)
    dirs = dirs.to(voxel_map.device, dtype)
    dn = dirs.detach().norm(dim=-1)
    n_band, _ = band_sample_count(config, voxel_map.voxel_size_m, n_free, n_band)
    t = band_samples(depth.to(voxel_map.device, dtype), dn, n_band, n_free, config.truncation_m, free_range_m,
                     training, generator, jitter).detach()
    n, s = t.shape
    if voxel_map.n_voxels == 0:  # nothing to evaluate (as render_rays: no hits)
        return BandSamples(t.new_zeros(n, s), None, t, torch.zeros(n, s, dtype=torch.bool, device=t.device), dn)
    flat = (origins[:, None, :] + dirs[:, None, :] * t[:, :, None]).reshape(-1, 3)  # [N S, 3]
    idx = voxel_map.lookup_voxels(flat.detach())
    mask = (idx >= 0).reshape(n, s)
    evaluate = NeuralField(voxel_map, field).evaluate_unchecked if isinstance(field, SDFDecoder) else field
    if compact is None:
        compact = flat.device.type == "cpu"
    if compact:
        inside = torch.nonzero(idx >= 0).squeeze(1)  # the one read-back: the count of samples inside the map
        sdf_in, rgb_in = evaluate(flat.index_select(0, inside), idx.index_select(0, inside))
        sdf = sdf_in.new_zeros(n * s).index_copy(0, inside, sdf_in)
        rgb = None if rgb_in is None else rgb_in.new_zeros(n * s, 3).index_copy(0, inside, rgb_in)
    else:  # an SDFField must then accept points outside the map too (tests: analytic surfaces)
        sdf, rgb = evaluate(flat, idx.clamp(min=0))
    return BandSamples(sdf.reshape(n, s), None if rgb is None else rgb.reshape(n, s, 3), t, mask, dn)


class RenderedImage(NamedTuple):
    """``depth [H, W]`` (camera z-depth metres, 0 where invalid), ``color [H, W, 3]`` or None,
    ``valid [H, W]`` bool (the pixel's ray found a surface)."""

    depth: torch.Tensor
    color: torch.Tensor | None
    valid: torch.Tensor


def image_chunk_rays(device: torch.device) -> int:
    """Rays per :func:`render_rays` call when rendering a whole image on ``device``. Each call costs a fixed ~450
    operators and ~9 host read-backs (sample counts, masked field queries) whatever its size: on a GPU, where those
    are launches and waits, a 256x192 occlusion image is one call (65536 rays: ~800 operators and 17 read-backs
    instead of ~5400 and 108 in 12 calls of 4096; a call's samples then take up to a few hundred MB of device
    memory); on a CPU 4096 rays keep a call's samples in cache (2-core AMD EPYC, the ``cpu`` preset's synthetic
    room, 256x192: 0.75 s in 12 calls against 1.06 s in one)."""
    return 4096 if device.type == "cpu" else 1 << 16


def image_rays(out: RenderOutput, with_color: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """An image's rays from a render: depth ``[N]`` and colour ``[N, 3]`` (None without, or unless ``with_color``)
    where a surface was found, 0 elsewhere, and that validity ``[N]`` (``surface & hit``)."""
    valid = out.surface & out.hit
    depth = torch.where(valid, out.depth, torch.zeros_like(out.depth))
    color = None
    if with_color and out.color is not None:
        color = torch.where(valid[:, None], out.color, torch.zeros_like(out.color))
    return depth, valid, color


@torch.no_grad()
def render_depth_image(voxel_map: VoxelMap, field: SDFField | SDFDecoder, K: torch.Tensor | np.ndarray,
                       T_world_cam: torch.Tensor | np.ndarray, width: int, height: int, config: RenderConfig,
                       chunk: int | None = None, with_color: bool = True,
                       fixed_walk: bool | None = None) -> RenderedImage:
    """Render a full depth (and colour) image in inference mode, ``chunk`` rays at a time (None:
    :func:`image_chunk_rays` for the map's device).

    Used for AR occlusion and evaluation. ``K`` is for the ``width x height`` resolution. ``with_color=False``
    renders depth alone (``color`` None; the colour head is skipped). ``fixed_walk`` (None: on a GPU) walks the
    rays with fixed shapes (:func:`render_rays_fixed`: fewer read-backs, the same image), falling back to
    :func:`render_rays` where that walk does not apply.
    """
    if chunk is None:
        chunk = image_chunk_rays(voxel_map.device)
    if chunk < 1:
        raise ValidationError("chunk", f"must be >= 1, got {chunk}")
    if fixed_walk is None:
        fixed_walk = voxel_map.device.type != "cpu"
    T = _as_tensor(T_world_cam, "T_world_cam", (4, 4), voxel_map.device)
    origins, dirs = camera_rays(K, T, width=width, height=height, dtype=voxel_map.embeddings.dtype)
    depth_parts, color_parts, valid_parts = [], [], []
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s:s + chunk], dirs[s:s + chunk]
        out = render_rays_fixed(voxel_map, field, o, d, config, with_color) if fixed_walk else None
        if out is None:
            out = render_rays(voxel_map, field, o, d, config, training=False, with_color=with_color)
        depth, valid, color = image_rays(out, with_color)
        depth_parts.append(depth)
        valid_parts.append(valid)
        if color is not None:
            color_parts.append(color)
    depth = torch.cat(depth_parts).reshape(height, width)
    valid = torch.cat(valid_parts).reshape(height, width)
    color = torch.cat(color_parts).reshape(height, width, 3) if color_parts else None
    return RenderedImage(depth, color, valid)
