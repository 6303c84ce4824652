"""Geometric tracking: Levenberg-Marquardt on point-to-SDF residuals (``tracking.method: sdf``).

The paper tracks by volume rendering (:mod:`.tracking`'s ``render`` method: dozens of decoder calls per
ray, ~20-30 Adam steps). The map already holds a signed distance field, so a frame's back-projected depth
points, moved into the world with the right pose, must sit on its zero level set. This module drives
``sdf(T @ p_cam)`` to zero directly:

* residual ``r_i = sdf(R p_i + t)`` (metres) for ``N`` camera-frame points ``p_i`` sampled among the
  frame's valid pixels; optionally a photometric residual ``w_c * (gray(colour(x_i)) - gray_i)`` from the
  colour head at the same point; optionally (``w_frame``) a frame-to-frame point-to-plane residual
  ``w_f * n . (x_ref - v)`` against the previous accepted frame's depth (:class:`DepthReference`, projective
  nearest-pixel association, normal from central differences): the map's SDF is only as sharp as its voxels,
  the previous depth is sharp at any voxel size, and the map term keeps the sum from drifting; optionally
  (``w_photo``, finest level only) a photometric residual ``w_p * (I_ref(pi(x_ref)) - gray_i)`` against the
  previous frame's smoothed gray image (bilinear, :func:`photometric_residuals`): texture pins motion that
  geometry cannot see, such as sliding along a wall; optionally (``w_photo_blurred``) the same term against
  a Gaussian-blurred copy of that image in a stage of its own between the coarse levels and the finest
  (an image pyramid's coarse level: a wider basin for the sharp term to polish);
* Jacobian w.r.t. a right perturbation ``T exp(xi)``, ``xi = (rho, phi)`` (:mod:`..lie`): with
  ``g = d sdf / dx`` (autograd w.r.t. the points, one backward pass) and ``g_c = R^T g``,
  ``J_i = [g_c, p_i x g_c]`` (``d x / d rho = R``, ``d x / d phi = -R [p_i]_x``); every term has this form,
  with ``g`` its residual's gradient with respect to the world point (``R_ref^T n`` for the frame term);
* robust Huber weights (scale ``huber_m``); points outside allocated voxels, non-finite, or with
  ``|r|`` beyond ``max_residual_m`` (the SDF saturates at the truncation in free space, so its gradient
  carries no information there) get weight 0 and a constant cost, so leaving the map never pays;
* 6x6 normal equations ``(H + lambda diag(H)) delta = -b`` solved on the device; a step is kept only if it
  lowers the cost, else ``lambda`` grows and the step is retried from the best pose. Accept / reject is a
  ``torch.where`` on device tensors, so an iteration never waits for the host (apart from the optional
  convergence test below, the only read-back is one per frame, at the end);
* coarse to fine: ``levels`` rounds with 4x fewer points per coarser level (geometry only), then, with
  ``w_photo_blurred``, the finest points against the blurred image, then the finest level;
* a level ends after ``iters`` iterations, or earlier once the next proposed step would move less than
  ``converge_tol`` (metres and radians, largest component; that step is then not evaluated) at the finest
  level, ``coarse_converge_tol`` at the coarser ones (they only have to bring the pose into the finest
  level's reach; the finest level polishes it): the test is read back every ``check_every`` iterations, so
  on a GPU the loop waits for the device at most once per ``check_every`` steps (on a CPU a read-back costs
  nothing and 1 is right).

Everything is float32 on the map's device except poses and the normal equations (float64). The device
prior (ARKit motion) enters as a Gaussian on the accumulated correction ``xi`` (first order: the sum of
accepted steps), in the same information form as the data term.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch

from ..compiled import CompiledFunction
from ..errors import ShapeError, ValidationError
from ..framedata import FrameData, sample_valid_pixels
from ..geometry import invert_pose
from ..lie import perturb_right
from ..map import VoxelMap
from ..map.field import NeuralField, SDFDecoder, interpolate_unchecked, local_coords, sdf_with_gradient
from ..precompiled import PrecompiledFunction, PrecompiledVariants

log = logging.getLogger("voxfusion.tracking")

__all__ = ["SdfSolverConfig", "SdfPoints", "SdfSolution", "DepthReference", "GrayImages", "depth_reference",
           "with_older_frames", "frame_residuals", "frame_weights", "photometric_residuals", "gray_images",
           "smoothed_gray", "gaussian_blur", "separable_filter", "sample_points", "solve_pose", "linearize",
           "linearize_terms", "linearize_signature", "pose_terms", "PoseTerms", "map_costs", "solve_spd",
           "solve_spd_elimination"]

_GRAY = (0.299, 0.587, 0.114)
_GRAY_WEIGHTS: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}


def gray_levels(rgb: torch.Tensor) -> torch.Tensor:
    """Gray levels ``[...]`` of colours ``rgb [..., 3]`` in [0, 1] (ITU-R 601 luma weights). The weights are made once
    per dtype and device, so a call copies nothing from the host (which a CUDA graph capture forbids) once the
    first call on that device has run."""
    key = (rgb.dtype, rgb.device)
    w = _GRAY_WEIGHTS.get(key)
    if w is None:
        w = _GRAY_WEIGHTS.setdefault(key, torch.tensor(_GRAY, dtype=rgb.dtype, device=rgb.device))
    return rgb @ w


@dataclass(frozen=True)
class SdfSolverConfig:
    """Options of :func:`solve_pose` (see ``TrackingConfig`` for the user-facing names)."""

    iters: int = 6
    """Levenberg-Marquardt iterations per level at most (each one field evaluation + one backward pass)."""
    converge_tol: float = 0.0
    """The finest level ends once a proposed step's largest component is below this (m / rad); 0: always
    ``iters`` (and no read-back at any level)."""
    coarse_converge_tol: float | None = None
    """The same test at the coarser levels (None: ``converge_tol``)."""
    check_every: int = 1
    """Read the convergence test back every this many iterations (each read-back waits for the device)."""
    huber_m: float = 0.01
    """Huber scale of the SDF residual (metres); also the data term's noise scale for the device prior."""
    max_residual_m: float = 0.08
    """Points with |sdf| beyond this are outliers (weight 0, constant cost)."""
    inlier_m: float = 0.03
    """|sdf| below this counts as an inlier for the lost-frame statistics."""
    w_color: float = 0.0
    """Weight of the photometric residual (gray level in [0, 1]) relative to the SDF residual in metres."""
    huber_color: float = 0.1
    lambda_init: float = 1e-3
    prior_info: tuple[float, float] = (0.0, 0.0)
    """Information (1 / sigma^2, in the data term's units) of the device prior on translation (1/m^2) and
    rotation (1/rad^2); 0 = no prior."""
    w_frame: float = 0.0
    """Weight of the frame-to-frame point-to-plane residual against a :class:`DepthReference` (metres, like
    the SDF residual; 0: map only)."""
    frame_max_m: float = 0.05
    """Point pairs of the frame-to-frame term further apart than this (metres) are not associated."""
    w_photo: float = 0.0
    """Weight of the photometric frame-to-frame residual (gray levels in [0, 1], against the reference's
    smoothed gray image; needs a reference with ``gray`` and points with ``gray``), relative to the SDF
    residual in metres (0: none)."""
    huber_photo: float = 0.05
    """Huber scale of the photometric frame-to-frame residual (gray levels)."""
    w_photo_blurred: float = 0.0
    """Weight of the photometric term in a stage of its own before the finest level, on the finest level's
    points, against the reference's blurred gray image (``DepthReference.gray_blurred``; needs one); that
    stage ends at ``coarse_converge_tol``. 0: no such stage."""
    compile: bool = False
    """Run :func:`linearize_terms` through :func:`torch.compile` (:data:`COMPILED_LINEARIZE`; eager where that
    fails). The stages then share no field terms (:func:`solve_pose`)."""


