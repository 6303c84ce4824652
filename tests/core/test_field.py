"""Neural field: trilinear interpolation of shared vertex embeddings, decoder, point queries."""

from __future__ import annotations

import pytest
import torch

from voxfusion.core.errors import ConfigError, ShapeError, ValidationError
from voxfusion.core.map import CORNER_OFFSETS, VoxelMap
from voxfusion.core.map.field import FieldConfig, NeuralField, SDFDecoder, interpolate, local_coords, query


def _two_voxel_map() -> VoxelMap:
    vm = VoxelMap(0.5, embed_dim=4, seed=0)
    vm.allocate(torch.tensor([[0.25, 0.25, 0.25], [0.75, 0.25, 0.25]]))
    with torch.no_grad():
        vm.embeddings.normal_(generator=torch.Generator().manual_seed(1))
    return vm


def test_interpolation_hits_vertex_values_at_corners():
    vm = _two_voxel_map()
    corners = (vm.voxel_coords[0] + CORNER_OFFSETS).double() * 0.5
    feats = interpolate(vm, corners, torch.zeros(8, dtype=torch.int64))
    assert torch.allclose(feats, vm.embeddings[vm.voxel_vertex_ids[0]], atol=1e-6)


def test_interpolation_matches_trilinear_formula_and_is_continuous_across_shared_faces():
    vm = _two_voxel_map()
    g = torch.Generator().manual_seed(2)
    loc = torch.rand(64, 3, generator=g)
    pts = loc * 0.5  # voxel 0 spans [0, 0.5)^3
    feats = interpolate(vm, pts, torch.zeros(64, dtype=torch.int64))
    e = vm.embeddings[vm.voxel_vertex_ids[0]].detach()  # [8, D], corner c = 4dx + 2dy + dz
    x, y, z = loc[:, 0:1], loc[:, 1:2], loc[:, 2:3]
    ref = torch.zeros_like(feats)
    for c, (dx, dy, dz) in enumerate(CORNER_OFFSETS.tolist()):
        w = (x if dx else 1 - x) * (y if dy else 1 - y) * (z if dz else 1 - z)
        ref = ref + w * e[c]
    assert torch.allclose(feats, ref, atol=1e-6)
    # points on the shared face x = 0.5 give the same features from either voxel
    face = torch.cat([torch.full((16, 1), 0.5), torch.rand(16, 2, generator=g) * 0.5], 1)
    a = interpolate(vm, face, torch.zeros(16, dtype=torch.int64))
    b = interpolate(vm, face, torch.ones(16, dtype=torch.int64))
    assert torch.allclose(a, b, atol=1e-6)
    assert torch.allclose(local_coords(vm, face, torch.ones(16, dtype=torch.int64))[:, 0], torch.zeros(16))


def test_interpolate_rejects_unallocated_points_and_bad_shapes():
    vm = _two_voxel_map()
    with pytest.raises(ValidationError):
        interpolate(vm, torch.zeros(2, 3), torch.tensor([0, -1]))
    with pytest.raises(ShapeError):
        interpolate(vm, torch.zeros(2, 2), torch.tensor([0, 0]))
    with pytest.raises(ShapeError):
        interpolate(vm, torch.zeros(2, 3), torch.tensor([0]))


def test_decoder_shapes_units_and_depth_only_variant():
    feats = torch.randn(10, 16)
    sdf, rgb = SDFDecoder(FieldConfig())(feats)
    assert sdf.shape == (10,) and rgb.shape == (10, 3)
    assert ((rgb >= 0) & (rgb <= 1)).all()
    sdf2, rgb2 = SDFDecoder(FieldConfig(use_color=False, sdf_layers=3, sdf_hidden=32))(feats)
    assert sdf2.shape == (10,) and rgb2 is None
    pe = SDFDecoder(FieldConfig(local_coord_freqs=4))
    assert pe.config.input_dim == 16 + 3 + 24
    assert pe(feats, torch.rand(10, 3))[0].shape == (10,)
    with pytest.raises(ValidationError):
        pe(feats)
    with pytest.raises(ShapeError):
        SDFDecoder()(torch.randn(10, 8))
    # the raw output is scaled to metres by sdf_scale_m
    torch.manual_seed(0)
    a = SDFDecoder(FieldConfig(sdf_scale_m=0.1))
    torch.manual_seed(0)
    b = SDFDecoder(FieldConfig(sdf_scale_m=0.2))
    assert torch.allclose(2 * a(feats)[0], b(feats)[0])


