"""Known-pose mapping on a tiny synthetic room: loose accuracy bounds, keyframes, checkpoints, exports."""

import numpy as np
import pytest
import torch
import trimesh

from voxfusion.core.checkpoint import load_checkpoint, save_checkpoint
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.datasets.transforms import TransformedCapture
from voxfusion.core.errors import CaptureError, ValidationError
from voxfusion.core.eval.mesh import MeshEvalConfig, compute_mesh_metrics, views_from_frames
from voxfusion.core.framedata import frame_to_device
from voxfusion.core.reconstruct import map_capture
from voxfusion.core.slam.mapping import Mapper
from voxfusion.core.slam.presets import load_preset

TINY = ["device=cpu", "mapping.rays_per_frame=256", "mapping.iters=5", "mapping.first_frame_iters=40",
        "field.sdf_hidden=64", "field.color_hidden=64", "mesh_res=4"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    cap = SyntheticCapture(SyntheticConfig(n_frames=6, width=96, height=72, seed=3))
    out = tmp_path_factory.mktemp("map")
    cfg = load_preset("cpu-small", TINY)
    return cap, cfg, map_capture(cap, cfg, out, progress=False)


def test_tiny_mapping_run_is_accurate_where_observed(tiny_run):
    cap, _, run = tiny_run
    assert len(run.mesh.faces) > 1000
    views = views_from_frames(list(cap.frames()))
    m = compute_mesh_metrics(run.mesh, cap.gt_mesh, MeshEvalConfig(n_samples=20000), views=views)
    # Loose bounds for 6 frames x few iterations (the benchmark targets 1.5 cm on 100 frames).
    assert m.accuracy_m < 0.03, m
    assert m.completion_m < 0.03, m
    assert m.completion_ratio > 0.9, m


def test_outputs_written(tiny_run):
    _, _, run = tiny_run
    out = run.out_dir
    for name in ("mesh.ply", "voxels.npz", "voxels.ply", "checkpoint.pt", "trajectory.txt", "timings.json"):
        assert (out / name).stat().st_size > 0, name
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert mesh.visual.vertex_colors.shape[0] == len(mesh.vertices)
    npz = np.load(out / "voxels.npz")
    assert npz["morton_codes"].shape[0] == run.mapper.voxels.n_voxels
    assert npz["voxel_vertex_ids"].shape == (run.mapper.voxels.n_voxels, 8)
    assert any(k.startswith("decoder/") for k in npz.files)


def test_checkpoint_round_trip_reproduces_mesh_exactly(tiny_run, tmp_path):
    _, cfg, run = tiny_run
    loaded = load_checkpoint(run.out_dir / "checkpoint.pt")
    assert loaded.config == run.config and run.config.mapping.optimize_poses is False
    assert loaded.keyframe_indices == [kf.data.index for kf in run.mapper.keyframes]
    np.testing.assert_allclose(loaded.trajectory.T_world_cam, run.trajectory.T_world_cam)
    again = loaded.mapper.extract_mesh(cfg.mesh_res)
    np.testing.assert_array_equal(again.vertices, run.mesh.vertices)
    np.testing.assert_array_equal(again.faces, run.mesh.faces)
    # and saving the loaded map again gives a loadable, identical map
    p = save_checkpoint(tmp_path / "again.pt", loaded.mapper, loaded.config)
    twice = load_checkpoint(p)
    assert torch.equal(twice.mapper.voxels.embeddings, loaded.mapper.voxels.embeddings)


def test_depth_only_checkpoint_round_trip(tmp_path):
    """A depth-only capture's map has no colour head; its checkpoint must load (the server resumes from it)."""
    cap = SyntheticCapture(SyntheticConfig(n_frames=2, width=48, height=36, seed=4))
    depth_only = TransformedCapture(cap, lambda f: f.with_(color=None))
    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=2", "mapping.iters=1"])
    run = map_capture(depth_only, cfg, tmp_path, progress=False)
    assert run.mapper.decoder.color_net is None
    loaded = load_checkpoint(run.out_dir / "checkpoint.pt")
    assert loaded.mapper.decoder.color_net is None
    np.testing.assert_array_equal(loaded.mapper.extract_mesh(cfg.mesh_res).vertices, run.mesh.vertices)


def test_corrupt_checkpoint_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CaptureError, match="bad.pt"):
        load_checkpoint(bad)
    with pytest.raises(CaptureError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")


def test_keyframe_rule_and_first_frame():
    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=1", "mapping.iters=1",
                                           "mapping.keyframe_max_interval=3", "mapping.keyframe_ratio=0.5"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=5, width=48, height=36))
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    frames = list(cap.frames())
    steps = [m.integrate(frame_to_device(f, "cpu"), f.T_world_cam) for f in frames[:4]]
    assert steps[0].is_keyframe and steps[0].observed_voxels == 0
    # nearby frames add few voxels (ratio < 0.5) so only the interval forces the next keyframe
    assert [s.is_keyframe for s in steps] == [True, False, False, True]
    # a frame seen from a far-away, unmapped place has a high new/observed ratio -> keyframe
    T = frames[4].T_world_cam.copy()
    T[:3, 3] += np.array([30.0, 0.0, 0.0])
    s = m.integrate(frame_to_device(frames[4], "cpu"), T)
    assert s.is_keyframe and s.new_voxels > 0 and s.observed_voxels == 0


