"""Mapping (paper §4.3): voxel allocation, keyframe selection and joint optimisation of the map.

The :class:`Mapper` owns the sparse voxel map, the decoder and their optimiser. Each frame handed to
:meth:`Mapper.integrate` (with its camera pose) is fused in three steps:

1. **Allocate** a voxel for every back-projected depth point that falls in no voxel yet (the frame's depth
   was already cleaned of unsupported outliers by :func:`~.framedata.frame_to_device`), then add the
   frame's **observation evidence** (depth points per voxel, free-space rays per voxel) and deactivate
   voxels that rays have mostly seen as empty (:mod:`..map.evidence`), so they never render a surface.
2. **Keyframe test**: the frame becomes a keyframe when ``N_c / N_o`` (voxels it would newly allocate /
   voxels it observes that exist already, counted before step 1) exceeds ``keyframe_ratio``, or when no
   keyframe was taken for ``keyframe_max_interval`` frames. The first frame is always a keyframe.
3. **Optimise** ``iters`` times a window of ``window_keyframes`` random keyframes plus the newest frame,
   ``rays_per_frame`` rays each, with the paper's losses; Adam updates embeddings and decoder.

Poses here are given (known-pose mapping, ``voxfusion map``); the tracking layer adds pose estimation
and hands refined poses in the same way.
"""

from __future__ import annotations

import dataclasses
import logging
import random
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..compiled import CompiledFunction
from ..depth_filter import DepthFilterConfig
from ..errors import ConfigError, ValidationError
from ..framedata import FrameData, flat_uv, sample_valid_pixels
from ..lie import perturb_right, se3_exp_np
from ..losses import LossConfig, LossTerms, band_losses, compute_losses
from ..map import VoxelMap
from ..map.evidence import EvidenceConfig, observe_frames
from ..map.field import FieldConfig, SDFDecoder, query
from ..mesh.colors import ColorView
from ..optim import adam, adam_step
from ..render.volume import (
    RenderConfig,
    band_field_samples,
    band_jitter,
    band_sample_count,
    camera_directions,
    composite,
    render_rays,
)

if TYPE_CHECKING:
    from .presets import VoxFusionConfig

__all__ = ["MappingConfig", "Keyframe", "MappingStep", "Mapper", "make_mapper", "publish_keyframe_poses", "band_loss",
           "warm_up_pose_rates"]

log = logging.getLogger("voxfusion.mapping")