@dataclass
class SdfPoints:
    """A frame's sampled points: ``p_cam [N, 3]`` float32 camera-frame metres, ``gray [N]`` in [0, 1] or
    None, and ``gray_blurred [N]`` (the frame's gray image blurred as the reference's ``gray_blurred`` is, at
    the same pixels) or None."""

    p_cam: torch.Tensor
    gray: torch.Tensor | None
    gray_blurred: torch.Tensor | None = None

    def prefix(self, n: int) -> SdfPoints:
        """The first ``n`` points (a coarser level's sample)."""
        return SdfPoints(self.p_cam[:n], None if self.gray is None else self.gray[:n],
                         None if self.gray_blurred is None else self.gray_blurred[:n])

    def blurred(self) -> SdfPoints:
        """These points with their blurred gray levels as their gray levels (what the blurred stage compares)."""
        return SdfPoints(self.p_cam, self.gray_blurred)


@dataclass
class SdfSolution:
    """Result of :func:`solve_pose`, all device tensors (read back once by the caller).

    ``T [4, 4]`` float64 best pose; ``cost`` 0-dim mean robust cost; ``inlier_fraction`` 0-dim share of the
    finest level's points with |sdf| < ``inlier_m``; ``median_residual_m`` 0-dim median |sdf| over the
    points inside the map (0 when none); ``n_valid`` 0-dim count of points inside the map and below
    ``max_residual_m``; ``iterations`` (a host int) the LM iterations run over all levels.
    """

    T: torch.Tensor
    cost: torch.Tensor
    inlier_fraction: torch.Tensor
    median_residual_m: torch.Tensor
    n_valid: torch.Tensor
    iterations: int


@dataclass
class DepthReference:
    """An earlier tracked frame's depth, for the frame-to-frame point-to-plane residual
    (:func:`frame_residuals`): ``depth_padded [H + 2 b, W + 2 b]`` float32 metres (0 = invalid, also in the
    ``b = baseline_px`` border), intrinsics ``K [3, 3]`` float32 of the ``[H, W]`` image and ``T_ref_world
    [4, 4]`` float64 (the inverse of its tracked pose). Made by :func:`depth_reference`; vertices and normals
    are computed only where points land, so keeping a reference costs one padded copy of the depth."""

    depth_padded: torch.Tensor
    K: torch.Tensor
    T_ref_world: torch.Tensor
    baseline_px: int
    offsets: torch.Tensor
    """``[5]`` int64 flat offsets in ``depth_padded`` of a pixel and its right, left, lower and upper neighbours
    ``baseline_px`` away (made once, on the depth's device)."""
    gray: torch.Tensor | None = None
    """``[H, W]`` float32 gray levels in [0, 1], smoothed (a 3x3 binomial filter), for the photometric
    frame-to-frame term (:func:`photometric_residuals`); None without colour or without that term."""
    gray_blurred: torch.Tensor | None = None
    """``[H, W]`` float32: ``gray`` blurred further by a Gaussian (:func:`gaussian_blur`), for the solver's
    blurred photometric stage (``SdfSolverConfig.w_photo_blurred``); None without that stage."""
    older_depth: torch.Tensor | None = None
    """``[R, H + 2 b, W + 2 b]`` float32: the padded depth of the R accepted frames before this one, newest first, for
    further point-to-plane references (:func:`with_older_frames`; slots not filled yet all zero); None: this frame
    is the only reference."""
    T_older_world: torch.Tensor | None = None
    """``[R, 4, 4]`` float64: the inverses of those frames' tracked poses (identity in empty slots)."""
    older_weights: torch.Tensor | None = None
    """``[R]`` float64: each older reference's weight relative to this frame's (0 in empty slots). A tensor, so that a
    weight that changes from frame to frame changes neither a compiled graph nor a recorded one."""

    def blurred(self) -> DepthReference:
        """This reference with the blurred image as its gray image (what the blurred stage aligns to)."""
        return replace(self, gray=self.gray_blurred)

    @property
    def height(self) -> int:
        return int(self.depth_padded.shape[0]) - 2 * self.baseline_px

    @property
    def width(self) -> int:
        return int(self.depth_padded.shape[1]) - 2 * self.baseline_px


def depth_reference(frame: FrameData, T_world_cam: np.ndarray, baseline_px: int = 2,
                    images: GrayImages | None = None) -> DepthReference:
    """``frame`` tracked at ``T_world_cam [4, 4]`` (a host array, as tracking returns poses) as a
    :class:`DepthReference`. Its normals will come from central differences ``baseline_px`` pixels either
    side: 2 tilts them less with sensor noise than direct neighbours (TUM fr1 desk, seed 2: ATE 0.32 cm with
    1, 0.22 with 2). ``images``: its gray images for the photometric terms (:func:`gray_images`, as the tracker
    made them for tracking this frame, with the blurred image when its blurred stage is on); None: none kept."""
    T_ref_world = torch.as_tensor(invert_pose(np.asarray(T_world_cam, dtype=np.float64)),
                                  device=frame.depth_m.device)
    b = baseline_px
    padded = torch.nn.functional.pad(frame.depth_m.to(torch.float32), (b, b, b, b))
    wp = padded.shape[1]
    offsets = torch.tensor([0, b, -b, b * wp, -b * wp], dtype=torch.int64, device=padded.device)
    gray, gray_blurred = (images.gray, images.blurred) if images is not None else (None, None)
    return DepthReference(padded, frame.K.to(torch.float32), T_ref_world, b, offsets, gray, gray_blurred)


def with_older_frames(ref: DepthReference, previous: DepthReference | None, count: int, weight: float
                      ) -> DepthReference:
    """``ref`` (the newest accepted frame) with up to ``count`` older frames as further point-to-plane references:
    ``previous`` (the reference this one replaces) first, then ``previous``'s own older frames, the oldest dropped,
    each at ``weight`` relative to ``ref``'s. Shapes are fixed from the first call on: slots not filled yet hold
    zero depth (no point associates there) and weight 0, so a recorded CUDA graph or a compiled evaluation made for
    one frame serves the next. ``previous`` of another image size (or None) starts the stack afresh.

    Why: the frame-to-frame terms' noise and pose errors are independent from reference to reference, so several
    average where one heavier reference drifts (``docs/engine-history.md``, 2026-12-07)."""
    r, hp, wp = count, *ref.depth_padded.shape
    dev = ref.depth_padded.device
    depth = torch.zeros((r, hp, wp), dtype=torch.float32, device=dev)
    T = torch.eye(4, dtype=torch.float64, device=dev).repeat(r, 1, 1)
    filled = torch.zeros(r, dtype=torch.bool, device=dev)
    if previous is not None and r > 0 and tuple(previous.depth_padded.shape) == (hp, wp):
        depth[0], T[0], filled[0] = previous.depth_padded, previous.T_ref_world, True
        older = previous.older_depth
        if r > 1 and older is not None and previous.older_weights is not None:
            m = min(r - 1, older.shape[0])
            depth[1:m + 1], T[1:m + 1] = older[:m], previous.T_older_world[:m]
            filled[1:m + 1] = previous.older_weights[:m] > 0
    weights = torch.where(filled, torch.full((r,), float(weight), dtype=torch.float64, device=dev),
                          torch.zeros(r, dtype=torch.float64, device=dev))
    return replace(ref, older_depth=depth, T_older_world=T, older_weights=weights)