def test_depth_only_capture_trains_without_colour(tmp_path):
    cap = SyntheticCapture(SyntheticConfig(n_frames=2, width=48, height=36, lidar=True))
    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=5", "mapping.iters=2"])

    class DepthOnly:
        name, path = "depth-only", tmp_path
        gt_mesh_path = None

        def __len__(self):
            return len(cap)

        def __getitem__(self, i):
            return cap[i].with_(color=None)

        def frames(self, start=0, stop=None, step=1):
            for i in range(*slice(start, stop, step).indices(len(cap))):
                yield self[i]

    run = map_capture(DepthOnly(), cfg, None, progress=False)
    assert run.mapper.decoder.config.use_color is False
    assert len(run.mesh.vertices) > 0


def test_window_with_a_colourless_frame_keeps_the_colour_term_of_the_others():
    """3D Scanner App exports photograph every third frame: a mapping window that mixes frames with and
    without colour trains colour on the rays that have it (it used to drop the colour term entirely)."""
    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=1", "mapping.iters=1",
                                           "mapping.keyframe_max_interval=1"])
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=2, width=48, height=36)).frames())
    frames[1] = frames[1].with_(color=None)
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    for f in frames:
        m.integrate(frame_to_device(f, "cpu"), f.T_world_cam)
    window = list(m.keyframes)
    assert len(window) == 2 and window[1].data.color is None and window[0].data.color is not None
    assert float(m.step(window).color.detach()) > 0
    assert float(m.step(window[1:]).color.detach()) == 0  # no frame with colour: no colour term


