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

from . import native
from .errors import ConfigError, ShapeError
from .render.volume import BandSamples, RenderConfig, RenderOutput, first_surface

__all__ = ["LossConfig", "LossTerms", "compute_losses", "band_losses"]


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


def _per_ray_mean(err: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean of ``err [N, S]`` over each ray's ``mask``, then over the rays whose mask is not empty (0 without any),
    and the derivative of that mean with respect to each of a ray's masked errors, ``[N]``."""
    cnt = mask.sum(1)
    ray_mean = (err * mask).sum(1) / cnt.clamp(min=1)
    has = cnt > 0
    n_rays = has.sum().clamp(min=1)
    return _masked_mean(ray_mean, has), 1.0 / (cnt.clamp(min=1) * n_rays)


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

    free_space = _per_ray_mean(fs_err, fs_mask)[0]
    sdf = _per_ray_mean(sdf_err, band)[0]
    total = (config.w_color * color + config.w_depth * depth + config.w_fs * free_space
             + config.w_sdf * sdf)
    return LossTerms(total=total, color=color, depth=depth, free_space=free_space, sdf=sdf)



def band_losses(samples: BandSamples, depth_gt: torch.Tensor, color_gt: torch.Tensor | None, render: RenderConfig,
                config: LossConfig | None = None, color_valid: torch.Tensor | None = None) -> LossTerms:
    """:func:`compute_losses` of :func:`~.render.composite` of a mapping iteration's samples (the band sampler's,
    :func:`~.render.band_field_samples`) in one autograd function, with the backward pass written out.

    The same terms as ``compute_losses(composite(sdf, rgb, t, mask, dir_norm, mask.any(1), render), depth_gt,
    color_gt, config, color_valid)`` (the reference the tests hold it to: the values to the bit, the gradients with
    respect to ``sdf`` and ``rgb`` to float32 rounding). On ``[N, S]`` tensors of a few thousand samples an operator
    costs its fixed overhead more than its arithmetic: autograd records ~90 operators there and runs ~60 backward
    nodes; this runs the forward without recording and the backward as ~35 operators. Gradients flow to
    ``samples.sdf`` and ``samples.rgb`` only (``t`` and ``dir_norm`` carry none, as in the renderer). Arguments as
    :func:`compute_losses`; no host synchronisation."""
    config = config or LossConfig()
    n = samples.t.shape[0]
    if depth_gt.shape != (n,):
        raise ShapeError("depth_gt", tuple(depth_gt.shape), f"({n},)")
    use_color = color_gt is not None and samples.rgb is not None
    if use_color and color_gt.shape != (n, 3):
        raise ShapeError("color_gt", tuple(color_gt.shape), f"({n}, 3)")
    dev, dtype = samples.t.device, samples.sdf.dtype
    function = _BandLossesKernel if _kernel_applies(samples) else _BandLosses
    terms = function.apply(
        samples.sdf, samples.rgb if use_color else None, samples.t, samples.mask, samples.dir_norm,
        depth_gt.to(dev, dtype), color_gt.to(dev, dtype) if use_color else None,
        color_valid.to(dev) if use_color and color_valid is not None else None, render, config)
    return LossTerms(*terms)


def _kernel_applies(samples: BandSamples) -> bool:
    """Whether the compiled kernel (:class:`_BandLossesKernel`) serves: float32 samples on a CPU, at most
    ``MAX_SAMPLES`` per ray, eager (not inside a graph ``torch.compile`` traces), and the kernel built."""
    t = samples.t
    return (t.device.type == "cpu" and t.dtype == torch.float32 and samples.sdf.dtype == torch.float32
            and (samples.rgb is None or samples.rgb.dtype == torch.float32) and t.shape[1] <= _KERNEL_MAX_SAMPLES
            and not torch.compiler.is_compiling() and native.band_loss_kernels() is not None)


_KERNEL_MAX_SAMPLES = 64
"""Samples per ray the kernel handles (``MAX_SAMPLES`` in ``band_losses.c``); more run as PyTorch operators."""


def _ptr(x: torch.Tensor | None) -> int:
    return 0 if x is None else x.data_ptr()


def _as_bytes(mask: torch.Tensor) -> torch.Tensor:
    """A boolean mask as the contiguous ``uint8`` array the kernel reads (any mask dtype: nonzero is True)."""
    return mask.to(torch.bool).contiguous().view(torch.uint8)


class _BandLossesKernel(torch.autograd.Function):
    """:class:`_BandLosses` on a CPU as one compiled loop over the rays per direction (``core/native/band_losses.c``,
    loaded by :mod:`.native`): the same arguments, terms and gradients (to float32 rounding: the sums over rays are
    accumulated in double there). The backward pass composites each ray again rather than keeping ``[N, S]``
    intermediates. On the 2-core AMD EPYC, at 1024 rays of 7 samples, forward and backward (``.backward()`` of the
    total, from Python) took 0.81-0.93 ms against 2.25-2.92 ms for :class:`_BandLosses` and 2.90-2.95 ms for
    composite + compute_losses through autograd (medians of 7 rounds of 100 calls, in turn in one process)."""

    @staticmethod
    def forward(ctx, sdf: torch.Tensor, rgb: torch.Tensor | None, t: torch.Tensor,  # noqa: ANN001, ANN205
                mask: torch.Tensor, dn: torch.Tensor, depth_gt: torch.Tensor, color_gt: torch.Tensor | None,
                color_valid: torch.Tensor | None, render: RenderConfig, config: LossConfig):
        n, s = t.shape
        inputs = [sdf.detach().contiguous(), None if rgb is None else rgb.detach().contiguous(), t.contiguous(),
                  _as_bytes(mask), dn.to(torch.float32).contiguous(), depth_gt.contiguous(),
                  None if color_gt is None else color_gt.contiguous(),
                  None if color_valid is None else _as_bytes(color_valid)]
        weights = torch.tensor([config.w_color, config.w_depth, config.w_fs, config.w_sdf], dtype=torch.float64)
        terms = torch.empty(5, dtype=torch.float64)
        counts = torch.empty(4, dtype=torch.float64)
        status = native.band_loss_kernels().band_losses_forward(
            *(_ptr(x) for x in inputs), n, s, render.truncation_m, render.weight_scale_m, weights.data_ptr(),
            terms.data_ptr(), counts.data_ptr())
        if status != 0:
            raise RuntimeError(f"band_losses.c refused {s} samples per ray")
        ctx.inputs, ctx.counts, ctx.weights, ctx.render = inputs, counts, weights, render
        return tuple(terms.to(sdf.dtype).unbind(0))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_total: torch.Tensor, g_color: torch.Tensor, g_depth: torch.Tensor,  # noqa: ANN001, ANN205
                 g_free: torch.Tensor, g_band: torch.Tensor):
        render, inputs = ctx.render, ctx.inputs
        sdf, rgb, t = inputs[0], inputs[1], inputs[2]
        # the gradient reaching each term: its own plus the total's times its weight
        own = torch.stack([g_color, g_depth, g_free, g_band]).to(torch.float64)
        coef = own + g_total.to(torch.float64) * ctx.weights
        grad_sdf = torch.empty_like(sdf)
        grad_rgb = torch.empty_like(rgb) if rgb is not None and ctx.needs_input_grad[1] else None
        n, s = t.shape
        native.band_loss_kernels().band_losses_backward(
            *(_ptr(x) for x in inputs), n, s, render.truncation_m, render.weight_scale_m, coef.data_ptr(),
            ctx.counts.data_ptr(), grad_sdf.data_ptr(), _ptr(grad_rgb))
        return grad_sdf, grad_rgb, None, None, None, None, None, None, None, None