@dataclass(frozen=True)
class GrayImages:
    """A frame's images for the photometric terms: ``gray [H, W]`` float32 (:func:`smoothed_gray`) and
    ``blurred [H, W]`` (``gray`` through :func:`gaussian_blur`; None without the blurred stage)."""

    gray: torch.Tensor
    blurred: torch.Tensor | None


def gray_images(color: torch.Tensor, blur_px: float = 0.0) -> GrayImages:
    """:class:`GrayImages` of ``color [H, W, 3]`` (RGB in [0, 1]); the blurred image only when ``blur_px`` > 0."""
    gray = smoothed_gray(color)
    return GrayImages(gray, gaussian_blur(gray, blur_px) if blur_px > 0 else None)


def smoothed_gray(color: torch.Tensor) -> torch.Tensor:
    """``[H, W]`` float32 gray levels of ``color [H, W, 3]`` (RGB in [0, 1]) smoothed by a 3x3 binomial filter
    (edges replicated): the reference image of the photometric term, so that image noise weighs less and the
    bilinear gradient reaches a little further. (Smoothing the tracked frame's side too measured no better:
    TUM fr1 desk 0.23 / 0.23 / 0.22 cm against 0.22 / 0.22 / 0.22.)"""
    g = gray_levels(color.to(torch.float32))
    return separable_filter(g, [0.25, 0.5, 0.25])


def gaussian_blur(image: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """``image [H, W]`` float32 blurred by a Gaussian of standard deviation ``sigma_px`` pixels (truncated at
    3 sigma, normalised, edges replicated); same shape."""
    r = max(1, int(3 * sigma_px + 0.5))
    taps = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_px) ** 2)
    return separable_filter(image, (taps / taps.sum()).tolist())


def separable_filter(image: torch.Tensor, taps: list[float]) -> torch.Tensor:
    """``image [H, W]`` float32 filtered by the 2-D kernel ``outer(taps, taps)`` (an odd number of taps, edges
    replicated); same shape. A weighted sum of shifted slices per axis: on a CPU ~3x faster than two
    ``conv2d`` passes with 1-D kernels, with equal results (640x480, 13 taps, 2-core AMD EPYC, 15 alternating
    pairs in one process: median 0.99 against 2.95 ms)."""
    r = len(taps) // 2
    h, w = image.shape
    p = torch.nn.functional.pad(image.to(torch.float32)[None, None], (r, r, r, r), mode="replicate")[0, 0]
    rows = p[:, 0:w] * taps[0]
    for i in range(1, len(taps)):
        rows = rows.add(p[:, i:i + w], alpha=taps[i])
    out = rows[0:h] * taps[0]
    for i in range(1, len(taps)):
        out = out.add(rows[i:i + h], alpha=taps[i])
    return out