def test_window_rays_match_each_keyframes_own_rays_and_pose_gradients():
    """The batched window rays against the plain per-keyframe path (:meth:`Keyframe.pose` +
    :func:`camera_rays`, autograd through the exponential): same rays; the same delta gradients at
    ``delta = 0`` and within a relative O(|delta|) at corrections of a keyframe's usual size (the written-out
    backward takes the exponential's Jacobian as the identity), none for a fixed keyframe or without
    ``train_poses``."""
    from voxfusion.core.framedata import sample_pixels
    from voxfusion.core.render.volume import camera_rays
    from voxfusion.core.slam.mapping import Keyframe, window_rays

    frames = list(SyntheticCapture(SyntheticConfig(n_frames=3, width=48, height=36)).frames())
    window = [Keyframe.create(frame_to_device(f, "cpu"), torch.as_tensor(f.T_world_cam), fixed=i == 0)
              for i, f in enumerate(frames)]
    for i, kf in enumerate(window):  # non-zero corrections, different per keyframe
        kf.delta.data = torch.tensor([0.01, -0.02, 0.03, 0.02, -0.01, 0.015], dtype=torch.float64) * (i + 1)
    n = 17
    o, d, depth, colours = window_rays(window, n, torch.Generator().manual_seed(3), train_poses=True)
    gen = torch.Generator().manual_seed(3)
    ref = []
    for kf in window:
        px = sample_pixels(kf.data, n, gen)
        ref.append((camera_rays(kf.data.K, kf.pose() if not kf.fixed else kf.T_world_cam, px.uv), px))
    torch.testing.assert_close(o, torch.cat([r[0][0] for r in ref]), rtol=0, atol=1e-6)
    torch.testing.assert_close(d, torch.cat([r[0][1] for r in ref]), rtol=0, atol=1e-6)
    torch.testing.assert_close(depth, torch.cat([r[1].depth_m for r in ref]))
    assert all(torch.equal(c, r[1].color) for c, r in zip(colours, ref, strict=True))
    # the same loss through both paths: the same delta gradients (the fixed keyframe gets none)
    t = torch.linspace(0.5, 2.0, o.shape[0], dtype=torch.float32)
    weights = torch.tensor([0.3, -0.7, 1.1])

    def loss(origins, dirs):
        return ((origins + dirs * t[:, None]) * weights).sum()

    def delta_grads(scale: float) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        for i, kf in enumerate(window):
            kf.delta.data = torch.tensor([1, -2, 3, 2, -1, 1.5], dtype=torch.float64) * (i + 1) * scale
        o, d, _, _ = window_rays(window, n, torch.Generator().manual_seed(3), train_poses=True)
        gen = torch.Generator().manual_seed(3)
        rays = [camera_rays(kf.data.K, kf.pose(), sample_pixels(kf.data, n, gen).uv) for kf in window]
        o_ref, d_ref = (torch.cat([r[j] for r in rays]) for j in (0, 1))
        deltas = [kf.delta for kf in window[1:]]
        return (list(torch.autograd.grad(loss(o, d), deltas)),
                list(torch.autograd.grad(loss(o_ref, d_ref), deltas)))

    for scale, rtol in ((0.0, 1e-6), (1e-3, 1e-2)):  # corrections of 1-9 mm / mrad here
        grads, grads_ref = delta_grads(scale)
        for g, g_ref in zip(grads, grads_ref, strict=True):
            assert g.abs().max() > 0
            torch.testing.assert_close(g, g_ref, rtol=rtol, atol=rtol * float(g_ref.abs().max()))
    o, d, _, _ = window_rays(window, n, torch.Generator().manual_seed(3), train_poses=True)
    assert torch.autograd.grad(loss(o, d), [window[0].delta], allow_unused=True)[0] is None  # fixed
    o, d, _, _ = window_rays(window, n, torch.Generator().manual_seed(3), train_poses=False)
    assert not o.requires_grad and not d.requires_grad


def test_window_directions_batched_equal_each_keyframes_own():
    """The window's camera directions in one batch are each keyframe's :func:`camera_directions` to the bit, and a
    window whose frames differ in width (two captures' keyframes) takes the per-keyframe path."""
    from voxfusion.core.framedata import flat_uv
    from voxfusion.core.render.volume import camera_directions
    from voxfusion.core.slam.mapping import Keyframe, _window_directions

    def keyframes(width: int, height: int, n: int) -> list:
        frames = SyntheticCapture(SyntheticConfig(n_frames=n, width=width, height=height)).frames()
        return [Keyframe.create(frame_to_device(f, "cpu"), torch.as_tensor(f.T_world_cam)) for f in frames]

    g = torch.Generator().manual_seed(0)
    for window in (keyframes(48, 36, 3), keyframes(48, 36, 1) + keyframes(40, 30, 2)):
        flat = [kf.data.valid_idx[torch.randint(0, kf.data.n_valid, (23,), generator=g)] for kf in window]
        got = _window_directions(window, flat)
        want = torch.stack([camera_directions(kf.data.K, flat_uv(f, kf.data.width))
                            for kf, f in zip(window, flat, strict=True)])
        assert got.shape == (len(window), 23, 3) and got.dtype == torch.float64
        assert torch.equal(got, want)