def test_field_config_validation():
    with pytest.raises(ConfigError):
        FieldConfig(sdf_layers=0)
    with pytest.raises(ConfigError):
        FieldConfig(sdf_scale_m=0.0)
    with pytest.raises(ConfigError):
        FieldConfig(local_coord_freqs=-1)
    with pytest.raises(ConfigError, match="precision"):
        FieldConfig(precision="float64")  # type: ignore[arg-type]


def test_query_marks_points_outside_voxels_invalid_and_matches_field():
    vm = VoxelMap(0.2, seed=0)
    inside = torch.rand(50, 3)
    vm.allocate(inside)
    dec = SDFDecoder()
    pts = torch.cat([inside, torch.full((5, 3), 10.0)])
    with torch.no_grad():
        sdf, rgb, valid = query(vm, dec, pts, chunk=7)
        idx = vm.lookup_voxels(pts)
        ref_sdf, ref_rgb = NeuralField(vm, dec)(pts[idx >= 0], idx[idx >= 0])
    assert torch.equal(valid, idx >= 0)
    assert valid[:50].all() and not valid[50:].any()
    assert torch.isnan(sdf[50:]).all() and (rgb[50:] == 0).all()
    assert torch.allclose(sdf[valid], ref_sdf) and torch.allclose(rgb[valid], ref_rgb)
    sdf_d, rgb_d, _ = query(vm, SDFDecoder(FieldConfig(use_color=False)), pts)
    assert rgb_d is None and sdf_d.shape == (55,)


def test_gradients_reach_embeddings_and_decoder():
    vm = VoxelMap(0.2, seed=0)
    vm.allocate(torch.rand(100, 3))
    dec = SDFDecoder()
    pts = torch.rand(64, 3)
    sdf, rgb, valid = query(vm, dec, pts)
    (sdf[valid].sum() + rgb[valid].sum()).backward()
    assert vm.embeddings.grad is not None and vm.embeddings.grad.abs().sum() > 0
    assert all(p.grad is not None for p in dec.parameters())
    with pytest.raises(ValidationError):
        NeuralField(vm, SDFDecoder(FieldConfig(embed_dim=8)))


def _map_with_points_inside(embed_dim: int, n_allocated: int, n_points: int, seed: int):
    """A random map, points that fall in its voxels with their voxel indices, and a random output gradient."""
    vm = VoxelMap(0.2, embed_dim=embed_dim, seed=0)
    g = torch.Generator().manual_seed(seed)
    vm.allocate(torch.rand(n_allocated, 3, generator=g))
    pts = torch.rand(n_points, 3, generator=g) * 0.98 + 0.01
    idx = vm.lookup_voxels(pts)
    pts, idx = pts[idx >= 0], idx[idx >= 0]
    return vm, pts, idx, torch.randn(pts.shape[0], embed_dim, generator=g)


def test_trilinear_weights_are_the_corner_products_with_their_gradient():
    """The per-column weights (hand-written backward) against the products of per-axis weights in corner
    order, and the backward against finite differences (float64)."""
    from voxfusion.core.map.field import trilinear_weights

    g = torch.Generator().manual_seed(3)
    local = torch.rand(257, 3, generator=g, dtype=torch.float64)
    local[:4] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [0.25, 0.0, 1.0]])
    off = CORNER_OFFSETS.to(torch.float64)
    want = (off * local[:, None, :] + (1.0 - off) * (1.0 - local[:, None, :])).prod(-1)  # [K, 8]
    got = trilinear_weights(local)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-15)
    torch.testing.assert_close(got.sum(1), torch.ones(257, dtype=torch.float64))
    x = local[:40].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(trilinear_weights, (x,))
    y = local[:40].clone().requires_grad_(True)
    out_grad = torch.randn(40, 8, generator=g, dtype=torch.float64)
    (gx,) = torch.autograd.grad(trilinear_weights(y), [y], out_grad)
    (gy,) = torch.autograd.grad((off * y[:, None, :] + (1.0 - off) * (1.0 - y[:, None, :])).prod(-1), [y], out_grad)
    torch.testing.assert_close(gx, gy, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_trilinear_weights_per_column_and_as_outer_products_are_the_same_numbers(dtype):
    """The CPU form (per column) and the GPU form (outer products of per-axis weights, fewer launches) compute the
    same arithmetic in the same order: equal to the bit, weights and coordinate gradients, corners included."""
    from voxfusion.core.map import field

    g = torch.Generator().manual_seed(5)
    local = torch.rand(1000, 3, generator=g, dtype=dtype)
    local[:4] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [0.25, 0.0, 1.0]], dtype=dtype)
    grad_w = torch.randn(1000, 8, generator=g, dtype=dtype)
    assert torch.equal(field._trilinear_weights_per_column(local), field._trilinear_weights_outer(local))
    assert torch.equal(field._trilinear_backward_per_column(local, grad_w),
                       field._trilinear_backward_outer(local, grad_w))
    assert torch.equal(field._trilinear_weight_columns(local), field._trilinear_weights_per_column(local))  # CPU