@dataclass(frozen=True)
class MappingConfig:
    """Mapping options (paper symbols in brackets)."""

    rays_per_frame: int = 1024
    """[N_m] rays sampled per window frame and iteration."""
    window_keyframes: int = 4
    """[N_kf] random keyframes optimised with the newest frame each round."""
    iters: int = 10
    """Optimisation iterations per mapping round."""
    first_frame_iters: int = 100
    """Iterations on the first frame alone (map initialisation)."""
    final_iters: int = 0
    """Iterations over random keyframe windows when the run finishes (clean-up of the whole map)."""
    lr_embeddings: float = 0.01
    lr_decoder: float = 0.005
    keyframe_ratio: float = 0.1
    """[p_kf threshold] a frame whose new/observed voxel ratio exceeds this becomes a keyframe."""
    keyframe_max_interval: int = 20
    """[N] a keyframe is forced when none was taken for this many frames."""
    map_every: int = 1
    """Run a mapping round every ``map_every``-th frame (keyframes always get one)."""
    min_depth_m: float = 0.05
    max_depth_m: float = 10.0
    """Depth outside this range is ignored (neither allocated nor supervised)."""
    min_confidence: int | None = None
    """Drop pixels whose confidence (0/1/2) is below this, when the frame has a confidence map."""
    depth_filter: DepthFilterConfig = dataclasses.field(default_factory=DepthFilterConfig)
    """Neighbourhood-support outlier filter applied to every frame's depth where it enters the engine
    (:func:`~.framedata.frame_to_device`), for tracking and mapping alike; ``enabled=false`` turns it off."""
    evidence: EvidenceConfig = dataclasses.field(default_factory=EvidenceConfig)
    """Per-voxel observation evidence and the active mask (:mod:`..map.evidence`); ``enabled=false`` turns it
    off (every allocated voxel stays active)."""
    alloc_stride: int = 1
    """Back-project every ``alloc_stride``-th pixel (per axis) for allocation, surface marks and the evidence
    (:meth:`stride_for`); 0: by image width, ``max(1, width // 320)`` (every pixel up to 639 columns, every 2nd
    at 640x480). Each point costs the same whatever the image, and at 640x480 (fx ~ 525 px) two pixels span
    under 1.6 cm at 4 m, about one 1.25 cm surface-mark cell (``voxel / 16`` at 0.2 m), so the map loses
    almost nothing (a synthetic 640x480 frame allocates 638 voxels instead of 640) while a frame's bookkeeping
    handles a quarter of the points. Measured with `cpu` sizes on the 2-core Xeon, A/B runs of `bench/run.py`
    beside the targets runs (1 -> 2): 7-Scenes 0-499 seeds 0-4 ATE 3.84 / 3.85 / 3.64 / 4.10 / 3.73 -> 3.83 /
    4.09 / 3.83 / 3.94 / 3.74 cm at 8.3-9.2 -> 10.8-11.2 frames/s; TUM fr1 desk 0.22 / 0.22 / 0.22 -> 0.22 /
    0.23 / 0.23 cm at 7.4-7.6 -> 8.3-9.0; TUM fr3 8.9-9.3 -> 10.8-11.3 frames/s (the tenth targets run: 7-Scenes
    10.4-10.5, TUM fr3 8.6-10.4); on the 320x240 synthetic room stride 2 would gain ~6 % but sits at 1.6 cm per
    step at 2 m, so 0 keeps every pixel there. The `cpu` preset uses 0; the built-in default keeps every pixel
    (the paper's behaviour)."""
    optimize_poses: bool = True
    """Jointly refine the window's camera poses (the first keyframe stays fixed). Off for known poses."""
    lr_pose: float = 1e-3
    """Adam learning rate of the pose corrections (6-vectors, metres / radians)."""
    pose_warmup_steps: int = 10
    """A frame's pose correction moves at ``lr_pose * k / pose_warmup_steps`` on its k-th Adam step (counted per
    frame, over the rounds that train it), at ``lr_pose`` from then on; 0: at ``lr_pose`` from the first step.
    Adam's first steps move every coordinate by about the learning rate whatever the gradient (the first, with
    its bias correction, by exactly ``lr_pose``), and a round's pose gradient from 256 random rays per frame is
    mostly noise: a frame the tracker had placed to a fraction of a millimetre was pushed ~1 mm and ~1 mrad per
    step, and the map was fitted to rays cast from there. A frame that is not a keyframe is trained in one round
    only (its correction is then dropped, the trajectory keeps the tracked pose), so with 10 it moves at a
    tenth to a half of the rate; a keyframe reaches full rate in its third round. Measured on the 2-core AMD
    EPYC, `cpu` sizes, one torch thread per run (0 -> 10; `docs/engine-history.md`, "TUM fr1 desk looked at
    again"), ATE cm: synthetic room seeds 0 / 1 / 2 0.136 / 0.199 / 0.229 -> 0.130 / 0.186 / 0.222, held-out
    seeds 3-6 0.839 / 0.165 / 0.161 / 0.159 -> 0.708 / 0.137 / 0.139 / 0.140, fast rotation 0.219 / 0.252 /
    0.262 -> 0.227 / 0.251 / 0.271, held-out 3-5 0.721 / 0.530 / 0.270 -> 0.576 / 0.330 / 0.276, TUM fr1 desk
    0.252 / 0.215 / 0.180 -> 0.233 / 0.171 / 0.164, 7-Scenes 0-499 3.94 / 3.60 / 3.86 -> 3.98 / 3.91 / 4.01
    (worse on every seed, within its seed spread); 5: in between, fast rotation worse. In the sixteenth targets run
    (the tracker precompiled, which rounds differently) against the fifteenth: TUM 0.252 / 0.215 / 0.180 -> 0.233 /
    0.171 / 0.164, 7-Scenes 3.91 / 3.76 / 4.09 -> 3.79 / 3.92 / 3.75, but fast rotation seed 2 0.30 -> 0.51 and
    held-out synthetic seed 3 0.66 -> 0.96 (README, "Measured results (CPU)")."""
    sampler: str = "band"
    """Where a mapping ray's samples go. ``band``: a fixed number per ray around its observed depth
    (:func:`~.render.render_band`: ``free_samples`` strata over the ``free_range_voxels`` voxel edges in
    front of the truncation band, the band itself in ``band_samples`` strata) - fixed shapes, no host
    synchronisation. ``voxels``: the paper's sampler, every ``step`` along the allocated voxels the ray
    crosses up to the depth plus the truncation (:func:`~.render.render_rays`), the reference."""
    compact_samples: bool | None = None
    """``band`` sampler: evaluate the field only at the samples inside allocated voxels (the others get no
    weight and no loss either way; :func:`~.render.render_band`'s ``compact``): True reads their count back
    once per iteration (free on a CPU; on the synthetic room ~30 % of the samples are outside the map, and a
    CPU mapping iteration ran ~20 % faster), False keeps every shape fixed and nothing waiting for the host
    (CUDA graphs). None: True on a CPU, False elsewhere."""
    free_samples: int = 6
    """``band`` sampler: free-space samples per ray (the ``voxels`` sampler averaged ~6 on the synthetic room)."""
    free_range_voxels: float = 2.0
    """``band`` sampler: free space covered in front of the band, in voxel edges (allocated voxels sit
    around observed surfaces, so farther samples would mostly fall outside the map)."""
    band_samples: int | None = None
    """``band`` sampler: samples per ray inside the truncation band ``|D - t| <= tr``, one per stratum, jittered
    every iteration. None: the renderer's spacing (``ceil(2 tr / (render.step_ratio * voxel))``, 10 for the
    paper's 0.1 m band and 2 cm step). A mapping iteration costs about what its samples cost, and jittered
    strata cover the band over the iterations, so the CPU preset uses fewer (``configs/cpu.yaml``); depth
    rendering for tracking, occlusion and evaluation keeps the renderer's step."""

    compile: bool = False
    """Run a mapping iteration's renderer and losses (:func:`band_loss`: sampling, field, compositing, the four
    terms, and through autograd their backward pass) through :func:`torch.compile` (dynamic shapes: the map
    grows), with the fixed-shape samples (``compact_samples`` is then ignored: compacting reads a count back, which
    a graph cannot hold) and the jitter drawn outside the graph from the same generator. ``band`` sampler only
    (``voxels`` stays eager). Where compilation fails the step logs one warning and runs eager. Aimed at GPUs,
    where an eager iteration is 1500-2000 operators, each a kernel launch; ``make bench-gpu`` (accel) measures it."""

    def stride_for(self, width: int) -> int:
        """The pixel stride of allocation for a ``width``-pixel image (``alloc_stride``, or 0's rule)."""
        return self.alloc_stride if self.alloc_stride > 0 else max(1, width // 320)

    def __post_init__(self) -> None:
        for name in ("rays_per_frame", "iters", "keyframe_max_interval", "map_every"):
            if getattr(self, name) < 1:
                raise ConfigError(name, f"must be >= 1, got {getattr(self, name)}")
        for name in ("window_keyframes", "first_frame_iters", "final_iters", "alloc_stride", "pose_warmup_steps"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be >= 0, got {getattr(self, name)}")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError("min_depth_m", "need 0 < min_depth_m < max_depth_m")
        if self.sampler not in ("band", "voxels"):
            raise ConfigError("sampler", f"must be 'band' or 'voxels', got {self.sampler!r}")
        if self.free_samples < 0 or not self.free_range_voxels >= 0:
            raise ConfigError("free_samples", "free_samples and free_range_voxels must be >= 0")
        if self.band_samples is not None and self.band_samples < 1:
            raise ConfigError("band_samples", f"must be >= 1 or None (the renderer's spacing), got {self.band_samples}")


@dataclass
class Keyframe:
    """A frame kept for joint optimisation.

    Its pose is ``T_base @ exp(delta)`` (right perturbation, :mod:`..lie`): ``T_base`` ``[4, 4]`` float64
    camera-to-world as tracked, ``delta`` a trainable 6-vector refined by joint mapping.

    Threads: ``delta`` is updated in place by the mapping thread's optimiser; other threads read
    :meth:`published_pose`, a copy the mapping thread swaps in whole with each published map
    (:func:`publish_keyframe_poses`), and ``T_base_host``, never the device tensors themselves (on a GPU a read
    from another thread's stream could see them before the mapping stream wrote them, and would wait for it).
    """

    data: FrameData
    T_base: torch.Tensor
    delta: torch.nn.Parameter
    T_base_host: np.ndarray
    """``T_base`` on the host (``[4, 4]`` float64), copied where the keyframe was made."""
    fixed: bool = False
    published: np.ndarray | None = None
    """``[4, 4]`` float64 pose as of the last published map (``None`` until then)."""
    pose_changed: bool = True
    """``delta`` moved since ``published`` was computed (set by :meth:`Mapper.step` for the keyframes it trains:
    its fused optimiser updates ``delta`` without bumping the tensor's version counter)."""

    @classmethod
    def create(cls, data: FrameData, T_world_cam: torch.Tensor, fixed: bool = False,
               T_host: np.ndarray | None = None) -> Keyframe:
        """A keyframe at ``T_world_cam [4, 4]`` (on the map's device); ``T_host``: the same pose already on the host
        (else it is copied from the device)."""
        delta = torch.nn.Parameter(torch.zeros(6, dtype=torch.float64, device=T_world_cam.device))
        T_base = T_world_cam.detach().to(torch.float64)
        host = np.array(T_host, dtype=np.float64) if T_host is not None else T_base.cpu().numpy()
        return cls(data, T_base, delta, host, fixed)

    def pose(self) -> torch.Tensor:
        """Current camera-to-world pose ``[4, 4]`` (differentiable in ``delta``)."""
        return perturb_right(self.T_base, self.delta)

    @property
    def T_world_cam(self) -> torch.Tensor:
        """Current pose, detached (the mapping thread's view; other threads use :meth:`published_pose`)."""
        return self.pose().detach()

    def published_pose(self) -> np.ndarray:
        """``[4, 4]`` float64 pose as of the last published map (the tracked pose before the first)."""
        published = self.published
        return published if published is not None else self.T_base_host


def publish_keyframe_poses(keyframes: list[Keyframe] | tuple[Keyframe, ...]) -> None:
    """Publish the current poses of the keyframes whose ``delta`` changed since they last published (or that
    never did), as one batched exponential. A mapping round moves only the keyframes of its windows, and the
    map publishes every keyframe's pose: one pose at a time cost ~0.1 ms each on a CPU (~1 ms per frame at ten
    keyframes, growing with the keyframes of a long run)."""
    moved = [kf for kf in keyframes if kf.published is None or kf.pose_changed]
    if not moved:
        return
    with torch.no_grad():
        poses = perturb_right(torch.stack([kf.T_base for kf in moved]),
                              torch.stack([kf.delta for kf in moved])).cpu().numpy()
    for kf, T in zip(moved, poses, strict=True):
        kf.published = T
        kf.pose_changed = False


@dataclass(frozen=True)
class MappingStep:
    """What one :meth:`Mapper.integrate` call did."""

    frame_index: int
    is_keyframe: bool
    new_voxels: int
    observed_voxels: int
    iterations: int
    loss: float
    time_ms: float
    inactive_voxels: int = 0
    """Voxels the evidence marks empty after this frame (kept allocated, read as empty)."""


def _backproject(frame: FrameData, T_world_cam: torch.Tensor, stride: int) -> torch.Tensor:
    """``[N, 3]`` world points of the frame's valid depth (every ``stride``-th pixel per axis)."""
    d = frame.depth_m[::stride, ::stride]
    v, u = torch.nonzero(d > 0, as_tuple=True)
    z = d[v, u].to(torch.float64)
    K = frame.K
    x = (u.to(torch.float64) * stride - K[0, 2]) / K[0, 0] * z
    y = (v.to(torch.float64) * stride - K[1, 2]) / K[1, 1] * z
    pts = torch.stack([x, y, z], -1)
    T = T_world_cam.detach().to(pts.device, torch.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


class _PoseRays(torch.autograd.Function):
    """World rays of camera-frame directions at a window's poses, with the pose gradient written out.

    ``forward(delta [W, 6], T [W, 4, 4], d_cam [W, n, 3])``: ``T = T_base exp(delta)`` float64, computed
    without a graph; ``d_cam`` float64 camera-frame directions -> ``origins [W n, 3]`` (each camera's centre)
    and ``dirs [W n, 3]`` (``R d_cam``), float32.

    Backward: the gradient with respect to a right perturbation ``eps = (rho, phi)`` of each pose, ``T exp(eps)``
    at ``eps = 0`` (``t + R rho``, ``R (d + phi x d)``): ``dL/drho = R^T sum_rays dL/do``, ``dL/dphi = sum_rays
    d_cam x (R^T dL/dd)``, passed on as the gradient of ``delta``. That takes the exponential's Jacobian at
    ``delta`` as the identity: exact at ``delta = 0``, off by a relative O(|delta|) otherwise. A keyframe's
    correction is small (median ~1e-3 m / rad, largest ~1e-2 over the first 200 7-Scenes frames), so the
    gradient is within ~0.1-1 % of autograd's; Adam's steps do not depend on the gradient's scale.
    Autograd through :func:`~.lie.perturb_right` (:meth:`Keyframe.pose`, the reference the tests compare
    with) takes ~100 small operations for a window, forward and backward: ~0.3 of ~8.7 ms of a CPU mapping
    iteration at 4 x 256 rays."""

    @staticmethod
    def forward(ctx, delta: torch.Tensor, T: torch.Tensor, d_cam: torch.Tensor  # noqa: ANN001
                ) -> tuple[torch.Tensor, torch.Tensor]:
        R = T[:, :3, :3]
        ctx.save_for_backward(R, d_cam)
        w, n, _ = d_cam.shape
        dirs = (d_cam @ R.transpose(1, 2)).reshape(-1, 3)
        origins = T[:, None, :3, 3].expand(w, n, 3).reshape(-1, 3)
        return origins.float(), dirs.float()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_origins: torch.Tensor, grad_dirs: torch.Tensor  # noqa: ANN001, ANN205
                 ) -> tuple[torch.Tensor, None, None]:
        R, d_cam = ctx.saved_tensors
        w, n, _ = d_cam.shape
        g_o = grad_origins.to(R.dtype).reshape(w, n, 3).sum(1, keepdim=True)  # [W, 1, 3]
        g_d_cam = grad_dirs.to(R.dtype).reshape(w, n, 3) @ R  # R^T dL/dd per ray, as rows
        g_rho = (g_o @ R).squeeze(1)
        g_phi = torch.cross(d_cam, g_d_cam, dim=-1).sum(1)
        return torch.cat([g_rho, g_phi], -1), None, None


def warm_up_pose_rates(optimizer: torch.optim.Adam, lr: float, warmup_steps: int) -> None:
    """Set the learning rate of each of ``optimizer``'s groups (one frame's pose correction each) that has a gradient
    this step: ``lr * k / warmup_steps`` for the group's k-th step, ``lr`` from ``warmup_steps`` on (``warmup_steps``
    0: ``lr`` always). The count lives in the group (``"pose_steps"``), beside the Adam state it tempers, so a new
    optimiser starts both afresh. Host bookkeeping only: nothing is read from the device."""
    for group in optimizer.param_groups:
        if all(p.grad is None for p in group["params"]):  # a frame outside this window
            continue
        k = group.get("pose_steps", 0) + 1
        group["pose_steps"] = k
        group["lr"] = lr * min(1.0, k / warmup_steps) if warmup_steps > 0 else lr


def window_rays(window: list[Keyframe], rays_per_frame: int, generator: torch.Generator | None = None,
                train_poses: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[torch.Tensor | None]]:
    """A mapping window's rays in one batch: ``rays_per_frame`` pixels per keyframe (:func:`sample_valid_pixels`, in
    window order) as world ``origins [W n, 3]`` and ``dirs [W n, 3]`` float32 (:func:`~.render.camera_rays`'
    convention), their observed depth ``[W n]`` and each keyframe's pixel colours ``[n, 3]`` (None without colour).

    Only the draws and the gathers from each keyframe's images are per keyframe; the pixels' camera directions
    (:func:`_window_directions`), the window's poses ``T_base exp(delta)`` (one batched ``[W, 4, 4]`` exponential)
    and the world rays are computed for the whole window at once (on a GPU every operator is a launch), differentiable
    in the deltas of the keyframes that are not fixed when ``train_poses``, with the pose gradient written out
    (:class:`_PoseRays`). Per keyframe, :func:`~.framedata.sample_pixels`, :meth:`Keyframe.pose` and
    :func:`~.render.camera_rays` give the same rays (to the bit) and, up to the first order in ``delta``, the same
    gradients (tested)."""
    flat = [sample_valid_pixels(kf.data, rays_per_frame, generator) for kf in window]
    depth = torch.cat([kf.data.depth_m.reshape(-1).index_select(0, f) for kf, f in zip(window, flat, strict=True)])
    colors = [None if kf.data.color is None else kf.data.color.reshape(-1, 3).index_select(0, f)
              for kf, f in zip(window, flat, strict=True)]
    delta = torch.stack([kf.delta if train_poses and not kf.fixed else kf.delta.detach() for kf in window])
    T = _window_poses(torch.stack([kf.T_base for kf in window]), delta.detach())  # [W, 4, 4] float64
    origins, dirs = _PoseRays.apply(delta, T, _window_directions(window, flat))
    return origins, dirs, depth, colors


def _window_poses(T_base: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """``T_base exp(delta)`` ``[W, 4, 4]`` float64 of a window's poses (``[W, 4, 4]``, ``[W, 6]``), no gradient: in
    numpy on a CPU (:func:`~.lie.se3_exp_np`: ~0.12 against ~0.35-0.48 ms for 4 poses through torch's ~40 small
    operators, the same numbers to float64 rounding), :func:`~.lie.perturb_right` elsewhere (nothing leaves a GPU)."""
    if T_base.device.type == "cpu" and delta.device.type == "cpu":
        return torch.from_numpy(T_base.to(torch.float64).numpy() @ se3_exp_np(delta.to(torch.float64).numpy()))
    with torch.no_grad():
        return perturb_right(T_base, delta)


def _window_directions(window: list[Keyframe], flat: list[torch.Tensor]) -> torch.Tensor:
    """``[W, n, 3]`` float64 camera-frame directions (:func:`~.render.camera_directions`' convention, the same
    numbers) of each keyframe's pixels ``flat [n]`` (``v * width + u``), one batch for the window when its frames
    share a width (one capture), else per keyframe."""
    widths = {kf.data.width for kf in window}
    if len(widths) != 1:
        return torch.stack([camera_directions(kf.data.K, flat_uv(f, kf.data.width))
                            for kf, f in zip(window, flat, strict=True)])
    (w,) = widths
    K = torch.stack([kf.data.K for kf in window]).to(torch.float64)  # [W, 3, 3]
    uv = flat_uv(torch.stack(flat), w)  # [W, n, 2]
    c = K[:, None, :2, 2]  # [W, 1, 2] principal point
    f = torch.diagonal(K, dim1=1, dim2=2)[:, None, :2]  # [W, 1, 2] focal lengths
    xy = (uv - c) / f
    return torch.cat([xy, torch.ones_like(xy[..., :1])], -1)


def band_loss(voxels: VoxelMap, decoder: SDFDecoder, origins: torch.Tensor, dirs: torch.Tensor, depth_gt: torch.Tensor,
              color_gt: torch.Tensor | None, color_valid: torch.Tensor | None, jitter: torch.Tensor,
              render: RenderConfig, loss: LossConfig, n_free: int, free_range_m: float, n_band: int,
              compact: bool | None = False, fused: bool = False
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One mapping iteration's forward pass with the ``band`` sampler: :func:`~.render.band_field_samples` (stratum
    positions ``jitter [N, S]``, drawn by the caller; ``compact`` as there), then the compositing and the loss terms,
    as the tuple ``(total, color, depth, free_space, sdf)`` (:class:`~.losses.LossTerms`' fields): with ``fused``
    in one autograd function with a written-out backward (:func:`~.losses.band_losses`, an eager mapper's), else
    :func:`~.render.composite` and :func:`~.losses.compute_losses` (the reference, and what ``mapping.compile``
    compiles: Inductor fuses those operators itself). Rays ``origins`` / ``dirs [N, 3]``, observed depth ``[N]``,
    colours ``[N, 3]`` or None. A free function of tensors and configuration with no random draw, and with
    ``compact`` False no read-back either, so that ``mapping.compile`` can compile it (:data:`COMPILED_BAND_LOSS`)."""
    s = band_field_samples(voxels, decoder, origins, dirs, depth_gt, render, n_free, free_range_m, training=True,
                           n_band=n_band, compact=compact, jitter=jitter)
    if fused:
        t = band_losses(s, depth_gt, color_gt, render, loss, color_valid)
    else:
        out = composite(s.sdf, s.rgb, s.t, s.mask, s.dir_norm, s.mask.any(1), render)
        t = compute_losses(out, depth_gt, color_gt, loss, color_valid)
    return t.total, t.color, t.depth, t.free_space, t.sdf


COMPILED_BAND_LOSS = CompiledFunction(band_loss, "mapping.compile", log)
""":func:`band_loss` compiled (``mapping.compile``), forward and backward; one for every mapper (shapes dynamic)."""


def _window_colors(colors: list[torch.Tensor | None], depths: list[torch.Tensor]
                   ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The window's ray colours ``[N, 3]`` and which rays have one (``[N]`` bool; ``None`` when all do).

    Captures that photograph only some frames (3D Scanner App: every third) put frames with and without
    colour in one window: their rays keep the colour term, the others carry zeros masked out of it.
    ``(None, None)`` when no frame of the window has colour."""
    if all(c is None for c in colors):
        return None, None
    if all(c is not None for c in colors):
        return torch.cat(colors), None  # type: ignore[arg-type]
    filled = [c if c is not None else d.new_zeros((d.shape[0], 3)) for c, d in zip(colors, depths, strict=True)]
    valid = [torch.full((d.shape[0],), c is not None, dtype=torch.bool, device=d.device)
             for c, d in zip(colors, depths, strict=True)]
    return torch.cat(filled), torch.cat(valid)


def keyframe_color_views(keyframes: list[Keyframe] | tuple[Keyframe, ...]) -> list[ColorView]:
    """The keyframes' colour images at their current poses, for mesh colours (none for depth-only maps)."""
    return [ColorView(kf.data.color, kf.data.depth_m, kf.data.K, torch.from_numpy(kf.published_pose().copy()))
            for kf in list(keyframes) if kf.data.color is not None]


FUSE_BATCH_MAX = 16
"""Frames :meth:`Mapper.integrate_batch` fuses in one pass at most (a mapper far behind fuses in several)."""


class Mapper:
    """Owns the map (voxels + decoder) and fuses posed frames into it.

    Args:
        voxel_size_m: voxel edge (paper: 0.2 m).
        field: decoder architecture; ``field.use_color=False`` for depth-only captures.
        render: renderer options; loss: loss weights; mapping: :class:`MappingConfig`.
        device: compute device; seed: seeds ray sampling, window choice and embedding initialisation.
    """

    def __init__(self, voxel_size_m: float, field: FieldConfig, render: RenderConfig, loss: LossConfig,
                 mapping: MappingConfig, device: torch.device | str = "cpu", seed: int = 0) -> None:
        self.device = torch.device(device)
        self.field_config = field
        self.render_config = render
        self.loss_config = loss
        self.config = mapping
        self.voxels = VoxelMap(voxel_size_m, field.embed_dim, self.device, seed=seed)
        with torch.random.fork_rng(devices=[]):  # seeded decoder weights without reseeding the process's RNG
            torch.manual_seed(seed)
            self.decoder = SDFDecoder(field)
        self.decoder = self.decoder.to(self.device)
        self.rebuild_optimizer()
        self.keyframes: list[Keyframe] = []
        # on the map's device, so ray and sample jitter never cross from the host (one stream per device
        # kind: a CUDA run draws other numbers than a CPU run with the same seed)
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self._rng = random.Random(seed)
        self._frames_since_keyframe = 0
        self._n_integrated = 0
        self.version = 0
        """Bumped after every optimisation round (cache key for meshes and renders)."""

    def rebuild_optimizer(self) -> None:
        """A fresh Adam over the current embeddings and decoder (after loading or moving the map)."""
        self.optimizer = adam([
            {"params": [self.voxels.embeddings], "lr": self.config.lr_embeddings},
            {"params": list(self.decoder.parameters()), "lr": self.config.lr_decoder},
        ], lr=self.config.lr_embeddings)
        self.pose_optimizer: torch.optim.Adam | None = None

    def _pose_optimizer(self, window: list[Keyframe]) -> torch.optim.Adam | None:
        """Adam over the pose corrections of the non-fixed frames in ``window``: one parameter group per frame, with
        that frame's Adam state and its own learning rate (:func:`warm_up_pose_rates`)."""
        if not self.config.optimize_poses:
            return None
        params = [kf.delta for kf in window if not kf.fixed]
        if not params:
            return None
        if self.pose_optimizer is None:
            self.pose_optimizer = adam([{"params": [p]} for p in params], lr=self.config.lr_pose)
        known = {id(p) for g in self.pose_optimizer.param_groups for p in g["params"]}
        for p in params:
            if id(p) not in known:
                self.pose_optimizer.add_param_group({"params": [p], "lr": self.config.lr_pose})
        return self.pose_optimizer

    def _forget_pose(self, kf: Keyframe) -> None:
        """Drop a non-keyframe's temporary pose correction from the pose optimiser."""
        opt = self.pose_optimizer
        if opt is None:
            return
        opt.param_groups = [g for g in opt.param_groups if not any(p is kf.delta for p in g["params"])]
        opt.state.pop(kf.delta, None)

    # ------------------------------------------------------------------ fusion
    def integrate(self, frame: FrameData, T_world_cam: torch.Tensor | np.ndarray,
                  optimize: bool = True) -> MappingStep:
        """Fuse one frame with its camera-to-world pose ``[4, 4]`` (OpenCV axes, metres).

        ``optimize=False`` only allocates voxels and applies the keyframe test (a realtime mapper that
        fell behind does this for the frames it skips, so no geometry or keyframe is lost).
        """
        return self.integrate_batch([(frame, T_world_cam)], optimize)[0]

    def integrate_batch(self, frames: list[tuple[FrameData, torch.Tensor | np.ndarray]],
                        optimize: bool = True) -> list[MappingStep]:
        """Fuse several frames in order, as :meth:`integrate` on each with ``optimize=False`` and then on the last
        with ``optimize``, with the map's bookkeeping done once for all of them: one allocation
        (:meth:`~.map.VoxelMap.allocate_counting_batch`), one surface-mark update and one evidence update
        (:func:`~..map.evidence.observe_frames`). A realtime mapper fuses the frames tracked since its last round so
        (on an H100 a frame fused alone cost ~11 ms of a ~240 ms round, 7 of them per round).

        Each frame's keyframe test sees the counts it would have seen in turn; what differs from fusing them one
        by one: the new voxels are numbered (and their vertices initialised) in one ascending Morton order, each
        frame's free-space rays also meet the voxels the batch's later frames allocated, and the active mask is
        updated once. The map's very first frame is fused (and optimised) on its own first; frames of different
        sizes (allocation strides) one by one. A step's ``time_ms`` is its share of the batch's fusion plus its
        own iterations.
        """
        if not frames:
            raise ValidationError("frames", "needs at least one (frame, T_world_cam) pair")
        if len(frames) > FUSE_BATCH_MAX:  # bounded memory: consecutive batches, the last one optimised
            head = [step for i in range(0, len(frames) - FUSE_BATCH_MAX, FUSE_BATCH_MAX)
                    for step in self.integrate_batch(frames[i:i + FUSE_BATCH_MAX], optimize=False)]
            return [*head, *self.integrate_batch(frames[len(head):], optimize)]
        strides = {self.config.stride_for(frame.width) for frame, _ in frames}
        if len(frames) > 1 and (not self.keyframes or len(strides) > 1):
            alone = 1 if len(strides) == 1 else len(frames) - 1  # the first frame, or all but the last
            return [*(step for i in range(alone) for step in self.integrate_batch([frames[i]], optimize=False)),
                    *self.integrate_batch(frames[alone:], optimize)]
        t0 = time.perf_counter()
        (stride,) = strides
        poses, points = [], []
        for frame, T_world_cam in frames:
            T = torch.as_tensor(np.asarray(T_world_cam) if not isinstance(T_world_cam, torch.Tensor)
                                else T_world_cam, dtype=torch.float64, device=self.device).detach()
            if frame.n_valid == 0:
                raise ValidationError("depth_m", f"frame {frame.index} has no valid depth; nothing to fuse")
            poses.append(T)
            points.append(_backproject(frame, T, stride))
        counts = self.voxels.allocate_counting_batch(points, self.optimizer)
        all_points = points[0] if len(points) == 1 else torch.cat(points)
        located = self.voxels.locate_surface_points(all_points)  # each point's voxel, looked up once
        self.voxels.add_surface_points(located)  # where the scene was seen: mesh support (mesh.support)
        if self.config.evidence.enabled:
            observe_frames(self.voxels, [(frame, T) for (frame, _), T in zip(frames, poses, strict=True)],
                           all_points, self.config.evidence, point_weight=float(stride ** 2),
                           point_voxels=located.voxel_idx)
        fuse_ms = (time.perf_counter() - t0) * 1e3 / len(frames)
        steps = []
        for i, ((frame, pose_in), T, (n_new, n_obs)) in enumerate(zip(frames, poses, counts, strict=True)):
            t1 = time.perf_counter()
            first = not self.keyframes
            is_kf = (first or self._frames_since_keyframe + 1 >= self.config.keyframe_max_interval
                     or n_new > self.config.keyframe_ratio * max(n_obs, 1))
            host = None if isinstance(pose_in, torch.Tensor) else np.asarray(pose_in)
            current = Keyframe.create(frame, T, fixed=first, T_host=host)
            if is_kf:
                self.keyframes.append(current)
                self._frames_since_keyframe = 0
            else:
                self._frames_since_keyframe += 1
            iters = 0
            loss = float("nan")
            if first:
                iters = self.config.first_frame_iters
            elif optimize and i == len(frames) - 1 and (is_kf or self._n_integrated % self.config.map_every == 0):
                iters = self.config.iters
            if iters:
                loss = self.optimize(iters, newest=current)
            if not is_kf:
                self._forget_pose(current)
            self._n_integrated += 1
            steps.append(MappingStep(frame.index, is_kf, n_new, n_obs, iters, loss,
                                     fuse_ms + (time.perf_counter() - t1) * 1e3,
                                     inactive_voxels=self.voxels.n_voxels - self.voxels.n_active))
        return steps

    def optimize(self, iters: int, newest: Keyframe | None = None) -> float:
        """Run ``iters`` joint iterations on windows of random keyframes (+ ``newest``); mean loss."""
        total = torch.zeros((), dtype=torch.float64, device=self.device)
        for _ in range(iters):
            window = self._window(newest)
            terms = self.step(window)
            total += terms.total.detach()  # stays on the device: one read-back per round, not per iteration
        self.version += 1
        return float(total) / max(iters, 1)

    def _window(self, newest: Keyframe | None) -> list[Keyframe]:
        pool = [kf for kf in self.keyframes if kf is not newest]
        k = min(self.config.window_keyframes, len(pool))
        window = self._rng.sample(pool, k) if k else []
        if newest is not None:
            window.append(newest)
        elif not window and self.keyframes:
            window = [self.keyframes[-1]]
        return window

    def step(self, window: list[Keyframe]) -> LossTerms:
        """One optimisation iteration over ``window`` (``rays_per_frame`` rays per frame)."""
        pose_opt = self._pose_optimizer(window)
        o, d, depth_gt, color = window_rays(window, self.config.rays_per_frame, self.generator,
                                            train_poses=pose_opt is not None)
        color_gt, color_valid = _window_colors(color, list(depth_gt.split(self.config.rays_per_frame)))
        color_gt = color_gt if self.field_config.use_color else None
        if self.config.sampler == "band":
            n_band, k = band_sample_count(self.render_config, self.voxels.voxel_size_m, self.config.free_samples,
                                          self.config.band_samples)
            jitter = band_jitter(o.shape[0], k, self.device, self.voxels.embeddings.dtype, self.generator)
            compiled = self.config.compile
            if compiled:
                self.voxels.index_grid()  # built (and cached) here: a graph cannot build it (it reads the map's extent)
            terms = LossTerms(*(COMPILED_BAND_LOSS if compiled else band_loss)(
                self.voxels, self.decoder, o, d, depth_gt, color_gt, color_valid, jitter, self.render_config,
                self.loss_config, self.config.free_samples, self.config.free_range_voxels * self.voxels.voxel_size_m,
                n_band, compact=False if compiled else self.config.compact_samples, fused=not compiled))
        else:
            t_far = depth_gt + self.render_config.truncation_m
            out = render_rays(self.voxels, self.decoder, o, d, self.render_config, training=True,
                              generator=self.generator, t_far=t_far)
            terms = compute_losses(out, depth_gt, color_gt, self.loss_config, color_valid)
        self.optimizer.zero_grad(set_to_none=True)
        if pose_opt is not None:
            pose_opt.zero_grad(set_to_none=True)
        terms.total.backward()
        adam_step(self.optimizer)
        if pose_opt is not None:
            warm_up_pose_rates(pose_opt, self.config.lr_pose, self.config.pose_warmup_steps)
            adam_step(pose_opt)
            for kf in window:
                kf.pose_changed = kf.pose_changed or not kf.fixed
        return terms

    def finish(self) -> float:
        """Final clean-up iterations over random keyframe windows (``final_iters``); mean loss."""
        if self.config.final_iters and self.keyframes:
            return self.optimize(self.config.final_iters)
        return float("nan")

    # ------------------------------------------------------------------ outputs
    def query(self, points_world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """Field at world points: ``(sdf_m [N], rgb [N, 3] or None, valid [N])`` (no gradient)."""
        with torch.no_grad():
            return query(self.voxels, self.decoder, points_world.to(self.device))


    def extract_mesh(self, mesh_res: int = 20, support: bool = True,  # noqa: ANN201 - trimesh.Trimesh
                     colors: str = "images"):
        """Triangle mesh of this mapper's map as it is now (:meth:`.slam.MapSnapshot.mesh`, the one mesh path)."""
        from .system import MapSnapshot

        return MapSnapshot.of(self).mesh(mesh_res, support, colors)


def make_mapper(config: VoxFusionConfig, has_color: bool = True, device: torch.device | str | None = None) -> Mapper:
    """The one way a :class:`Mapper` is built from a run's configuration (SLAM, known-pose mapping, checkpoint
    loading): on ``device`` (default: the configured one); the colour head is dropped for depth-only captures
    (``has_color=False``)."""
    from .presets import resolve_device

    field_cfg = config.field if has_color else dataclasses.replace(config.field, use_color=False)
    return Mapper(config.voxel_size_m, field_cfg, config.render, config.loss, config.mapping,
                  device=resolve_device(config.device) if device is None else device, seed=config.seed)