def test_window_colours_mask_rays_without_colour():
    from voxfusion.core.slam.mapping import _window_colors

    depth = [torch.ones(3), torch.ones(2)]
    rgb = torch.rand(3, 3)
    colour, valid = _window_colors([rgb, None], depth)
    torch.testing.assert_close(colour[:3], rgb)
    assert colour.shape == (5, 3) and valid.tolist() == [True, True, True, False, False]
    assert _window_colors([rgb, rgb[:2]], depth)[1] is None
    assert _window_colors([None, None], depth) == (None, None)


def test_a_mapper_leaves_the_process_random_state_alone():
    """Sessions share a process: building one engine must not reseed torch's global generator."""
    cfg = load_preset("cpu-small", TINY)
    torch.manual_seed(1234)
    expected = torch.rand(4)
    torch.manual_seed(1234)
    a = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu", seed=7)
    torch.testing.assert_close(torch.rand(4), expected)
    b = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu", seed=7)
    for pa, pb in zip(a.decoder.parameters(), b.decoder.parameters(), strict=True):
        torch.testing.assert_close(pa, pb)  # still reproducible from the seed


def test_the_papers_voxel_sampler_still_maps_accurately(tiny_run):
    """``mapping.sampler: voxels`` (samples along the allocated voxels a ray crosses, the reference for the
    fixed-shape ``band`` default) meets the same bounds on the same frames."""
    cap, cfg, _ = tiny_run
    cfg = load_preset("cpu-small", TINY + ["mapping.sampler=voxels"])
    run = map_capture(cap, cfg, None, progress=False)
    m = compute_mesh_metrics(run.mesh, cap.gt_mesh, MeshEvalConfig(n_samples=20000),
                             views=views_from_frames(list(cap.frames())))
    assert m.accuracy_m < 0.03 and m.completion_m < 0.03 and m.completion_ratio > 0.9, m


def test_band_samples_is_validated_and_defaults_to_the_renderers_spacing():
    """``mapping.band_samples``: None (the built-in default) keeps the renderer's 2 cm spacing; the CPU sizes set
    5; anything below 1 is a typed error naming the key."""
    from voxfusion.core.errors import ConfigError

    assert load_preset("default", ["device=cpu"]).mapping.band_samples is None
    assert load_preset("cpu", []).mapping.band_samples == 5
    with pytest.raises(ConfigError, match="band_samples"):
        load_preset("cpu", ["mapping.band_samples=0"])


def test_alloc_stride_zero_picks_the_stride_from_the_image_width():
    """``mapping.alloc_stride``: 1 (the built-in default) keeps every pixel; the CPU sizes' 0 takes every pixel
    below 640 columns and every ``width // 320``-th from there; a negative stride is a typed error naming it."""
    from voxfusion.core.errors import ConfigError

    assert load_preset("default", ["device=cpu"]).mapping.stride_for(640) == 1
    cpu = load_preset("cpu", []).mapping
    assert [cpu.stride_for(w) for w in (256, 320, 639, 640, 1280, 1920)] == [1, 1, 1, 2, 4, 6]
    assert load_preset("cpu", ["mapping.alloc_stride=3"]).mapping.stride_for(320) == 3
    with pytest.raises(ConfigError, match="alloc_stride"):
        load_preset("cpu", ["mapping.alloc_stride=-1"])