class _BandLosses(torch.autograd.Function):
    """:func:`band_losses`: ``(sdf [N, S], rgb [N, S, 3] | None, t, mask, dir_norm, depth_gt, color_gt, color_valid,
    render, config) -> (total, color, depth, free_space, sdf)`` 0-dim tensors, differentiable in ``sdf`` and ``rgb``.

    Forward: :func:`~.render.composite`'s and :func:`compute_losses`' operators in their order (the same values).
    Backward, per ray and sample (``c_x = g_total w_x + g_x``: the gradient reaching term ``x``):

    * depth ``D = sum_s a_s t_s`` and colour ``C = sum_s a_s c_s`` from the normalised weights ``a``: the L1 terms
      give ``dL/dD = c_depth sign(D - D_gt) / n_valid`` and ``dL/dC = c_color sign(C - C_gt) / (3 n_colour)`` on their
      rays; ``dL/da_s = dL/dD t_s + dL/dC . c_s`` and ``dL/dc_s = dL/dC a_s``;
    * ``a = w / max(sum w, 1e-20)``: ``dL/dw_s = (dL/da_s - sum_s' dL/da_s' a_s') / max(sum w, 1e-20)`` (the sum term
      only where ``sum w >= 1e-20``, as ``clamp``'s gradient);
    * ``w = sigmoid(s / b) sigmoid(-s / b) keep`` (``keep``: inside the map and not behind the first surface plus the
      truncation; constant): ``dw/ds = sigmoid(s / b) sigmoid(-s / b) (sigmoid(-s / b) - sigmoid(s / b)) / b``;
    * the free-space and SDF terms: ``2 (s - target) / tr^2`` times :func:`_per_ray_mean`'s derivative.
    """

    @staticmethod
    def forward(ctx, sdf: torch.Tensor, rgb: torch.Tensor | None, t: torch.Tensor,  # noqa: ANN001, ANN205
                mask: torch.Tensor, dn: torch.Tensor, depth_gt: torch.Tensor, color_gt: torch.Tensor | None,
                color_valid: torch.Tensor | None, render: RenderConfig, config: LossConfig):
        tr, b = render.truncation_m, render.weight_scale_m
        # composite (render/volume.py), operator for operator
        sdf = torch.where(mask, sdf, torch.zeros_like(sdf))
        s_pos, s_neg = torch.sigmoid(sdf / b), torch.sigmoid(-sdf / b)
        bell = s_pos * s_neg
        keep = first_surface(sdf, t, mask, dn, tr)[1]
        w = bell * mask * keep
        w_sum = w.sum(1)
        w_norm = w_sum.clamp(min=1e-20)
        weights = w / w_norm[:, None]
        depth = (weights * t).sum(1)
        hit = mask.any(1)
        # compute_losses, operator for operator
        valid_d = hit & (depth_gt > 0) & torch.isfinite(depth_gt)
        color_term = depth.new_zeros(())
        color_sign = color_rays = None
        if rgb is not None:
            rgb = torch.where(mask[:, :, None].expand(-1, -1, 3).contiguous(), rgb, torch.zeros_like(rgb))
            color = torch.stack([(weights * rgb[:, :, c]).sum(1) for c in range(3)], 1)
            diff = color - color_gt
            color_rays = hit if color_valid is None else hit & color_valid
            color_term = _masked_mean(diff.abs().mean(-1), color_rays)
            color_sign = diff.sign()
        depth_diff = depth - torch.where(valid_d, depth_gt, depth)
        depth_term = _masked_mean(depth_diff.abs(), valid_d)
        d_gt = torch.where(valid_d, depth_gt, torch.zeros_like(depth_gt))
        dist = (d_gt[:, None] - t) * dn[:, None]
        base = mask & valid_d[:, None]
        fs_mask = base & (dist > tr)
        band = base & (dist.abs() <= tr)
        fs_res = (sdf - tr) / tr
        band_res = (sdf - dist) / tr
        free_space, fs_scale = _per_ray_mean(fs_res ** 2, fs_mask)
        sdf_term, band_scale = _per_ray_mean(band_res ** 2, band)
        total = (config.w_color * color_term + config.w_depth * depth_term + config.w_fs * free_space
                 + config.w_sdf * sdf_term)
        ctx.config, ctx.b, ctx.tr = config, b, tr
        ctx.save_for_backward(mask & keep, t, rgb, s_pos, s_neg, bell, w_sum, w_norm, weights, valid_d,
                              depth_diff.sign(), color_sign, color_rays, fs_res * fs_mask, fs_scale,
                              band_res * band, band_scale)
        return total, color_term, depth_term, free_space, sdf_term

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_total: torch.Tensor, g_color: torch.Tensor, g_depth: torch.Tensor,  # noqa: ANN001, ANN205
                 g_free: torch.Tensor, g_band: torch.Tensor):
        (kept, t, rgb, s_pos, s_neg, bell, w_sum, w_norm, weights, valid_d, depth_sign, color_sign, color_rays,
         fs_res, fs_scale, band_res, band_scale) = ctx.saved_tensors
        cfg, tr = ctx.config, ctx.tr
        # d loss / d depth [N], then / d normalised weight [N, S]
        c_depth = g_total * cfg.w_depth + g_depth
        g_weights = (depth_sign * valid_d * (c_depth / valid_d.sum().clamp(min=1)))[:, None] * t
        g_rgb = None
        if rgb is not None:  # d loss / d colour [N, 3]
            c_color = g_total * cfg.w_color + g_color
            g_col = color_sign * (color_rays * (c_color / (3 * color_rays.sum().clamp(min=1))))[:, None]
            g_weights = g_weights + (rgb * g_col[:, None, :]).sum(-1)
            if ctx.needs_input_grad[1]:
                # zero outside the map, as the reference's where (outside it the weights are 0 as well)
                g_rgb = weights[:, :, None] * g_col[:, None, :]
        # the normalisation, then the bell-shaped weight
        g_sum = (g_weights * weights).sum(1) * (w_sum >= 1e-20)
        g_w = (g_weights - g_sum[:, None]) / w_norm[:, None]
        g_s = g_w * kept * bell * (s_neg - s_pos) / ctx.b
        # the free-space and SDF terms (residuals already zero outside their sets)
        c_free = g_total * cfg.w_fs + g_free
        c_band = g_total * cfg.w_sdf + g_band
        g_s = g_s + (fs_res * (fs_scale * (2.0 / tr) * c_free)[:, None]
                     + band_res * (band_scale * (2.0 / tr) * c_band)[:, None])
        return g_s, g_rgb, None, None, None, None, None, None, None, None