def _project_into(ref: DepthReference, p_cam: torch.Tensor, T: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Camera-frame points ``p_cam [N, 3]`` at pose ``T [4, 4]`` in ``ref``'s camera: ``(x [N, 3], u [N],
    v [N])``, the points in its camera frame (metres) and their continuous pixel coordinates (depth clamped
    at 1e-6 m for the division; callers test ``x[:, 2]`` for points behind the camera)."""
    A = (ref.T_ref_world @ T).to(p_cam.dtype)
    x = p_cam @ A[:3, :3].T + A[:3, 3]
    z = x[:, 2].clamp(min=1e-6)
    return x, x[:, 0] / z * ref.K[0, 0] + ref.K[0, 2], x[:, 1] / z * ref.K[1, 1] + ref.K[1, 2]


def photometric_residuals(ref: DepthReference, p_cam: torch.Tensor, gray_cur: torch.Tensor, T: torch.Tensor,
                          max_dist_m: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Photometric residuals of camera-frame points ``p_cam [N, 3]`` with gray levels ``gray_cur [N]`` at pose
    ``T [4, 4]`` against ``ref.gray``: ``r = I_ref(u, v) - gray`` where ``(u, v)`` is the point's projection
    into the reference image (bilinear; the frame-to-frame analogue of direct image alignment).

    Returns ``(r [N], g_world [N, 3], ok [N])``: the residual in gray levels, its gradient with respect to the
    world point (the bilinear image gradient chained with the projection), and the usable points (projected at
    least one pixel inside the image, and not occluded there: the reference depth at the nearest pixel within
    ``max_dist_m`` of the point's). Fixed shapes, no host synchronisation."""
    assert ref.gray is not None
    x, u, v = _project_into(ref, p_cam, T)
    h, w, k = ref.height, ref.width, ref.baseline_px
    fx, fy = ref.K[0, 0], ref.K[1, 1]
    z = x[:, 2].clamp(min=1e-6)
    inb = (x[:, 2] > 1e-3) & (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
    u, v = u.clamp(1, w - 2), v.clamp(1, h - 2)
    u0, v0 = u.floor(), v.floor()
    au, av = u - u0, v - v0
    i00 = (v0 * w + u0).to(torch.int64)
    flat = ref.gray.reshape(-1)
    # (row, col) offsets: 01 right, 10 down; index_select: a 1-D gather, 2-3x faster on a CPU than indexing
    g00, g01, g10, g11 = (flat.index_select(0, i00 + o) for o in (0, 1, w, w + 1))
    top, bottom = g00 + au * (g01 - g00), g10 + au * (g11 - g10)
    val = top + av * (bottom - top)
    di_du = (1 - av) * (g01 - g00) + av * (g11 - g10)
    di_dv = bottom - top
    # occlusion: the reference's depth at the nearest pixel must agree with the point's
    near = ((torch.round(v) + k) * (w + 2 * k) + torch.round(u) + k).to(torch.int64)
    z_ref = ref.depth_padded.reshape(-1).index_select(0, near)
    visible = (z_ref > 0) & ((z_ref - x[:, 2]).abs() < max_dist_m)
    g_ref = torch.stack([di_du * fx / z, di_dv * fy / z, -(di_du * fx * x[:, 0] + di_dv * fy * x[:, 1]) / (z * z)], -1)
    r = val - gray_cur.to(val.dtype)
    g_world = g_ref @ ref.T_ref_world[:3, :3].to(g_ref.dtype)
    return r, g_world, inb & visible


def frame_residuals(ref: DepthReference, p_cam: torch.Tensor, T: torch.Tensor, max_dist_m: float,
                    max_step: float = 0.05) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Point-to-plane residuals of camera-frame points ``p_cam [N, 3]`` at pose ``T [4, 4]`` against ``ref``
    by projective association (the nearest reference pixel; the association is not differentiated).

    The reference surface at pixel ``(u, v)``: its back-projected vertex, and the normal of the cross product
    of central differences ``baseline_px`` pixels either side; defined only where those four neighbours have
    depth within ``max_step`` (relative) of the centre, so no normal spans a depth edge.

    Returns ``(r [N], g_world [N, 3], ok [N])``: ``r = n . (x_ref - v)`` in metres, its gradient with respect
    to the world point (``R_ref^T n``), and the associated pairs (in the image, a normal there, the pair
    closer than ``max_dist_m``). Fixed shapes, no host synchronisation. With ``ref``'s older frames
    (:func:`with_older_frames`, R of them) the same against each of them follows: ``[(1 + R) N]`` residuals and
    masks, ``[(1 + R) N, 3]`` gradients, ``ref`` first, then the older frames newest first (weights:
    :func:`frame_weights`)."""
    x, u, v = _project_into(ref, p_cam, T)
    r, n, ok = _point_to_plane(ref, ref.depth_padded.reshape(-1), x, u, v, x.new_zeros((), dtype=torch.int64),
                               max_dist_m, max_step)
    g_world = n @ ref.T_ref_world[:3, :3].to(n.dtype)
    if ref.older_depth is None or ref.T_older_world is None:
        return r, g_world, ok
    n_pts, n_older = p_cam.shape[0], ref.older_depth.shape[0]
    A = (ref.T_older_world @ T).to(p_cam.dtype)  # [R, 4, 4]
    xo = p_cam @ A[:, :3, :3].mT + A[:, None, :3, 3]  # [R, N, 3]
    zo = xo[..., 2].clamp(min=1e-6)
    uo, vo = xo[..., 0] / zo * ref.K[0, 0] + ref.K[0, 2], xo[..., 1] / zo * ref.K[1, 1] + ref.K[1, 2]
    plane = ref.depth_padded.numel()
    base = (torch.arange(n_older, device=p_cam.device, dtype=torch.int64) * plane).repeat_interleave(n_pts)
    ro, no, oko = _point_to_plane(ref, ref.older_depth.reshape(-1), xo.reshape(-1, 3), uo.reshape(-1),
                                  vo.reshape(-1), base, max_dist_m, max_step)
    go = (no.reshape(n_older, n_pts, 3) @ ref.T_older_world[:, :3, :3].to(no.dtype)).reshape(-1, 3)
    return torch.cat([r, ro]), torch.cat([g_world, go]), torch.cat([ok, oko])


def frame_weights(ref: DepthReference, n_points: int) -> torch.Tensor | None:
    """Per residual of :func:`frame_residuals` against ``ref`` with its older frames: ``[(1 + R) N]`` float64, 1 for
    ``ref``'s own, then each older frame's weight ``N`` times; None when ``ref`` has no older frames (every residual
    at weight 1)."""
    if ref.older_weights is None:
        return None
    ones = ref.older_weights.new_ones(1)
    return torch.cat([ones, ref.older_weights]).repeat_interleave(n_points)


def _point_to_plane(ref: DepthReference, depth_flat: torch.Tensor, x: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                    base: torch.Tensor, max_dist_m: float, max_step: float
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The association and residual of :func:`frame_residuals` for points ``x [M, 3]`` already in a reference
    camera's frame (metres) with their pixel coordinates ``u, v [M]``, against padded depth images of ``ref``'s
    size and intrinsics flattened into ``depth_flat``, each point's image starting at ``base`` (``[M]`` or 0-dim,
    flat offsets). Returns ``(r [M], n [M, 3], ok [M])``: the residual (metres), the reference's normal in its own
    camera frame, and the associated pairs."""
    h, w, k = ref.height, ref.width, ref.baseline_px
    fx, fy, cx, cy = ref.K[0, 0], ref.K[1, 1], ref.K[0, 2], ref.K[1, 2]
    u, v = torch.round(u), torch.round(v)
    inb = (x[:, 2] > 1e-3) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u, v = u.clamp(0, w - 1), v.clamp(0, h - 1)
    wp = w + 2 * k
    centre = ((v + k) * wp + (u + k)).to(torch.int64) + base
    taps = (centre[:, None] + ref.offsets).reshape(-1)
    z0, zr, zl, zd, zu = depth_flat.index_select(0, taps).reshape(centre.shape[0], -1).unbind(1)
    # the reference vertex at (u, v) and the central differences to its neighbours, back-projected:
    # X(u, v, d) = ((u - cx) d / fx, (v - cy) d / fy, d)
    a, c = (u - cx) / fx, (v - cy) / fy
    v0 = torch.stack([a * z0, c * z0, z0], -1)
    dzx, dzy = zr - zl, zd - zu
    dx = torch.stack([a * dzx + k / fx * (zr + zl), c * dzx, dzx], -1)
    dy = torch.stack([a * dzy, c * dzy + k / fy * (zd + zu), dzy], -1)
    n = torch.cross(dx, dy, dim=-1)
    norm = n.norm(dim=-1, keepdim=True)
    n = n / norm.clamp(min=1e-12)
    n = torch.where((n * v0).sum(-1, keepdim=True) > 0, -n, n)  # facing the camera
    nbrs = torch.stack([zr, zl, zd, zu], -1)
    smooth = (z0 > 0) & (norm[:, 0] > 0) & ((nbrs > 0) & ((nbrs - z0[:, None]).abs() <= max_step * z0[:, None])).all(-1)
    diff = x - v0
    r = (n * diff).sum(-1)
    ok = inb & smooth & (diff.norm(dim=-1) < max_dist_m)
    return r, n, ok


def sample_points(frame: FrameData, n: int, generator: torch.Generator | None = None,
                  with_gray: bool = False, blurred: torch.Tensor | None = None) -> SdfPoints:
    """Back-project ``n`` random valid pixels (with replacement; fixed count, so every step has static
    shapes) into camera-frame points ``[n, 3]`` (metres). ``with_gray``: their gray levels too (when the frame
    has colour); ``blurred``: the frame's blurred gray image ``[H, W]`` (:attr:`GrayImages.blurred`), whose
    values at the same pixels become the points' ``gray_blurred``."""
    flat = sample_valid_pixels(frame, n, generator)
    w = frame.width
    u = (flat % w).to(torch.float32)
    v = torch.div(flat, w, rounding_mode="floor").to(torch.float32)
    z = frame.depth_m.reshape(-1)[flat].to(torch.float32)
    K = frame.K.to(torch.float32)
    p = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    gray = None
    if with_gray and frame.color is not None:
        rgb = frame.color.reshape(-1, 3)[flat]
        gray = gray_levels(rgb)
    return SdfPoints(p, gray, None if blurred is None else blurred.reshape(-1)[flat])


def _huber_weight(r: torch.Tensor, k: float | torch.Tensor) -> torch.Tensor:
    a = r.abs()
    return torch.where(a <= k, torch.ones_like(a), k / a.clamp(min=1e-12))


def _huber_cost(r: torch.Tensor, k: float | torch.Tensor) -> torch.Tensor:
    a = r.abs()
    return torch.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k))


