"""Losses (paper eq. 5-7): zero for perfect predictions, each term measures what it should."""

from __future__ import annotations

import pytest
import torch

from voxfusion.core.errors import ConfigError, ShapeError
from voxfusion.core.losses import LossConfig, compute_losses
from voxfusion.core.map import VoxelMap
from voxfusion.core.map.field import SDFDecoder
from voxfusion.core.render.volume import RenderConfig, RenderOutput, camera_rays, render_rays

TR = 0.1


def _output(depth_gt: torch.Tensor, dir_norm: torch.Tensor, sdf_offset: float = 0.0) -> RenderOutput:
    """Hand-made render of rays sampled every 1 cm from 1.5 to 2.5 with the perfect truncated SDF."""
    n = depth_gt.shape[0]
    t = torch.linspace(1.5, 2.5, 101).expand(n, 101).clone()
    dist = (depth_gt[:, None] - t) * dir_norm[:, None]
    sdf = dist.clamp(max=TR) + sdf_offset  # behind the band: any value (no loss there)
    mask = torch.ones(n, 101, dtype=torch.bool)
    mask[:, -5:] = False
    w = torch.exp(-(dist / 0.01) ** 2)
    w = w / w.sum(1, keepdim=True)
    return RenderOutput(depth=depth_gt.clone(), color=torch.full((n, 3), 0.5), weight_sum=torch.ones(n),
                        hit=torch.ones(n, dtype=torch.bool), surface=torch.ones(n, dtype=torch.bool), t=t,
                        sdf=sdf, weights=w, sample_mask=mask, dir_norm=dir_norm, truncation_m=TR)


def test_losses_are_zero_for_perfect_predictions():
    depth = torch.tensor([2.0, 1.9, 2.1, 1.95])
    dn = torch.tensor([1.0, 1.1, 1.3, 1.02])
    terms = compute_losses(_output(depth, dn), depth, torch.full((4, 3), 0.5))
    for name, val in terms.as_floats().items():
        assert val == pytest.approx(0.0, abs=1e-10), name


def test_each_term_measures_its_error():
    depth = torch.tensor([2.0, 1.9, 2.1, 1.95])
    dn = torch.ones(4)
    out = _output(depth, dn)
    out.depth = depth + torch.tensor([0.1, -0.1, 0.0, 0.0])
    out.color = torch.full((4, 3), 0.7)
    t = compute_losses(out, depth, torch.full((4, 3), 0.5))
    assert float(t.depth) == pytest.approx(0.05, rel=1e-5)
    assert float(t.color) == pytest.approx(0.2, rel=1e-5)
    # an SDF offset of tr gives 1 (squared error in units of tr) in both SDF terms
    t2 = compute_losses(_output(depth, dn, sdf_offset=TR), depth, None)
    assert float(t2.free_space) == pytest.approx(1.0, rel=1e-4)
    assert float(t2.sdf) == pytest.approx(1.0, rel=1e-4)
    assert float(t2.color) == 0.0
    cfg = LossConfig(w_color=0.0, w_depth=0.0, w_fs=3.0, w_sdf=7.0)
    total = compute_losses(_output(depth, dn, TR), depth, None, cfg).total
    assert float(total) == pytest.approx(10.0, rel=1e-4)


def test_band_uses_metric_distance_along_the_ray():
    # with |d| = 2, a sample 0.06 t-units in front of D is 0.12 m away: free space, not band
    depth = torch.tensor([2.0])
    out = _output(depth, torch.tensor([2.0]))
    out.sdf = torch.zeros_like(out.sdf)
    terms = compute_losses(out, depth, None)
    dist = (depth[:, None] - out.t) * 2.0
    fs = (dist > TR) & out.sample_mask
    band = (dist.abs() <= TR) & out.sample_mask
    assert float(terms.free_space) == pytest.approx(1.0, rel=1e-5)  # (0 - tr)^2 / tr^2
    expect = float(((dist[band] / TR) ** 2).mean())
    assert float(terms.sdf) == pytest.approx(expect, rel=1e-5)
    assert fs.sum() > 0 and band.sum() == 11  # |t - D| <= 0.05 t-units, 1 cm steps