@pytest.mark.parametrize("n_points", [3000, 40])
def test_fused_interpolation_matches_the_reference_in_values_and_gradients(n_points: int, native_path: str):
    """The fast paths (the compiled kernel; embedding_bag forward with a hand-written backward) against the plain
    gather-and-sum: features, and gradients to both the embeddings and the points (the trackers differentiate
    through the trilinear weights). 3000 points outnumber the voxels (the operators accumulate the table gradient
    per voxel first), 40 do not (one accumulation over the corner rows)."""
    from voxfusion.core.map.field import interpolate_reference, interpolate_unchecked

    vm, pts, idx, out_grad = _map_with_points_inside(16, 400, n_points, seed=1)
    assert (pts.shape[0] > vm.n_voxels) == (n_points == 3000)
    results = []
    for fn in (interpolate_unchecked, interpolate_reference):
        x = pts.clone().requires_grad_(True)
        vm.embeddings.grad = None
        feats = fn(vm, x, idx)
        feats.backward(out_grad)
        results.append((feats.detach(), vm.embeddings.grad.clone(), x.grad.clone()))
    for fast, ref in zip(results[0], results[1], strict=True):
        torch.testing.assert_close(fast, ref, rtol=1e-4, atol=1e-5)  # float32 sums in another order


def test_fused_interpolation_backward_is_reproducible_and_serves_a_frozen_table(native_path: str):
    """Offline runs are bit-reproducible on CPU, so the hand-written backward must be too; and the SDF
    tracker asks only for the points' gradient, with a table that needs none."""
    from voxfusion.core.map.field import interpolate_unchecked

    vm, pts, idx, out_grad = _map_with_points_inside(8, 300, 5000, seed=2)
    grads = []
    for _ in range(2):
        vm.embeddings.grad = None
        interpolate_unchecked(vm, pts, idx).backward(out_grad)
        grads.append(vm.embeddings.grad.clone())
    assert torch.equal(grads[0], grads[1])
    x = pts.clone().requires_grad_(True)
    vm.embeddings.requires_grad_(False)  # a frozen table: only the points need a gradient
    (gx,) = torch.autograd.grad(interpolate_unchecked(vm, x, idx), [x], out_grad)
    assert vm.embeddings.grad is None or torch.equal(vm.embeddings.grad, grads[1])  # the table was left alone
    assert torch.isfinite(gx).all() and gx.abs().sum() > 0


def _decoder_pair(sdf_layers: int = 2, **fast: object) -> tuple[SDFDecoder, SDFDecoder]:
    """The float32 eager reference and a variant (``fast``: its execution options) with the same weights."""
    import dataclasses

    torch.manual_seed(0)
    ref = SDFDecoder(FieldConfig(sdf_hidden=32, color_hidden=32, sdf_layers=sdf_layers))
    variant = SDFDecoder(dataclasses.replace(ref.config, **fast))
    variant.load_state_dict(ref.state_dict())
    return ref, variant


def _outputs_and_grads(decoder: SDFDecoder, feats: torch.Tensor) -> list[torch.Tensor]:
    x = feats.clone().requires_grad_(True)
    sdf, rgb = decoder(x)
    (sdf.sum() * 10 + rgb.sum()).backward()
    return [sdf.detach(), rgb.detach(), x.grad, *[p.grad for p in decoder.parameters()]]


