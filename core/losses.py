"""Training losses (paper eq. 5-7): colour L1, depth L1, free-space and SDF terms.

Units and sets, per ray ``r`` with ground-truth depth ``D`` (t-units, camera z-depth) and per sample
``t`` with predicted SDF ``s`` (metres); ``|d|`` is the ray's metres per unit ``t``, ``tr`` the
truncation (:attr:`RenderOutput.truncation_m`):

* colour: mean absolute RGB error over hit rays (both in [0, 1]);
* depth: mean ``|depth - D|`` (metres of camera depth) over hit rays with valid ``D > 0``;
* free space (eq. 6): samples in front of the band, ``(D - t) |d| > tr``; target ``s = tr``;
* SDF (eq. 7): samples in the band, ``|D - t| |d| <= tr``; target ``s = (D - t) |d|``, the metric
  distance to the observed surface along the ray;

samples behind the band get no loss (the renderer masks them instead). Both SDF terms are squared errors
**in units of tr** (``((s - target) / tr)**2``, as Vox-Fusion's code, so the weights do not depend on the
chosen ``tr``), averaged over each ray's set, then over the rays whose set is not empty.

Default weights come from Vox-Fusion's Replica config (rgb 0.5, depth 1, sdf 5000, fs 10); its SDF terms
are means over *all* samples times ``1 - fraction``, i.e. ``f (1 - f) <= 1/4`` times ours for a
free-space fraction ``f``, so we take a quarter: sdf 1250, fs 2.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .errors import ConfigError, ShapeError
from .render.volume import RenderOutput

__all__ = ["LossConfig", "LossTerms", "compute_losses"]


@dataclass(frozen=True)
class LossConfig:
    """Weights of the four loss terms (0 disables a term)."""

    w_color: float = 0.5
    """Colour L1 (RGB in [0, 1])."""
    w_depth: float = 1.0
    """Depth L1, per metre."""
    w_fs: float = 2.5
    """Free-space term (squared error in units of tr)."""
    w_sdf: float = 1250.0
    """SDF term inside the truncation band (squared error in units of tr)."""

    def __post_init__(self) -> None:
        for name in ("w_color", "w_depth", "w_fs", "w_sdf"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0):
                raise ConfigError(name, f"must be a finite number >= 0, got {val}")


@dataclass
class LossTerms:
    """Weighted ``total`` and the unweighted terms, each a 0-dim tensor (0 when a term has no support)."""

    total: torch.Tensor
    color: torch.Tensor
    depth: torch.Tensor
    free_space: torch.Tensor
    sdf: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        """Detached Python floats, for logging."""
        return {k: float(getattr(self, k).detach()) for k in ("total", "color", "depth", "free_space", "sdf")}


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over ``mask`` (same shape), 0 where the mask is empty; whatever ``x`` holds outside the mask
    (non-finite values included) counts for nothing. Five operators, no read-back."""
    return torch.where(mask, x, 0.0).sum() / mask.sum().clamp(min=1)


def compute_losses(out: RenderOutput, depth_gt: torch.Tensor, color_gt: torch.Tensor | None,
                   config: LossConfig | None = None, color_valid: torch.Tensor | None = None) -> LossTerms:
    """Loss terms for rendered rays.

    Args:
        out: :func:`~.render.render_rays` output for ``N`` rays.
        depth_gt: ``[N]`` ground-truth depth in t-units (camera z-depth metres), 0 = invalid.
        color_gt: ``[N, 3]`` ground-truth RGB in [0, 1], or None (no colour term).
        config: weights.
        color_valid: ``[N]`` bool, rays whose ``color_gt`` is real (rays from frames without a colour image
            carry zeros there), or None: every ray's.

    Returns:
        :class:`LossTerms`; the colour term is 0 when ``color_gt`` or ``out.color`` is None.
    """
    config = config or LossConfig()
    n = out.depth.shape[0]
    if depth_gt.shape != (n,):
        raise ShapeError("depth_gt", tuple(depth_gt.shape), f"({n},)")
    depth_gt = depth_gt.to(out.depth.device, out.depth.dtype)
    zero = out.depth.new_zeros(())
    hit = out.hit
    valid_d = hit & (depth_gt > 0) & torch.isfinite(depth_gt)

    color = zero
    if color_gt is not None and out.color is not None:
        if color_gt.shape != (n, 3):
            raise ShapeError("color_gt", tuple(color_gt.shape), f"({n}, 3)")
        err = (out.color - color_gt.to(out.color.device, out.color.dtype)).abs().mean(-1)
        color = _masked_mean(err, hit if color_valid is None else hit & color_valid.to(hit.device))

    depth = _masked_mean((out.depth - torch.where(valid_d, depth_gt, out.depth.detach())).abs(), valid_d)

    tr = out.truncation_m
    d_gt = torch.where(valid_d, depth_gt, torch.zeros_like(depth_gt))
    dist = (d_gt[:, None] - out.t) * out.dir_norm[:, None]  # metres along the ray to the observed surface
    base = out.sample_mask & valid_d[:, None]
    fs_mask = base & (dist > tr)
    band = base & (dist.abs() <= tr)
    fs_err = ((out.sdf - tr) / tr) ** 2
    sdf_err = ((out.sdf - dist) / tr) ** 2

    def per_ray(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        cnt = mask.sum(1)
        ray_mean = (err * mask).sum(1) / cnt.clamp(min=1)
        return _masked_mean(ray_mean, cnt > 0)

    free_space = per_ray(fs_err, fs_mask)
    sdf = per_ray(sdf_err, band)
    total = (config.w_color * color + config.w_depth * depth + config.w_fs * free_space
             + config.w_sdf * sdf)
    return LossTerms(total=total, color=color, depth=depth, free_space=free_space, sdf=sdf)