def test_invalid_depth_and_missed_rays_are_ignored():
    depth = torch.tensor([2.0, 0.0, 2.0])
    out = _output(torch.tensor([2.0, 2.0, 2.0]), torch.ones(3))
    out.hit = torch.tensor([True, True, False])
    out.depth = torch.tensor([2.0, 5.0, 9.0])
    out.sdf[2] = 9.0
    out.color = torch.tensor([[0.5] * 3, [0.5] * 3, [1.0] * 3])
    t = compute_losses(out, depth, torch.full((3, 3), 0.5))
    assert all(v == 0.0 for v in t.as_floats().values())
    with pytest.raises(ShapeError):
        compute_losses(out, depth[:2], None)
    with pytest.raises(ShapeError):
        compute_losses(out, depth, torch.zeros(3, 4))
    with pytest.raises(ConfigError):
        LossConfig(w_sdf=-1.0)


def test_losses_of_a_rendered_analytic_truncated_sdf_are_near_zero_and_decoder_gets_gradients():
    vm = VoxelMap(0.2, seed=0)
    ax = torch.linspace(-0.9, 0.9, 10)
    x, y, z = torch.meshgrid(ax, ax, torch.linspace(1.7, 2.3, 4), indexing="ij")
    vm.allocate(torch.stack([x, y, z], -1).reshape(-1, 3))
    K = torch.tensor([[60.0, 0.0, 15.5], [0.0, 60.0, 11.5], [0.0, 0.0, 1.0]])
    o, d = camera_rays(K, torch.eye(4), width=32, height=24)
    cfg = RenderConfig(truncation_m=TR, step_ratio=0.05, max_distance_m=4.0)

    def truncated_plane(p, _idx):
        return (2.0 - p[:, 2]).clamp(max=TR), torch.full((p.shape[0], 3), 0.3)

    out = render_rays(vm, truncated_plane, o, d, cfg)
    gt = torch.full((o.shape[0],), 2.0)
    t = compute_losses(out, gt, torch.full((o.shape[0], 3), 0.3))
    assert t.depth < 1e-3 and t.color < 1e-6 and t.free_space < 1e-10
    # z-distance vs metric distance along slightly oblique rays: small but nonzero
    assert t.sdf < 0.05

    dec = SDFDecoder()
    gen = torch.Generator().manual_seed(0)
    out = render_rays(vm, dec, o[:128], d[:128], cfg, training=True, generator=gen)
    terms = compute_losses(out, gt[:128], torch.full((128, 3), 0.3))
    terms.total.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in dec.parameters())
    assert vm.embeddings.grad.abs().sum() > 0


def _band_samples(n: int, s: int, seed: int):
    """Random mapping samples with every case the compositing meets: samples outside the map holding garbage
    (non-finite), rays with no sample in the map, rays whose observed depth is invalid, surfaces crossed inside
    the band, and samples behind the first surface plus the truncation."""
    from voxfusion.core.render.volume import BandSamples

    g = torch.Generator().manual_seed(seed)
    depth = 1.0 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64).float()
    t = torch.sort(depth[:, None] + (torch.rand(n, s, generator=g) - 0.7) * 0.5, dim=1).values
    dn = 1.0 + 0.2 * torch.rand(n, generator=g)
    sdf = ((depth[:, None] - t) * dn[:, None]).clamp(max=TR) + 0.02 * torch.randn(n, s, generator=g)
    mask = torch.rand(n, s, generator=g) > 0.2
    mask[:5] = False  # rays that miss the map
    sdf = torch.where(mask, sdf, torch.full_like(sdf, float("nan")))  # never read outside the map
    rgb = torch.where(mask[:, :, None], torch.rand(n, s, 3, generator=g), torch.full((n, s, 3), float("inf")))
    depth[5:9] = 0.0  # invalid observed depth
    color_gt = torch.rand(n, 3, generator=g)
    color_valid = torch.rand(n, generator=g) > 0.3
    return BandSamples(sdf, rgb, t, mask, dn), depth, color_gt, color_valid