@pytest.mark.parametrize("precision", ["bfloat16", "float16"])
def test_mixed_precision_decoder_matches_the_float32_reference(precision):
    ref, fast = _decoder_pair(precision=precision)
    feats = torch.randn(2048, 16, generator=torch.Generator().manual_seed(2)) * 0.3
    want = _outputs_and_grads(ref, feats)
    got = _outputs_and_grads(fast, feats)
    assert all(g.dtype == torch.float32 for g in got[:3])  # outputs and input gradients stay float32
    assert not torch.equal(got[0], want[0])  # the products really ran in the low precision
    # SDF within 1 mm (sdf_scale 0.1 m), colour within 0.01 everywhere. Gradients, relative to their norm
    # (single entries differ more where rounding moves a ReLU across its kink): the input's (what the SDF
    # tracker's Jacobian is made of; measured 5.8 % bf16, 1.6 % fp16) and the parameters' (what mapping
    # steps with; measured <= 1.1 % bf16, 0.2 % fp16)
    torch.testing.assert_close(got[0], want[0], atol=1e-3, rtol=0)
    torch.testing.assert_close(got[1], want[1], atol=1e-2, rtol=0)
    tol_input, tol_params = (0.08, 0.02) if precision == "bfloat16" else (0.02, 0.005)
    assert float((got[2] - want[2]).norm() / want[2].norm()) < tol_input
    for g, w in zip(got[3:], want[3:], strict=True):
        assert float((g - w).norm() / w.norm()) < tol_params


def test_compiled_decoder_matches_eager_and_serves_copies():
    import copy

    ref, fast = _decoder_pair(compile=True)
    feats = torch.randn(300, 16, generator=torch.Generator().manual_seed(3))
    want = _outputs_and_grads(ref, feats)
    got = _outputs_and_grads(fast, feats)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, atol=1e-5, rtol=1e-5)
    for snapshot in (fast.frozen_copy(), copy.deepcopy(fast)):  # the engine's map snapshots copy the decoder
        with torch.no_grad():
            torch.testing.assert_close(snapshot(feats[:77])[0], ref(feats[:77])[0], atol=1e-5, rtol=1e-5)