def test_a_strided_frame_leaves_the_same_voxels_and_evidence_as_every_pixel():
    """Allocation from every 2nd pixel of a 640x480 frame: the same surface voxels as from every pixel (a 0.2 m
    voxel spans many pixels), and the hit evidence counts pixels, not points (each point is worth 4)."""
    from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
    from voxfusion.core.framedata import frame_to_device
    from voxfusion.core.reconstruct import make_mapper

    frame = SyntheticCapture(SyntheticConfig(n_frames=1, width=640, height=480))[0]
    maps = {}
    for stride in (1, 2, 0):  # 0: the CPU preset's rule, every 2nd pixel at 640 columns
        cfg = load_preset("cpu", TINY + [f"mapping.alloc_stride={stride}", "mapping.first_frame_iters=1"])
        mapper = make_mapper(cfg)
        mapper.integrate(frame_to_device(frame, "cpu"), frame.T_world_cam)
        maps[stride] = mapper.voxels
    one, two, auto = maps[1], maps[2], maps[0]
    assert two.n_voxels >= 0.97 * one.n_voxels and two.n_voxels <= one.n_voxels
    assert float(two.voxel_hits.sum()) == pytest.approx(float(one.voxel_hits.sum()), rel=0.05)
    assert auto.n_voxels == two.n_voxels and torch.equal(auto.voxel_hits, two.voxel_hits)


def test_published_keyframe_poses_follow_every_trained_keyframe_and_skip_the_others():
    """After mapping rounds that refine keyframe poses (fused Adam updates the corrections in place), every
    keyframe's published pose is its current pose; a publish with nothing moved recomputes nothing (the same
    arrays), and one after a round recomputes only the keyframes that round trained."""
    from voxfusion.core.slam.mapping import publish_keyframe_poses

    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=2", "mapping.iters=3",
                                           "mapping.keyframe_max_interval=1", "mapping.window_keyframes=1"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=5, width=48, height=36))
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    for f in cap.frames():
        m.integrate(frame_to_device(f, "cpu"), f.T_world_cam)
        publish_keyframe_poses(m.keyframes)
    assert len(m.keyframes) == 5
    moved = [kf for kf in m.keyframes if float(kf.delta.detach().abs().max()) > 1e-6]
    assert moved and not m.keyframes[0].delta.detach().any()  # poses were refined; the first stays fixed
    for kf in m.keyframes:
        np.testing.assert_allclose(kf.published_pose(), kf.T_world_cam.numpy(), rtol=0, atol=1e-12)
    before = [kf.published for kf in m.keyframes]
    publish_keyframe_poses(m.keyframes)
    assert all(kf.published is b for kf, b in zip(m.keyframes, before, strict=True))
    window = [m.keyframes[0], m.keyframes[2]]
    m.step(window)
    publish_keyframe_poses(m.keyframes)
    assert [kf.published is b for kf, b in zip(m.keyframes, before, strict=True)] == [True, True, False, True, True]
    np.testing.assert_allclose(m.keyframes[2].published_pose(), m.keyframes[2].T_world_cam.numpy(), atol=1e-12)


def test_a_keyframes_pose_before_its_first_publish_is_a_host_copy_of_the_pose_it_was_fused_with(monkeypatch):
    """Other threads read a keyframe's pose before the map that holds it is published (the tracker's reference
    keyframe, a trajectory): that is ``T_base_host``, copied where the keyframe was made (from the caller's host
    array, or from the device for a tensor), never ``T_base`` on the mapping thread's device stream."""
    from voxfusion.core.slam.mapping import Keyframe

    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=1", "mapping.iters=1"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=3, width=48, height=36))
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    frames = list(cap.frames())
    pose = frames[0].T_world_cam.astype(np.float32)  # any host array; kept as float64
    m.integrate(frame_to_device(frames[0], "cpu"), pose)
    kf = m.keyframes[0]
    assert kf.published is None and kf.T_base_host.dtype == np.float64
    np.testing.assert_array_equal(kf.T_base_host, kf.T_base.numpy())
    pose[:3, 3] += 1.0  # the caller's array is not kept
    assert not np.array_equal(kf.T_base_host, pose)

    def refuse(self):  # noqa: ANN001, ANN202
        raise AssertionError("a pose was read from the device tensor")

    monkeypatch.setattr(torch.Tensor, "cpu", refuse)
    np.testing.assert_array_equal(kf.published_pose(), kf.T_base_host)
    monkeypatch.undo()
    from_tensor = Keyframe.create(frame_to_device(frames[1], "cpu"), torch.as_tensor(frames[1].T_world_cam))
    np.testing.assert_array_equal(from_tensor.T_base_host, frames[1].T_world_cam)