def _scaled_costs(res: torch.Tensor, valid: torch.Tensor, huber: torch.Tensor, cap: torch.Tensor, scale: float
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals ``res [M]`` in units of the SDF noise scale (times ``scale``, float64, 0 where not ``valid``) and
    their Huber costs (scale ``huber``, in the residuals' units before scaling); an invalid residual costs as much
    as one at its ``cap``, so leaving the map (or the reference) never pays. ``huber`` and ``cap``: ``[M]`` or
    0-dim float64. The one cost rule of :func:`linearize_terms` and :func:`map_costs`."""
    rs = torch.where(valid, res, torch.zeros_like(res)).to(torch.float64) * scale
    k = huber * scale
    return rs, torch.where(valid, _huber_cost(rs, k), _huber_cost(cap * scale, k))


def solve_spd(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve ``A x = b`` for a small symmetric positive definite ``A [n, n]`` (``b [n]``); zeros where ``A``
    is not positive definite (a degenerate system: no step).

    On a CPU: Cholesky (``cholesky_ex``, no error check) and ``cholesky_solve``, two operators (~11 us at
    6 x 6 on one core, against ~84 us for the elimination below, ~9 solves per tracked frame;
    ``cholesky_solve`` reads LAPACK's status back, one scalar read that costs nothing on a CPU). Elsewhere:
    :func:`solve_spd_elimination`, whose whole-matrix operations never wait for the device and can be
    captured in a CUDA graph. Both are tested against :func:`torch.linalg.solve`."""
    if A.device.type != "cpu":
        return solve_spd_elimination(A, b)
    L, info = torch.linalg.cholesky_ex(A)
    x = torch.cholesky_solve(b[:, None], L)[:, 0]
    return torch.where(info == 0, x, torch.zeros_like(x))


def solve_spd_elimination(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """:func:`solve_spd` by Gauss-Jordan elimination without pivoting (safe for SPD matrices): ``n`` rounds of
    whole-matrix tensor operations, so it never waits for the device (LAPACK-backed solvers read pivots or
    error codes back to the host on a GPU). A singular ``A`` gives non-finite entries (the caller zeroes them)."""
    n = A.shape[0]
    M = torch.cat([A, b[:, None]], 1)  # [n, n + 1] augmented
    rows = torch.arange(n, device=A.device)
    for k in range(n):
        pivot_row = M[k] / M[k, k]
        M = torch.where((rows == k)[:, None], pivot_row[None, :], M - M[:, k:k + 1] * pivot_row[None, :])
    return M[:, n]


class PoseTerms(NamedTuple):
    """What :func:`linearize_terms` computes at one pose that does not depend on the points' gray levels, so
    that two solver stages on the same points and the same reference geometry (the blurred photometric stage
    and the finest) share it at the pose where one ends and the next begins.

    ``r [N]`` SDF residuals (metres), ``grads [N, 3]`` their world gradients, ``ok [N]`` the points inside the
    map with a finite residual below ``max_residual_m`` and a finite gradient; with the colour term (else None)
    the colour head's gray level ``gray_pred [N]`` and its world gradient ``g_col [N, 3]``; with the
    frame-to-frame term (else None) its residuals ``rf [N]`` (metres), world gradients ``gf [N, 3]`` and usable
    pairs ``okf [N]``. What a stage keeps when no later stage reuses its terms is ``r`` and ``ok`` alone (the
    rest None)."""

    r: torch.Tensor
    grads: torch.Tensor | None
    ok: torch.Tensor
    gray_pred: torch.Tensor | None
    g_col: torch.Tensor | None
    rf: torch.Tensor | None
    gf: torch.Tensor | None
    okf: torch.Tensor | None

    def residuals(self) -> PoseTerms:
        """``r`` and ``ok`` alone, the rest None (what a stage whose terms nobody reuses keeps)."""
        return PoseTerms(self.r, None, self.ok, None, None, None, None, None)

    def where(self, cond: torch.Tensor, other: PoseTerms, residuals_only: bool = False) -> PoseTerms:
        """These terms where the 0-dim ``cond`` holds, else ``other``'s (on the device, no read-back);
        ``residuals_only``: ``r`` and ``ok`` alone, the rest None (what a stage whose terms nobody reuses keeps)."""
        if residuals_only:
            return PoseTerms(torch.where(cond, self.r, other.r), None, torch.where(cond, self.ok, other.ok),
                             None, None, None, None, None)
        return PoseTerms(*(a if a is None else torch.where(cond, a, b) for a, b in zip(self, other, strict=True)))


def pose_terms(voxels: VoxelMap, decoder: SDFDecoder, pts: SdfPoints, T: torch.Tensor, cfg: SdfSolverConfig,
               reference: DepthReference | None = None) -> PoseTerms:
    """The field's residuals at pose ``T [4, 4]`` (float64): the SDF and, with the colour term (``w_color``, points
    with gray levels, a colour head), the colour head's gray level, each with its world gradient; with
    ``reference`` and ``cfg.w_frame > 0``, the frame-to-frame term's (:class:`PoseTerms`). No host
    synchronisation."""
    dtype = voxels.embeddings.dtype
    p_cam = pts.p_cam.to(dtype)
    x = (p_cam @ T[:3, :3].to(dtype).T + T[:3, 3].to(dtype)).detach()
    idx = voxels.lookup_voxels(x)
    inside = idx >= 0
    idx = idx.clamp(min=0)
    gray_pred = g_col = None
    if _uses_color(decoder, pts, cfg):  # the colour head's gradient too: through autograd
        with torch.enable_grad():
            x.requires_grad_(True)
            loc = local_coords(voxels, x, idx)
            sdf, rgb = decoder(interpolate_unchecked(voxels, x, idx, loc), loc, with_color=True)
            grads = torch.autograd.grad(sdf.sum(), x, retain_graph=True)[0]
            gray = gray_levels(rgb)
            g_col = torch.autograd.grad(gray.sum(), x)[0]
        gray_pred = gray.detach()
    else:  # geometry only: the field's SDF and spatial gradient in one pass, no autograd graph
        sdf, grads = sdf_with_gradient(voxels, decoder, x, idx)
    r = sdf.detach()
    ok = inside & torch.isfinite(r) & (r.abs() < cfg.max_residual_m) & torch.isfinite(grads).all(-1)
    rf = gf = okf = None
    if reference is not None and cfg.w_frame > 0:
        rf, gf, okf = frame_residuals(reference, p_cam, T, cfg.frame_max_m)
    return PoseTerms(r, grads, ok, gray_pred, g_col, rf, gf, okf)


def _uses_color(decoder: SDFDecoder, pts: SdfPoints, cfg: SdfSolverConfig) -> bool:
    """Whether :func:`linearize` has the colour-head term (``w_color``, points with gray levels, a colour head)."""
    return cfg.w_color > 0 and pts.gray is not None and decoder.color_net is not None


def linearize_terms(voxels: VoxelMap, decoder: SDFDecoder, pts: SdfPoints, T: torch.Tensor, cfg: SdfSolverConfig,
                    reference: DepthReference | None = None, terms: PoseTerms | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, PoseTerms]:
    """:func:`linearize`, returning ``(cost, H, b, terms)``: ``terms`` (:class:`PoseTerms`) in place of its
    ``r`` and ``ok``. Given ``terms`` (computed by :func:`pose_terms` at this ``T`` for points at these
    positions, this reference's depth and these ``max_residual_m``, ``w_color``, ``w_frame`` and
    ``frame_max_m``), it skips the field query and the frame-to-frame term; only the terms that compare gray
    levels are evaluated. No host synchronisation."""
    if terms is None:
        terms = pose_terms(voxels, decoder, pts, T, cfg, reference)
    if terms.grads is None:
        raise ValidationError("terms", "holds residuals only (PoseTerms.where with residuals_only); pass full terms")
    dtype = voxels.embeddings.dtype
    R = T[:3, :3].to(dtype)
    p_cam = pts.p_cam.to(dtype)
    r, ok = terms.r, terms.ok
    # residual blocks (value, world gradient, Huber scale, cost cap, valid), all in metres: the SDF, then the
    # optional photometric and frame-to-frame terms, weighted; stacked so one pass builds H and b
    blocks: list[tuple[torch.Tensor, torch.Tensor, float | torch.Tensor, float | torch.Tensor, torch.Tensor]] = [
        (r, terms.grads, cfg.huber_m, cfg.max_residual_m, ok)]
    if terms.gray_pred is not None and terms.g_col is not None and pts.gray is not None:
        rc = (terms.gray_pred - pts.gray.to(dtype)) * cfg.w_color
        blocks.append((rc, terms.g_col * cfg.w_color, cfg.huber_color * cfg.w_color, cfg.max_residual_m,
                       ok & torch.isfinite(rc)))
    if terms.rf is not None and terms.gf is not None and terms.okf is not None:
        per_ref = None if reference is None else frame_weights(reference, r.shape[0])
        if per_ref is None:
            blocks.append((terms.rf * cfg.w_frame, terms.gf * cfg.w_frame, cfg.huber_m * cfg.w_frame,
                           cfg.frame_max_m * cfg.w_frame, terms.okf & torch.isfinite(terms.rf)))
        else:  # with older frames: a weight per residual (0 in empty slots: no pair, no cost)
            wf = per_ref * cfg.w_frame
            wr = wf.to(terms.rf.dtype)
            blocks.append((terms.rf * wr, terms.gf * wr[:, None], wf * cfg.huber_m, wf * cfg.frame_max_m,
                           terms.okf & (wf > 0) & torch.isfinite(terms.rf)))
    use_photo = reference is not None and reference.gray is not None and cfg.w_photo > 0 and pts.gray is not None
    if use_photo:
        rp, gp, okp = photometric_residuals(reference, p_cam, pts.gray, T, cfg.frame_max_m)
        w = cfg.w_photo
        blocks.append((rp * w, gp * w, cfg.huber_photo * w, 4 * cfg.huber_photo * w, okp & torch.isfinite(rp)))
    n = r.shape[0]
    res, g_world, valid = (torch.cat([blk[i] for blk in blocks]) for i in (0, 1, 4))
    m = res.shape[0] // n  # residuals per point (a block holds N, or N per reference)
    # per residual [m N]: a block's scale and cap are numbers (filled on the device: no host-to-device copy per
    # call) or already one per residual
    k, cap = (torch.cat([blk[i].to(torch.float64) if isinstance(blk[i], torch.Tensor)
                         else res.new_full((blk[0].shape[0],), blk[i], dtype=torch.float64) for blk in blocks])
              for i in (2, 3))
    p_all = p_cam.repeat(m, 1) if m > 1 else p_cam
    # everything in units of the SDF noise scale: residual / huber_m
    scale = 1.0 / cfg.huber_m
    g_cam = torch.where(valid[:, None], g_world @ R, torch.zeros_like(g_world))
    J = torch.cat([g_cam, torch.cross(p_all, g_cam, dim=-1)], -1).to(torch.float64) * scale  # [m N, 6]
    rs, cost = _scaled_costs(res, valid, k, cap, scale)
    wgt = _huber_weight(rs, k * scale) * valid
    Jw = J * wgt[:, None]
    return cost.sum() / n, Jw.T @ J / n, Jw.T @ rs / n, terms


def linearize(voxels: VoxelMap, decoder: SDFDecoder, pts: SdfPoints, T: torch.Tensor, cfg: SdfSolverConfig,
              reference: DepthReference | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                                torch.Tensor, torch.Tensor]:
    """Residuals and normal equations at pose ``T [4, 4]`` (float64), with the frame-to-frame term against
    ``reference`` when one is given and ``cfg.w_frame > 0``.

    Returns ``(cost, H [6, 6], b [6], r [N], ok [N])``: mean robust cost (in units of ``huber_m^2``),
    ``H = J^T W J`` and ``b = J^T W r`` in float64 (same units), the SDF residuals (metres) and the
    mask of points inside the map and below ``max_residual_m`` (the lost-frame statistics use the SDF term
    only). No host synchronisation.
    """
    cost, H, b, terms = linearize_terms(voxels, decoder, pts, T, cfg, reference)
    return cost, H, b, terms.r, terms.ok


def map_costs(voxels: VoxelMap, decoder: SDFDecoder, p_cam: torch.Tensor, T: torch.Tensor, cfg: SdfSolverConfig,
              max_points: int = 1 << 18) -> torch.Tensor:
    """The map term's cost of :func:`linearize` (``w_color`` aside) at many poses at once: camera-frame points
    ``p_cam [N, 3]`` at each of ``T [K, 4, 4]`` (float64 camera-to-world) -> ``[K]`` float64 mean robust cost in
    units of ``huber_m^2`` (a point outside the map, with a non-finite SDF or beyond ``max_residual_m`` costs as
    much as one at that cap). No gradient: the poses go through the field in chunks of ``max_points // N`` (one
    query per chunk instead of ~300 operators per pose, which on a GPU are launches), with no host
    synchronisation. :func:`linearize`'s cost, pose by pose, is the reference the tests hold it to; it also
    caps a point whose SDF gradient is not finite, which this cannot see (with a float32 decoder a finite SDF
    has a finite gradient). With ``field.compile`` the decoder's first call here (no gradient) compiles a graph
    of its own, once per process."""
    if T.dim() != 3 or T.shape[1:] != (4, 4):
        raise ShapeError("T", tuple(T.shape), "[K, 4, 4]")
    dtype = voxels.embeddings.dtype
    n = p_cam.shape[0]
    per_chunk = max(1, max_points // max(n, 1))
    field = NeuralField(voxels, decoder)
    p = p_cam.to(dtype)
    huber, cap = (torch.full((), v, dtype=torch.float64, device=p.device) for v in (cfg.huber_m, cfg.max_residual_m))
    costs = []
    with torch.no_grad():
        for start in range(0, T.shape[0], per_chunk):
            Tc = T[start:start + per_chunk]
            x = (p @ Tc[:, :3, :3].to(dtype).mT + Tc[:, None, :3, 3].to(dtype)).reshape(-1, 3)  # [k N, 3]
            idx = voxels.lookup_voxels(x)
            sdf, _ = field.evaluate_unchecked(x, idx.clamp(min=0), with_color=False)
            ok = (idx >= 0) & torch.isfinite(sdf) & (sdf.abs() < cfg.max_residual_m)
            cost = _scaled_costs(sdf, ok, huber, cap, 1.0 / cfg.huber_m)[1]
            costs.append(cost.reshape(-1, n).sum(1) / n)  # as linearize's sum / n, not mean's 1 / n factor
    return torch.cat(costs)


PRECOMPILED_LINEARIZE = PrecompiledFunction(linearize_terms, "tracking.precompiled", log)
""":func:`linearize_terms` from ahead-of-time compiled artifacts (``tracking.precompiled``; :mod:`.precompiled`), one
per :func:`linearize_signature`, each called without ``terms`` and checked against the plain function when compiled.
At 4096 points with every term on the 2-core AMD EPYC (one thread), 4.2-4.5 ms a call against 7.0-8.4 eager."""


def linearize_signature(voxels: VoxelMap, decoder: SDFDecoder, pts: SdfPoints, cfg: SdfSolverConfig,
                        reference: DepthReference | None) -> tuple:
    """What a compiled :func:`linearize_terms` (called without ``terms``) is specialised to besides tensor sizes: the
    options it reads, which optional inputs exist, the map's voxel size, dtype, device and lookup structure (a dense
    index grid or sorted codes), whether the points outnumber the map's voxels (a branch of the field's gradient)
    and the decoder's architecture. Equal signatures can share an artifact; anything
    missed here is caught by the artifact's own guards (the call then runs eagerly)."""
    options = (cfg.huber_m, cfg.max_residual_m, cfg.w_color, cfg.huber_color, cfg.w_frame, cfg.frame_max_m,
               cfg.w_photo, cfg.huber_photo)
    ref = None if reference is None else (reference.baseline_px, reference.gray is None,
                                          reference.gray_blurred is None,
                                          None if reference.older_depth is None else reference.older_depth.shape[0])
    # the corner-weight gradient gathers per voxel or per point, whichever are fewer (field._corner_weight_grad)
    points_outnumber_voxels = pts.p_cam.shape[0] > voxels.voxel_vertex_ids.shape[0]
    return ("linearize_terms", options, pts.gray is None, pts.gray_blurred is None, ref, voxels.voxel_size_m,
            str(voxels.embeddings.dtype), voxels.device.type, voxels.index_grid() is None, points_outnumber_voxels,
            repr(decoder.config), decoder.has_plain_gradient, decoder.color_net is None)


COMPILED_LINEARIZE = CompiledFunction(linearize_terms, "tracking.compile", log)
""":func:`linearize_terms` compiled (``tracking.compile``; always called without ``terms``: with it the solver's
stages share no terms, so that every evaluation runs the compiled graph): one graph per solver stage, shapes
dynamic (the map grows between frames); tested against :func:`linearize_terms` itself. A call at 4096
points with every term took 3.2 ms against 6.8 eager on the 2-core AMD EPYC (one thread)."""


def _stages(levels: list[SdfPoints], cfg: SdfSolverConfig, reference: DepthReference | None
            ) -> list[tuple[SdfPoints, SdfSolverConfig, DepthReference | None]]:
    """The solver's stages, coarse first: ``(points, options, reference)``. The coarser levels are geometry
    only (the photometric term's basin is a pixel or two wide: at every level it pulled fast rotations into
    wrong minima); with ``w_photo_blurred`` and blurred images on both sides, a stage comparing the finest
    points' blurred gray levels with the reference's blurred image (a basin as wide as the blur) comes next;
    the finest level, with every term, polishes. Both sides are blurred alike, so the blurred stage's minimum
    is the sharp one's (blurring the reference alone moved it by ~2 mm on a test wall)."""
    geometric = replace(cfg, w_photo=0.0, w_photo_blurred=0.0)
    stages = [(pts, geometric, reference) for pts in levels[:-1]]
    finest = levels[-1]
    if (cfg.w_photo_blurred > 0 and reference is not None and reference.gray_blurred is not None
            and finest.gray_blurred is not None):
        stages.append((finest.blurred(), replace(cfg, w_photo=cfg.w_photo_blurred, w_photo_blurred=0.0),
                       reference.blurred()))
    stages.append((finest, replace(cfg, w_photo_blurred=0.0), reference))
    return stages


_REFERENCE_GEOMETRY = ("depth_padded", "K", "T_ref_world", "offsets", "older_depth", "T_older_world",
                       "older_weights")
"""The :class:`DepthReference` fields the point-to-plane term reads (its gray images aside)."""


def _shares_pose_terms(a: tuple[SdfPoints, SdfSolverConfig, DepthReference | None],
                       b: tuple[SdfPoints, SdfSolverConfig, DepthReference | None]) -> bool:
    """Whether two solver stages ``(points, options, reference)`` have the same :class:`PoseTerms` at a pose:
    the same point positions (the same tensor), both with or without gray levels, the same reference geometry
    (its depth, intrinsics, pose and offsets the same tensors, or no reference; its gray images may differ) and
    the options those terms depend on."""
    (pa, ca, ra), (pb, cb, rb) = a, b
    same_ref = (ra is None and rb is None) or (
        ra is not None and rb is not None and ra.baseline_px == rb.baseline_px
        and all(getattr(ra, f) is getattr(rb, f) for f in _REFERENCE_GEOMETRY))
    return (pa.p_cam is pb.p_cam and (pa.gray is None) == (pb.gray is None) and same_ref
            and (ca.max_residual_m, ca.w_color, ca.w_frame, ca.frame_max_m)
            == (cb.max_residual_m, cb.w_color, cb.w_frame, cb.frame_max_m))


class SolverStage(NamedTuple):
    """One stage of :func:`solve_pose` (:func:`solver_stages`): its ``points``, ``options`` and ``reference``, the
    convergence tolerance ``tol`` of its steps (m / rad), whether it starts from the previous stage's terms
    (``shares``: :func:`_shares_pose_terms`; never when compiled, so that every evaluation runs the compiled graph)
    and whether it keeps every term of its best pose for the next stage (``keeps``), else ``r`` and ``ok`` alone."""

    points: SdfPoints
    options: SdfSolverConfig
    reference: DepthReference | None
    tol: float
    shares: bool
    keeps: bool


def solver_stages(levels: list[SdfPoints], cfg: SdfSolverConfig, reference: DepthReference | None
                  ) -> list[SolverStage]:
    """:func:`_stages` with each stage's tolerance and how it hands its terms on (:class:`SolverStage`)."""
    stages = _stages(levels, cfg, reference)
    shares = [not cfg.compile and k > 0 and _shares_pose_terms(stages[k - 1], stages[k]) for k in range(len(stages))]
    out = []
    for k, (pts, lcfg, lref) in enumerate(stages):
        finest = k == len(stages) - 1
        tol = cfg.converge_tol if finest or cfg.coarse_converge_tol is None else cfg.coarse_converge_tol
        out.append(SolverStage(pts, lcfg, lref, tol, shares[k], k + 1 < len(stages) and shares[k + 1]))
    return out


class SolverPrior(NamedTuple):
    """The device prior as the solver adds it (:func:`_evaluate`): ``info [6]`` float64 (``prior_info`` per axis),
    divided by ``n_points`` (the largest level's point count: the prior's weight is per point of the data term's
    mean, so it does not depend on N); ``eye [6, 6]`` float64, the damping's regulariser."""

    info: torch.Tensor
    n_points: int
    eye: torch.Tensor


def solver_prior(cfg: SdfSolverConfig, levels: list[SdfPoints], device: torch.device) -> SolverPrior:
    """:class:`SolverPrior` of ``cfg.prior_info`` for these levels, on ``device``."""
    info = torch.tensor([cfg.prior_info[0]] * 3 + [cfg.prior_info[1]] * 3, dtype=torch.float64, device=device)
    return SolverPrior(info, max(p.p_cam.shape[0] for p in levels), torch.eye(6, dtype=torch.float64, device=device))


class LMState(NamedTuple):
    """A solver stage's Levenberg-Marquardt state, all device tensors: the best pose ``T [4, 4]`` float64 so far and
    the accumulated correction ``xi [6]`` (the device prior's argument: the sum of accepted steps), that pose's cost
    (0-dim), normal equations ``H [6, 6]``, ``b [6]`` (float64, the prior included) and terms, the damping ``lam``
    (0-dim) and the step ``delta [6]`` proposed from them: what the next iteration evaluates, and what the
    convergence test reads. :func:`stage_start` makes one, :func:`stage_step` advances it."""

    T: torch.Tensor
    xi: torch.Tensor
    cost: torch.Tensor
    H: torch.Tensor
    b: torch.Tensor
    lam: torch.Tensor
    delta: torch.Tensor
    terms: PoseTerms


def _propose(H: torch.Tensor, b: torch.Tensor, lam: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """The damped step ``-(H + lam (diag(H) + 1e-9 I))^-1 b`` ``[6]`` (0 where that is not finite)."""
    A = H + lam * (torch.diag(torch.diagonal(H)) + 1e-9 * eye)
    return torch.nan_to_num(solve_spd(A, -b), nan=0.0, posinf=0.0, neginf=0.0)


def _evaluate(voxels: VoxelMap, decoder: SDFDecoder, stage: SolverStage, prior: SolverPrior, T: torch.Tensor,
              xi: torch.Tensor, terms: PoseTerms | None = None, variants: PrecompiledVariants | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, PoseTerms]:
    """The stage's cost and normal equations at ``T`` (:func:`linearize_terms`, compiled with ``compile``, else from
    ``variants`` of :data:`PRECOMPILED_LINEARIZE` where given) plus the device prior at ``xi``; ``terms``: the stage's
    terms at ``T`` already known (the previous stage's)."""
    cfg = stage.options
    if terms is None:
        args = (voxels, decoder, stage.points, T, cfg, stage.reference)
        if cfg.compile:
            cost, H, b, terms = COMPILED_LINEARIZE(*args)
        elif variants is not None:
            signature = linearize_signature(voxels, decoder, stage.points, cfg, stage.reference)
            cost, H, b, terms = variants(signature, *args)
        else:
            cost, H, b, terms = linearize_terms(*args)
    else:
        cost, H, b, terms = linearize_terms(voxels, decoder, stage.points, T, cfg, stage.reference, terms)
    H = H + torch.diag(prior.info) / prior.n_points
    b = b + prior.info * xi / prior.n_points
    cost = cost + 0.5 * (prior.info * xi * xi).sum() / prior.n_points
    return cost, H, b, terms


def stage_start(voxels: VoxelMap, decoder: SDFDecoder, stage: SolverStage, prior: SolverPrior, T: torch.Tensor,
                xi: torch.Tensor, carried: PoseTerms | None = None,
                variants: PrecompiledVariants | None = None) -> LMState:
    """A stage's :class:`LMState` at pose ``T [4, 4]`` (float64) with correction ``xi [6]``: one evaluation (none of
    the field when the stage ``shares`` and ``carried`` holds the previous stage's terms there) and the first step.
    Fresh tensors throughout (``T`` and ``xi`` are copied). No host synchronisation."""
    cost, H, b, terms = _evaluate(voxels, decoder, stage, prior, T, xi, carried if stage.shares else None, variants)
    if not stage.keeps:
        terms = terms.residuals()
    lam = torch.full((), stage.options.lambda_init, dtype=torch.float64, device=cost.device)
    return LMState(T.clone(), xi.clone(), cost, H, b, lam, _propose(H, b, lam, prior.eye), terms)


def stage_step(voxels: VoxelMap, decoder: SDFDecoder, stage: SolverStage, prior: SolverPrior, state: LMState,
               variants: PrecompiledVariants | None = None) -> LMState:
    """One Levenberg-Marquardt iteration: evaluate ``state.delta``; keep it where it lowers the cost (and lower
    the damping), else keep the state (and raise it); propose the next step. A new :class:`LMState` of the same
    structure; no host synchronisation."""
    T_c = perturb_right(state.T, state.delta)
    xi_c = state.xi + state.delta
    cost_c, H_c, b_c, terms_c = _evaluate(voxels, decoder, stage, prior, T_c, xi_c, variants=variants)
    better = cost_c < state.cost
    H = torch.where(better, H_c, state.H)
    b = torch.where(better, b_c, state.b)
    lam = torch.where(better, (state.lam * 0.3).clamp(min=1e-7), state.lam * 5.0)
    return LMState(torch.where(better, T_c, state.T), torch.where(better, xi_c, state.xi),
                   torch.where(better, cost_c, state.cost), H, b, lam, _propose(H, b, lam, prior.eye),
                   terms_c.where(better, state.terms, residuals_only=not stage.keeps))


def iterate_stage(state: LMState, stage: SolverStage, step: Callable[[LMState], LMState]) -> tuple[LMState, int]:
    """Run ``step`` (:func:`stage_step`, or its replay) up to ``iters`` times from ``state``, ending earlier once the
    proposed step is below the stage's tolerance (read back every ``check_every`` iterations). Returns the final
    state and the iterations run."""
    cfg = stage.options
    n = 0
    for it in range(1, cfg.iters + 1):
        # converged: the next step would move the pose less than the tolerance (not worth an evaluation)
        if cfg.converge_tol > 0 and (it - 1) % cfg.check_every == 0 and float(state.delta.abs().max()) < stage.tol:
            break
        state = step(state)
        n += 1
    return state, n


def solution(state: LMState, cfg: SdfSolverConfig, iterations: int) -> SdfSolution:
    """The :class:`SdfSolution` of the last stage's final ``state`` (its residual statistics; fresh tensors)."""
    r, ok = state.terms.r, state.terms.ok
    a = r.abs()
    inlier = (ok & (a < cfg.inlier_m)).to(torch.float64).mean()
    inside_abs = torch.where(ok, a, torch.full_like(a, float("inf")))
    n_valid = ok.sum()
    mid = ((n_valid - 1).clamp(min=0) // 2).reshape(1)
    med = torch.where(n_valid > 0, inside_abs.sort().values.gather(0, mid)[0], a.new_zeros(()))
    return SdfSolution(state.T.clone(), state.cost.clone(), inlier, med, n_valid, iterations)


def solve_pose(voxels: VoxelMap, decoder: SDFDecoder, levels: list[SdfPoints], T_init: torch.Tensor,
               cfg: SdfSolverConfig, reference: DepthReference | None = None,
               variants: PrecompiledVariants | None = None) -> SdfSolution:
    """Levenberg-Marquardt from ``T_init [4, 4]`` float64 over ``levels`` (coarse first; the stages of
    :func:`solver_stages`), eager (each field evaluation from ``variants``' artifacts where given and available).
    Without a ``converge_tol`` it never waits for the device; with one, once every ``check_every`` iterations.
    :class:`~.tracking_graphs.SolverGraphs` replays the same stages from CUDA graphs."""
    prior = solver_prior(cfg, levels, T_init.device)
    T = T_init.to(torch.float64)
    xi = torch.zeros(6, dtype=torch.float64, device=T.device)
    state: LMState | None = None
    iterations = 0
    for stage in solver_stages(levels, cfg, reference):
        # where the previous stage ended, its field and frame-to-frame terms are this one's (only gray levels differ)
        state = stage_start(voxels, decoder, stage, prior, T, xi, None if state is None else state.terms, variants)
        state, n = iterate_stage(state, stage, lambda s, st=stage: stage_step(voxels, decoder, st, prior, s, variants))
        T, xi = state.T, state.xi
        iterations += n
    assert state is not None
    return solution(state, cfg, iterations)