def test_frozen_copy_is_an_independent_decoder_without_gradient():
    import copy

    decoder = SDFDecoder(FieldConfig(embed_dim=16, sdf_hidden=32, color_hidden=32))
    frozen = decoder.frozen_copy()
    reference = copy.deepcopy(decoder).requires_grad_(False)  # what it stands for
    feats = torch.randn(50, 16, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        for got, want in zip(frozen(feats), reference(feats), strict=True):
            assert torch.equal(got, want)
    assert [name for name, _ in frozen.named_parameters()] == [name for name, _ in decoder.named_parameters()]
    assert all(not p.requires_grad for p in frozen.parameters())
    assert all(p.requires_grad for p in decoder.parameters())  # the original keeps training
    with torch.no_grad():  # training the original later does not reach the copy
        next(decoder.parameters()).add_(1.0)
        assert torch.equal(frozen(feats)[0], reference(feats)[0])
    assert frozen.config is decoder.config and type(frozen.sdf_net) is type(decoder.sdf_net)


def test_compile_failure_leaves_one_warning_and_the_eager_decoder(monkeypatch, caplog):
    import torch._dynamo
    import torch._inductor.config as inductor_config

    from voxfusion.core.map import field

    monkeypatch.setattr(field.COMPILED_MLP, "_compiled", None)
    monkeypatch.setattr(field.COMPILED_MLP, "failed", False)
    torch._dynamo.reset()
    ref, fast = _decoder_pair(sdf_layers=3, compile=True)  # a graph no earlier test compiled
    feats = torch.randn(64, 16, generator=torch.Generator().manual_seed(4))
    # a real compiler failure: inductor is pointed at a C++ compiler that does not exist, and no cached artefact
    # stands in for it (the config's own patch restores both: ``force_disable_caches`` is an alias there)
    with inductor_config.patch({"cpp.cxx": ("/nonexistent/voxfusion-c++",), "force_disable_caches": True}), \
            caplog.at_level("WARNING", logger="voxfusion.field"):
        got = [fast(feats)[0], fast(feats)[0]]
    assert field.COMPILED_MLP.failed is True
    assert len([r for r in caplog.records if "field.compile" in r.getMessage()]) == 1
    for g in got:
        torch.testing.assert_close(g, ref(feats)[0], atol=0, rtol=0)
    torch._dynamo.reset()


def test_geometry_only_decoding_is_the_sdf_of_the_full_decoder_with_its_gradient():
    """``with_color=False`` (SDF tracker, meshing) evaluates only the SDF row of the last layer: the same SDF
    and the same gradient to the features as the full decoder."""
    torch.manual_seed(0)
    dec = SDFDecoder(FieldConfig(sdf_hidden=32, color_hidden=32))
    feats = torch.randn(500, 16, generator=torch.Generator().manual_seed(5)) * 0.3
    x_full = feats.clone().requires_grad_(True)
    x_geo = feats.clone().requires_grad_(True)
    sdf_full, rgb = dec(x_full)
    sdf_geo, none = dec(x_geo, with_color=False)
    assert rgb is not None and none is None and sdf_geo.shape == (500,)
    torch.testing.assert_close(sdf_geo, sdf_full, rtol=1e-5, atol=1e-7)
    (g_full,) = torch.autograd.grad(sdf_full.sum(), x_full)
    (g_geo,) = torch.autograd.grad(sdf_geo.sum(), x_geo)
    torch.testing.assert_close(g_geo, g_full, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("sdf_layers", [1, 2, 3])
def test_sdf_with_gradient_matches_autograd_through_the_field(sdf_layers: int, native_path: str):
    """The SDF tracker's field query (forward and backward written out, no autograd graph) against autograd
    through the same interpolation and decoder: values and spatial gradients, for 1-3 hidden layers, with
    points on voxel faces and corners (where the local coordinate is exactly 0 or 1) among random ones, and
    with random decoder weights large enough that many ReLUs are off."""
    from voxfusion.core.map.field import sdf_with_gradient, sdf_with_gradient_reference

    vm, pts, idx, _ = _map_with_points_inside(16, 400, 3000, seed=4)
    with torch.no_grad():
        vm.embeddings.mul_(30.0)  # the map's init is tiny: spread the features so the decoder's units switch
    corners = vm.voxel_coords[idx[:20]].to(pts.dtype) * vm.voxel_size_m  # voxel origins: local (0, 0, 0)
    pts = torch.cat([corners, pts[20:]])
    ref, _ = _decoder_pair(sdf_layers)
    assert ref.has_plain_gradient
    sdf, grad = sdf_with_gradient(vm, ref, pts, idx)
    sdf_ref, grad_ref = sdf_with_gradient_reference(vm, ref, pts, idx)
    scale = float(grad_ref.abs().max())
    assert scale > 0.01 and (grad_ref.abs() > 0.1 * scale).float().mean() > 0.3  # not a comparison of zeros
    torch.testing.assert_close(sdf, sdf_ref, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-5 * scale)
    assert not sdf.requires_grad and not grad.requires_grad


@pytest.mark.parametrize("variant", [{"local_coord_freqs": 2}, {"precision": "bfloat16"}])
def test_sdf_with_gradient_falls_back_to_autograd_for_other_decoders(variant: dict):
    """Decoders whose input is not the embedding alone (positional encoding) or that run in mixed precision
    take the autograd path, so the result is the reference's exactly."""
    import dataclasses

    from voxfusion.core.map.field import sdf_with_gradient, sdf_with_gradient_reference

    vm, pts, idx, _ = _map_with_points_inside(16, 200, 500, seed=5)
    torch.manual_seed(0)
    dec = SDFDecoder(dataclasses.replace(FieldConfig(sdf_hidden=32, color_hidden=32), **variant))
    assert not dec.has_plain_gradient
    for got, want in zip(sdf_with_gradient(vm, dec, pts, idx), sdf_with_gradient_reference(vm, dec, pts, idx),
                         strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_corner_weight_gradient_gathers_per_voxel_or_per_sample_alike():
    """More samples than voxels: every voxel's corner rows once, then per sample; fewer: per sample directly. The
    same numbers either way (the rows gathered are the same, the product the same)."""
    from voxfusion.core.map.field import _corner_weight_grad

    g = torch.Generator().manual_seed(5)
    emb = torch.randn(60, 16, generator=g)
    vertex_ids = torch.randint(0, 60, (30, 8), generator=g)
    for k in (100, 10):  # K > M, then K < M
        voxel_idx = torch.randint(0, 30, (k,), generator=g)
        grad_out = torch.randn(k, 16, generator=g)
        got = _corner_weight_grad(emb, vertex_ids, voxel_idx, grad_out)
        rows = emb[vertex_ids[voxel_idx]]  # [K, 8, D]
        torch.testing.assert_close(got, (rows * grad_out[:, None, :]).sum(-1), rtol=1e-6, atol=1e-6)
        other = torch.nn.functional.embedding(vertex_ids, emb).reshape(30, 128).index_select(0, voxel_idx)
        assert torch.equal(got, torch.bmm(other.reshape(k, 8, 16), grad_out[:, :, None]).squeeze(2))


def test_interpolation_kernel_clamps_like_the_operators_at_and_beyond_voxel_faces(monkeypatch):
    """Points exactly on voxel faces and corners, and a little outside their voxel (the clamped local coordinate,
    whose gradient is zero along the clamped axis), through the kernel and the operators: the same features and
    gradients."""
    from voxfusion.core import native
    from voxfusion.core.map.field import interpolate_unchecked

    if native._compiler() is None:
        pytest.skip("no C compiler: the interpolation kernel cannot be built here")
    vm, pts, idx, out_grad = _map_with_points_inside(16, 300, 600, seed=5)
    origin = vm.voxel_coords[idx].to(pts.dtype) * vm.voxel_size_m
    pts = pts.clone()
    pts[:10] = origin[:10]  # low corners: local (0, 0, 0)
    pts[10:20] = origin[10:20] + vm.voxel_size_m  # high corners
    pts[20:30, 0] = origin[20:30, 0] - 0.01  # 1 cm outside along x: clamped to 0
    pts[30:40, 2] = origin[30:40, 2] + vm.voxel_size_m + 0.01  # clamped to 1 along z
    results = {}
    for switch in ("1", "0"):
        monkeypatch.setenv(native.ENV_SWITCH, switch)
        x = pts.clone().requires_grad_(True)
        vm.embeddings.grad = None
        feats = interpolate_unchecked(vm, x, idx)
        feats.backward(out_grad)
        results[switch] = (feats.detach(), vm.embeddings.grad.clone(), x.grad.clone())
    assert results["1"][2][20:30, 0].abs().max() == 0 and results["1"][2][30:40, 2].abs().max() == 0
    for fast, ref in zip(results["1"], results["0"], strict=True):
        torch.testing.assert_close(fast, ref, rtol=1e-4, atol=1e-5)


def test_interpolation_kernel_build_failure_leaves_one_warning_and_the_operators(monkeypatch, tmp_path, caplog):
    """Where the C compiler fails (here: ``CC=false``), the first call logs one warning, later calls stay quiet,
    and the interpolation runs as PyTorch operators with the same results; a compiler that works builds the library
    once into the cache and later processes load it from there."""
    import logging

    from voxfusion.core import native
    from voxfusion.core.map.field import interpolate_reference, interpolate_unchecked

    monkeypatch.setenv("VOXFUSION_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(native.ENV_SWITCH, "1")
    monkeypatch.setenv("CC", "false")
    monkeypatch.setattr(native, "_loaded", {})
    vm, pts, idx, _ = _map_with_points_inside(8, 100, 200, seed=6)
    with caplog.at_level(logging.WARNING, logger="voxfusion.native"):
        assert native.interpolation_kernels() is None
        feats = interpolate_unchecked(vm, pts, idx)
        assert native.interpolation_kernels() is None
    assert sum("interpolation kernel" in r.getMessage() for r in caplog.records) == 1
    torch.testing.assert_close(feats, interpolate_reference(vm, pts, idx), rtol=1e-5, atol=1e-6)
    assert not list(tmp_path.rglob("*.so")) and not list(tmp_path.rglob("*.tmp*"))  # nothing half-written left

    monkeypatch.delenv("CC")
    if native._compiler() is None:
        return
    monkeypatch.setattr(native, "_loaded", {})
    kernels = native.interpolation_kernels()
    assert kernels is not None and kernels.path.parent == tmp_path / "native" and kernels.path.exists()
    built = kernels.path.stat().st_mtime_ns
    monkeypatch.setattr(native, "_loaded", {})  # a new process: loads the cached library, does not build it again
    assert native.interpolation_kernels().path == kernels.path and kernels.path.stat().st_mtime_ns == built


def test_an_index_outside_the_map_is_a_clear_error_on_every_path(native_path: str):
    """A voxel index outside the map (a caller that forgot to mask the points outside it) raises an error naming
    ``voxel_idx`` from the compiled kernel, never reads past its tables; the operators raise too."""
    from voxfusion.core.map.field import interpolate_unchecked

    vm, pts, idx, _ = _map_with_points_inside(8, 100, 50, seed=7)
    for bad in (-1, vm.n_voxels):
        wrong = idx.clone()
        wrong[3] = bad
        with pytest.raises((ValidationError, IndexError, RuntimeError)) as err:
            interpolate_unchecked(vm, pts, wrong)
        if native_path == "kernel":
            assert err.type is ValidationError and "voxel_idx" in str(err.value)


def test_a_new_kernel_build_deletes_that_kernels_oldest_libraries(tmp_path):
    """Every change to a C source (or the compiler, or the CPU) builds a new library under a new name, so a build
    keeps only that kernel's newest ``KEEP_LIBRARIES`` and removes build files a crashed build left; other kernels'
    libraries, a build running now and unrelated files stay."""
    import os
    import platform
    import time

    from voxfusion.core import native

    arch = platform.machine()
    now = time.time()

    def make(name: str, age_s: float) -> None:
        path = tmp_path / name
        path.write_bytes(b"\0")
        os.utime(path, (now - age_s, now - age_s))

    for i in range(6):  # interpolation-...-d0 is the newest
        make(f"interpolation-{arch}-d{i}.so", 100.0 * (i + 1))
    make(f"interpolation-{arch}-d0.abc.tmp.so", 3600.0)  # a build that died an hour ago
    make(f"interpolation-{arch}-d9.def.tmp.so", 1.0)  # a build running now
    make(f"band_losses-{arch}-old.so", 1e6)  # another kernel: not this prune's business
    make("notes.txt", 1e6)
    native.prune(tmp_path, "interpolation", keep=2)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([f"band_losses-{arch}-old.so", f"interpolation-{arch}-d0.so", f"interpolation-{arch}-d1.so",
                           f"interpolation-{arch}-d9.def.tmp.so", "notes.txt"])
    native.prune(tmp_path / "absent", "interpolation")  # no cache folder yet: nothing to do, no error


def test_building_a_kernel_prunes_its_older_builds_and_loads_the_new_one(monkeypatch, tmp_path):
    """The build path itself: with ``KEEP_LIBRARIES`` older libraries of the interpolation kernel in the cache, a
    fresh build leaves the new library and ``KEEP_LIBRARIES - 1`` of the old ones, and the kernel it returns works."""
    import os
    import platform

    from voxfusion.core import native
    from voxfusion.core.map.field import interpolate_reference, interpolate_unchecked

    if native._compiler() is None:
        pytest.skip("no C compiler: the interpolation kernel cannot be built here")
    monkeypatch.setenv("VOXFUSION_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(native.ENV_SWITCH, "1")
    monkeypatch.setattr(native, "_loaded", {})
    folder = tmp_path / "native"
    folder.mkdir()
    for i in range(native.KEEP_LIBRARIES):
        old = folder / f"interpolation-{platform.machine()}-old{i}.so"
        old.write_bytes(b"\0")
        os.utime(old, (1000 + i, 1000 + i))
    kernels = native.interpolation_kernels()
    assert kernels is not None and kernels.path.exists()
    left = sorted(p.name for p in folder.glob("interpolation-*.so"))
    expected = [f"interpolation-{platform.machine()}-old{i}.so" for i in range(1, native.KEEP_LIBRARIES)]
    assert left == sorted([kernels.path.name, *expected])
    vm, pts, idx, _ = _map_with_points_inside(8, 100, 200, seed=6)
    torch.testing.assert_close(interpolate_unchecked(vm, pts, idx), interpolate_reference(vm, pts, idx),
                               rtol=1e-5, atol=1e-6)