def test_compiled_mapping_step_matches_the_eager_fixed_shape_step():
    """``mapping.compile``: the renderer and losses through ``torch.compile`` (forward and, through autograd, the
    backward pass) against the same step run eagerly on the fixed-shape path: two mappers fed the same frames with
    the same seed draw the same rays and jitter, and reach the same losses, map and keyframe poses."""
    import dataclasses

    from voxfusion.core.slam.mapping import COMPILED_BAND_LOSS

    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=2", "mapping.iters=2",
                                           "mapping.keyframe_max_interval=1", "mapping.compact_samples=false"])
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=3, width=48, height=36)).frames())
    mappers = []
    for compiled in (False, True):
        mapping = dataclasses.replace(cfg.mapping, compile=compiled)
        m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, mapping, "cpu", seed=5)
        losses = [m.integrate(frame_to_device(f, "cpu"), f.T_world_cam).loss for f in frames]
        mappers.append((m, losses))
    (eager, eager_losses), (comp, comp_losses) = mappers
    assert COMPILED_BAND_LOSS._compiled is not None and not COMPILED_BAND_LOSS.failed
    assert len(comp.keyframes) == 3 and not comp.keyframes[2].fixed  # the window trained a pose too
    np.testing.assert_allclose(comp_losses, eager_losses, rtol=1e-4)
    torch.testing.assert_close(comp.voxels.embeddings, eager.voxels.embeddings, rtol=1e-4, atol=1e-6)
    for a, b in zip(comp.decoder.parameters(), eager.decoder.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    for a, b in zip(comp.keyframes, eager.keyframes, strict=True):
        torch.testing.assert_close(a.delta, b.delta, rtol=1e-3, atol=1e-9)
    assert float(comp.keyframes[2].delta.detach().abs().max()) > 0  # ... and it moved


def _by_code(vm, values: torch.Tensor) -> dict[int, object]:
    """Per-voxel values keyed by the voxel's Morton code (maps that numbered their voxels differently)."""
    return {int(c): v for c, v in zip(vm.voxel_codes.tolist(), values.tolist(), strict=True)}


def test_fusing_frames_in_one_batch_is_fusing_them_in_turn():
    """A realtime mapper fuses the frames it caught up on in one pass (Mapper.integrate_batch): the same keyframe
    decisions and counts, voxels, surface marks and hit evidence as fusing them one by one; each frame's rays add
    free-space evidence to the batch's later voxels too (never less than in turn); only the last frame is optimised."""
    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=1", "mapping.iters=1",
                                           "mapping.keyframe_max_interval=3", "mapping.keyframe_ratio=0.05"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=12, width=48, height=36))
    frames = [(frame_to_device(f, "cpu"), f.T_world_cam) for f in cap.frames()]
    turn = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    batch = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    one_by_one = [turn.integrate(f, T, optimize=False) for f, T in frames[:-1]] + [turn.integrate(*frames[-1])]
    together = batch.integrate_batch(frames[:1])
    before = {int(c) for c in batch.voxels.voxel_codes.tolist()}
    together += batch.integrate_batch(frames[1:3], optimize=False)
    together += batch.integrate_batch(frames[3:])
    for a, b in zip(one_by_one, together, strict=True):
        assert (a.is_keyframe, a.new_voxels, a.observed_voxels, a.iterations) == \
               (b.is_keyframe, b.new_voxels, b.observed_voxels, b.iterations)
    assert [s.iterations > 0 for s in together] == [True] + [False] * 10 + [True]
    assert any(s.is_keyframe for s in together[3:-1]) and any(s.new_voxels for s in together[3:])
    assert len(turn.keyframes) == len(batch.keyframes)
    a, b = turn.voxels, batch.voxels
    assert sorted(a.voxel_codes.tolist()) == sorted(b.voxel_codes.tolist())
    assert not torch.equal(a.voxel_codes, b.voxel_codes)  # numbered in one Morton order, not frame by frame
    assert _by_code(a, a.voxel_hits) == _by_code(b, b.voxel_hits)
    assert _by_code(a, a.voxel_surface.to(torch.int64)) == _by_code(b, b.voxel_surface.to(torch.int64))
    free_a, free_b = _by_code(a, a.voxel_free), _by_code(b, b.voxel_free)
    assert all(free_b[c] >= free_a[c] for c in free_a)
    assert all(free_b[c] == free_a[c] for c in before)  # voxels that existed before the batches: the same rays
    assert sum(free_b.values()) > sum(free_a.values())