@pytest.mark.parametrize("with_color", [True, False])
@pytest.mark.parametrize("samples_per_ray", [7, 1])
def test_band_losses_are_the_composited_losses_with_their_gradients(with_color: bool, samples_per_ray: int,
                                                                   native_path: str):
    """The mapper's fused compositing and losses (the C kernel; one autograd function of PyTorch operators with the
    backward written out) against composite + compute_losses through autograd: every term (to the bit from the
    operators, to float32 rounding from the kernel, which sums over rays in double), the gradients with respect to
    the SDF and the colours to float32 rounding, zero outside the map; with and without colour (and rays without a
    colour observation), and with one sample per ray."""
    from voxfusion.core.losses import band_losses
    from voxfusion.core.render.volume import BandSamples, composite

    samples, depth, color_gt, color_valid = _band_samples(300, samples_per_ray, seed=samples_per_ray)
    render = RenderConfig(truncation_m=TR)
    config = LossConfig(w_color=0.5, w_depth=1.0, w_fs=2.5, w_sdf=1250.0)
    cgt, cvalid = (color_gt, color_valid) if with_color else (None, None)
    results = []
    for fused in (True, False):
        sdf = samples.sdf.clone().requires_grad_(True)
        rgb = samples.rgb.clone().requires_grad_(True) if with_color else None
        s = BandSamples(sdf, rgb, samples.t, samples.mask, samples.dir_norm)
        if fused:
            terms = band_losses(s, depth, cgt, render, config, cvalid)
        else:
            out = composite(s.sdf, s.rgb, s.t, s.mask, s.dir_norm, s.mask.any(1), render)
            terms = compute_losses(out, depth, cgt, config, cvalid)
        grads = torch.autograd.grad(terms.total, [sdf] + ([rgb] if with_color else []))
        results.append((terms, grads))
    (fused_terms, fused_grads), (ref_terms, ref_grads) = results
    for name, value in ref_terms.as_floats().items():
        if native_path == "operators":
            assert getattr(fused_terms, name).item() == value, name
        else:
            assert getattr(fused_terms, name).item() == pytest.approx(value, rel=1e-6, abs=1e-9), name
    assert ref_terms.sdf > 0 and ref_terms.free_space > 0 and ref_terms.depth > 0  # every term has support
    for fast, ref in zip(fused_grads, ref_grads, strict=True):
        scale = float(ref.abs().max())
        assert scale > 0 and torch.isfinite(fast).all()
        torch.testing.assert_close(fast, ref, rtol=1e-4, atol=1e-5 * scale)
    outside = ~samples.mask
    assert fused_grads[0][outside].abs().max() == 0
    if with_color:
        assert fused_grads[1][outside].abs().max() == 0


def test_band_losses_pass_on_the_gradient_of_each_term(native_path: str):
    """A caller may differentiate any combination of the terms (the backward takes each term's gradient): the
    gradient of ``2 depth + 3 free_space`` matches autograd's."""
    from voxfusion.core.losses import band_losses
    from voxfusion.core.render.volume import BandSamples, composite

    samples, depth, color_gt, color_valid = _band_samples(200, 7, seed=3)
    render = RenderConfig(truncation_m=TR)
    grads = []
    for fused in (True, False):
        sdf = samples.sdf.clone().requires_grad_(True)
        s = BandSamples(sdf, samples.rgb, samples.t, samples.mask, samples.dir_norm)
        if fused:
            terms = band_losses(s, depth, color_gt, render, LossConfig(), color_valid)
        else:
            out = composite(s.sdf, s.rgb, s.t, s.mask, s.dir_norm, s.mask.any(1), render)
            terms = compute_losses(out, depth, color_gt, LossConfig(), color_valid)
        grads.append(torch.autograd.grad(2 * terms.depth + 3 * terms.free_space, sdf)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-5 * float(grads[1].abs().max()))
    with pytest.raises(ShapeError):
        band_losses(samples, depth[:5], None, render)