def test_a_long_batch_is_fused_in_bounded_passes_and_frames_of_other_sizes_alone(monkeypatch):
    from voxfusion.core.slam import mapping

    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=1", "mapping.iters=1"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=8, width=48, height=36))
    frames = [(frame_to_device(f, "cpu"), f.T_world_cam) for f in cap.frames()]
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    passes = []
    real = mapping.Mapper.integrate_batch

    def spy(self, fs, optimize=True):
        passes.append((len(fs), optimize))
        return real(self, fs, optimize)

    monkeypatch.setattr(mapping, "FUSE_BATCH_MAX", 3)
    monkeypatch.setattr(mapping.Mapper, "integrate_batch", spy)
    steps = m.integrate_batch(frames)
    assert [s.frame_index for s in steps] == [f.index for f, _ in frames]
    assert [s.iterations > 0 for s in steps] == [True] + [False] * 6 + [True]
    # the first frame alone, then passes of at most 3, only the last optimised
    assert passes[0] == (8, True) and (1, False) in passes and all(n <= 3 for n, _ in passes[1:] if n != 7)
    assert [opt for n, opt in passes[1:] if n <= 3] == [False] * (len(passes) - 2) + [True]
    with pytest.raises(ValidationError):
        m.integrate_batch([])


def test_a_mapping_iterations_fast_paths_give_the_plain_operators_gradients(monkeypatch):
    """One mapping iteration (the band sampler, compact samples, a window whose poses train) with the CPU's fast
    paths - the fused compositing and losses (:func:`~voxfusion.core.losses.band_losses`) and the compiled
    interpolation kernel - against the plain operators through autograd: the same loss, and the same gradients
    for the embeddings, the decoder and the keyframe poses, to float32 rounding."""
    from voxfusion.core import native
    from voxfusion.core.render.volume import band_jitter, band_sample_count
    from voxfusion.core.slam.mapping import _window_colors, band_loss, window_rays

    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=5", "mapping.iters=2",
                                           "mapping.keyframe_max_interval=1"])
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=4, width=64, height=48)).frames())
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu", seed=2)
    for f in frames:
        m.integrate(frame_to_device(f, "cpu"), f.T_world_cam)
    window = list(m.keyframes)
    for kf in window[1:]:  # corrections of a keyframe's usual size
        kf.delta.data = torch.tensor([1.0, -2.0, 1.5, 0.5, -1.0, 2.0], dtype=torch.float64) * 1e-3
    n_band, k = band_sample_count(cfg.render, cfg.voxel_size_m, cfg.mapping.free_samples, cfg.mapping.band_samples)
    results = {}
    for fast in (True, False):
        monkeypatch.setenv(native.ENV_SWITCH, "1" if fast else "0")
        built = (native.interpolation_kernels(), native.band_loss_kernels())
        if fast and native._compiler() is not None and None in built:
            pytest.fail("a C compiler is here but core/native/*.c did not build")
        gen = torch.Generator().manual_seed(7)
        o, d, depth, colours = window_rays(window, 64, gen, train_poses=True)
        color_gt, color_valid = _window_colors(colours, list(depth.split(64)))
        jitter = band_jitter(o.shape[0], k, o.device, torch.float32, gen)
        total = band_loss(m.voxels, m.decoder, o, d, depth, color_gt, color_valid, jitter, cfg.render, cfg.loss,
                          cfg.mapping.free_samples, cfg.mapping.free_range_voxels * cfg.voxel_size_m, n_band,
                          compact=True, fused=fast)[0]
        params = [m.voxels.embeddings, *m.decoder.parameters(), *(kf.delta for kf in window[1:])]
        results[fast] = (total.detach(), torch.autograd.grad(total, params))
    (fast_total, fast_grads), (ref_total, ref_grads) = results[True], results[False]
    torch.testing.assert_close(fast_total, ref_total, rtol=1e-5, atol=0)
    for fast, ref in zip(fast_grads, ref_grads, strict=True):
        scale = float(ref.abs().max())
        assert scale > 0
        torch.testing.assert_close(fast, ref, rtol=1e-3, atol=1e-4 * scale)


def _three_keyframe_mapper(warmup: int) -> Mapper:
    """A mapper holding three keyframes (the first fixed) and no optimiser steps taken yet."""
    cfg = load_preset("cpu-small", TINY + ["mapping.first_frame_iters=2", "mapping.keyframe_max_interval=1",
                                           "mapping.lr_pose=1e-3", f"mapping.pose_warmup_steps={warmup}"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=3, width=48, height=36))
    m = Mapper(cfg.voxel_size_m, cfg.field, cfg.render, cfg.loss, cfg.mapping, "cpu")
    for f in cap.frames():
        m.integrate(frame_to_device(f, "cpu"), f.T_world_cam, optimize=False)
    assert len(m.keyframes) == 3 and m.pose_optimizer is None
    return m


def test_a_frames_pose_steps_warm_up_to_lr_pose_counted_per_frame():
    """With ``pose_warmup_steps`` W, a frame's k-th pose step runs at ``lr_pose * k / W`` (then ``lr_pose``), counted
    over the steps that train that frame only; Adam's first step moves every coordinate of a correction by exactly
    its learning rate (bias correction), so the first move is ``lr_pose / W``, and ``lr_pose`` without warm-up."""
    for warmup, first_move in ((4, 1e-3 / 4), (0, 1e-3)):
        m = _three_keyframe_mapper(warmup)
        kf0, kf1, kf2 = m.keyframes
        m.step([kf0, kf1])
        moved = kf1.delta.detach().abs()
        np.testing.assert_allclose(moved[moved > 0], first_move, rtol=1e-6)
        assert moved.count_nonzero() >= 5 and not kf2.delta.detach().any()
        if not warmup:
            continue
        rates = []
        for _ in range(5):
            m.step([kf0, kf1])
            (g1,) = [g for g in m.pose_optimizer.param_groups if g["params"][0] is kf1.delta]
            rates.append(g1["lr"])
        np.testing.assert_allclose(rates, [0.5e-3, 0.75e-3, 1e-3, 1e-3, 1e-3])
        m.step([kf0, kf2])  # kf2's first step: its own count, at a quarter of the rate; kf1's untouched
        (g1,) = [g for g in m.pose_optimizer.param_groups if g["params"][0] is kf1.delta]
        (g2,) = [g for g in m.pose_optimizer.param_groups if g["params"][0] is kf2.delta]
        assert (g1["pose_steps"], g2["pose_steps"], g2["lr"]) == (6, 1, 0.25e-3)


def test_pose_warmup_steps_is_validated():
    from voxfusion.core.errors import ConfigError

    with pytest.raises(ConfigError, match="pose_warmup_steps"):
        load_preset("cpu-small", TINY + ["mapping.pose_warmup_steps=-1"])
