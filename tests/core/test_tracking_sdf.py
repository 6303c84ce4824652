"""The geometric (point-to-SDF) tracker: Jacobians against autograd, perturbation recovery on the synthetic
room and on real 7-Scenes frames, lost-frame detection, and the render tracker beside it."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from rooms import mapped_room  # tests/core/rooms.py

from voxfusion.core.datasets import open_capture
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import ConfigError, ValidationError
from voxfusion.core.framedata import FrameData, frame_to_device
from voxfusion.core.lie import perturb_right, se3_exp
from voxfusion.core.reconstruct import make_mapper
from voxfusion.core.slam import tracking_sdf
from voxfusion.core.slam.presets import load_preset
from voxfusion.core.slam.tracking import Tracker, TrackingConfig, masked_median
from voxfusion.core.slam.tracking_sdf import (
    SdfSolverConfig,
    depth_reference,
    frame_residuals,
    gaussian_blur,
    gray_images,
    linearize,
    photometric_residuals,
    sample_points,
)

TINY = ["device=cpu", "mapping.map_every=1", "mapping.rays_per_frame=192", "mapping.iters=8",
        "mapping.first_frame_iters=40", "field.sdf_hidden=64", "field.color_hidden=64"]


def pose_error(T_a, T_b):
    dt = np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])
    R = T_a[:3, :3].T @ T_b[:3, :3]
    return dt, np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def perturb(T, scale=1.0):
    xi = torch.tensor([0.03, -0.02, 0.025, np.deg2rad(2.0), np.deg2rad(-1.5), np.deg2rad(1.0)], dtype=torch.float64)
    return T @ se3_exp(xi * scale).numpy()


@pytest.fixture(scope="module")
def room():
    return mapped_room("cpu-small", TINY)


def tracker_for(cfg, mapper, use_color=True, **kw):
    tr = Tracker(TrackingConfig(**kw), cfg.render, use_color=use_color)
    tr.set_map(mapper.voxels.snapshot(), mapper.decoder)
    return tr


def test_normal_equations_match_autograd_jacobian(room):
    """H = J^T W J and b = J^T W r with the analytic J = [R^T g, p x R^T g] equal the ones built from
    autograd's Jacobian of sdf(T exp(xi) p) with respect to xi at xi = 0."""
    cap, cfg, mapper = room
    f = cap[6]
    data = frame_to_device(f, "cpu")
    pts = sample_points(data, 256, torch.Generator().manual_seed(0))
    T = torch.as_tensor(perturb(f.T_world_cam, 0.3))
    scfg = SdfSolverConfig(huber_m=1.0, max_residual_m=0.08)  # huber 1 m: all weights 1 (plain least squares)
    cost, H, b, r, ok = linearize(mapper.voxels, mapper.decoder, pts, T, scfg)
    assert int(ok.sum()) > 100

    from voxfusion.core.map.field import query

    def residuals(xi):
        Tx = perturb_right(T, xi)
        x = pts.p_cam.to(torch.float64) @ Tx[:3, :3].T + Tx[:3, 3]
        sdf, _, _ = query(mapper.voxels, mapper.decoder, x.to(torch.float32))
        return sdf.to(torch.float64)

    J = torch.autograd.functional.jacobian(residuals, torch.zeros(6, dtype=torch.float64))[ok]  # [K, 6]
    r_ref = residuals(torch.zeros(6, dtype=torch.float64))[ok]
    n = pts.p_cam.shape[0]
    torch.testing.assert_close(r[ok].to(torch.float64), r_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(H, J.T @ J / n, rtol=2e-3, atol=1e-5)
    torch.testing.assert_close(b, J.T @ r_ref / n, rtol=2e-3, atol=1e-6)


def plane_frame(h=48, w=64, normal=(0.3, -0.2, -1.0), dist=2.0):
    """A depth image of the plane ``n . X = -dist`` (unit ``n`` facing the camera), its ``n`` and ``K``."""
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    K = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    z = -dist / (rays @ n)
    data = FrameData(0, 0.0, torch.as_tensor(z, dtype=torch.float32), None, torch.as_tensor(K),
                     torch.arange(h * w))
    return data, n, K


def test_frame_residuals_on_a_tilted_plane():
    """Against a plane's own depth: normals equal the plane's, a point moved by d along the normal has residual
    d, and the world gradient is the (world) normal, whatever the reference's pose."""
    data, n, K = plane_frame()
    T_ref = perturb(np.eye(4), 2.0)  # any pose: the residual is measured in the reference camera
    ref = depth_reference(data, T_ref)
    gen = torch.Generator().manual_seed(0)
    idx = torch.randint(0, data.depth_m.numel(), (500,), generator=gen)
    z = data.depth_m.reshape(-1)[idx].to(torch.float64)
    u, v = (idx % data.width).to(torch.float64), (idx // data.width).to(torch.float64)
    on_plane = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    d = torch.linspace(-0.03, 0.03, 500, dtype=torch.float64)
    p_cam = (on_plane + d[:, None] * torch.as_tensor(n)).to(torch.float32)  # in the reference camera
    r, g_world, ok = frame_residuals(ref, p_cam, torch.as_tensor(T_ref), max_dist_m=0.05)
    assert int(ok.sum()) > 400  # all but the points projected off the image or onto its 2-pixel border
    torch.testing.assert_close(r[ok].to(torch.float64), d[ok], atol=2e-4, rtol=0)
    n_world = torch.as_tensor(T_ref[:3, :3] @ n, dtype=torch.float32)
    torch.testing.assert_close(g_world[ok], n_world.expand(int(ok.sum()), 3), atol=1e-3, rtol=0)
    # pairs further apart than max_dist_m are not associated
    assert not frame_residuals(ref, p_cam, torch.as_tensor(T_ref), max_dist_m=0.01)[2][d.abs() > 0.012].any()


def test_frame_term_normal_equations_match_autograd_jacobian(room):
    """With a reference frame, H and b add the frame-to-frame term's J^T W J and J^T W r, J from autograd of
    the point-to-plane residuals (the association is held fixed: it is not differentiated)."""
    cap, cfg, mapper = room
    f, f_ref = cap[7], cap[6]
    data = frame_to_device(f, "cpu")
    ref = depth_reference(frame_to_device(f_ref, "cpu"), f_ref.T_world_cam)
    pts = sample_points(data, 256, torch.Generator().manual_seed(0))
    T = torch.as_tensor(perturb(f.T_world_cam, 0.1))
    w = 2.0
    plain = SdfSolverConfig(huber_m=1.0, max_residual_m=0.08)
    both = SdfSolverConfig(huber_m=1.0, max_residual_m=0.08, w_frame=w, frame_max_m=0.05)
    _, H0, b0, _, _ = linearize(mapper.voxels, mapper.decoder, pts, T, plain)
    _, H1, b1, _, _ = linearize(mapper.voxels, mapper.decoder, pts, T, both, ref)
    _, _, ok = frame_residuals(ref, pts.p_cam, T, 0.05)
    assert int(ok.sum()) > 100

    def residuals(xi):
        return w * frame_residuals(ref, pts.p_cam.to(torch.float64), perturb_right(T, xi), 0.05)[0][ok]

    J = torch.autograd.functional.jacobian(residuals, torch.zeros(6, dtype=torch.float64))
    r = residuals(torch.zeros(6, dtype=torch.float64))
    n = pts.p_cam.shape[0]
    torch.testing.assert_close(H1 - H0, J.T @ J / n, rtol=2e-3, atol=1e-5)
    torch.testing.assert_close(b1 - b0, J.T @ r / n, rtol=2e-3, atol=1e-6)


def test_older_frames_stack_newest_first_with_fixed_shapes():
    """``with_older_frames`` keeps the last ``count`` references before the newest, newest first, the oldest dropped;
    slots not filled yet are zero depth at weight 0, so the stack's shapes never change; another image size starts
    afresh."""
    cap = SyntheticCapture(SyntheticConfig(n_frames=6, width=48, height=36, seed=2))
    refs = [depth_reference(frame_to_device(f, "cpu"), f.T_world_cam) for f in cap.frames(0, 5)]
    stacked = tracking_sdf.with_older_frames(refs[0], None, 3, 0.5)
    assert stacked.older_depth.shape == (3, *refs[0].depth_padded.shape)
    assert torch.equal(stacked.older_weights, torch.zeros(3, dtype=torch.float64))
    assert not stacked.older_depth.any()
    for k in range(1, 5):
        stacked = tracking_sdf.with_older_frames(refs[k], stacked, 3, 1.0 / k)
        assert stacked.older_depth.shape == (3, *refs[0].depth_padded.shape)
        filled = min(k, 3)
        expected = torch.tensor([1.0 / k] * filled + [0.0] * (3 - filled), dtype=torch.float64)
        torch.testing.assert_close(stacked.older_weights, expected, rtol=0, atol=0)
        for slot in range(filled):  # slot 0: the frame before the newest
            older = refs[k - 1 - slot]
            assert torch.equal(stacked.older_depth[slot], older.depth_padded)
            assert torch.equal(stacked.T_older_world[slot], older.T_ref_world)
    assert torch.equal(stacked.depth_padded, refs[4].depth_padded)
    small = SyntheticCapture(SyntheticConfig(n_frames=1, width=32, height=24, seed=2))[0]
    fresh = tracking_sdf.with_older_frames(depth_reference(frame_to_device(small, "cpu"), small.T_world_cam),
                                           stacked, 3, 1.0)
    assert fresh.older_depth.shape == (3, 28, 36) and not fresh.older_weights.any()


def test_older_frames_residuals_and_normal_equations_are_each_references_own(room):
    """Against a reference with older frames, the point-to-plane residuals are those against each frame on its own
    (the batched association against the one-reference one), and H and b add each older frame's own term at its
    weight: H(newest + older) - H(newest) = sum_k w_k (H(older k alone) - H(map only)); an empty slot adds nothing."""
    cap, cfg, mapper = room
    f = cap[7]
    data = frame_to_device(f, "cpu")
    refs = [depth_reference(frame_to_device(cap[k], "cpu"), cap[k].T_world_cam) for k in (4, 5, 6)]
    stacked = tracking_sdf.with_older_frames(refs[1], tracking_sdf.with_older_frames(refs[0], None, 3, 1.0), 3, 1.0)
    stacked = tracking_sdf.with_older_frames(refs[2], stacked, 3, 0.5)  # 6 newest; older 5, 4 at 0.5; one empty
    pts = sample_points(data, 256, torch.Generator().manual_seed(0))
    T = torch.as_tensor(perturb(f.T_world_cam, 0.1))
    n = pts.p_cam.shape[0]
    r, g, ok = frame_residuals(stacked, pts.p_cam, T, 0.05)
    assert r.shape == (4 * n,) and g.shape == (4 * n, 3)
    for slot, ref in enumerate((refs[2], refs[1], refs[0])):
        r1, g1, ok1 = frame_residuals(ref, pts.p_cam, T, 0.05)
        assert int(ok1.sum()) > 100
        assert torch.equal(ok[slot * n:(slot + 1) * n], ok1)
        torch.testing.assert_close(r[slot * n:(slot + 1) * n][ok1], r1[ok1], rtol=0, atol=1e-6)
        torch.testing.assert_close(g[slot * n:(slot + 1) * n][ok1], g1[ok1], rtol=0, atol=1e-6)
    assert not ok[3 * n:].any()  # the empty slot associates nothing
    torch.testing.assert_close(tracking_sdf.frame_weights(stacked, 2),
                               torch.tensor([1, 1, 0.5, 0.5, 0.5, 0.5, 0, 0], dtype=torch.float64))
    frame = SdfSolverConfig(huber_m=0.01, max_residual_m=0.08, w_frame=2.0, frame_max_m=0.05)
    plain = replace(frame, w_frame=0.0)

    def normal_equations(scfg, ref):
        cost, H, b, _, _ = linearize(mapper.voxels, mapper.decoder, pts, T, scfg, ref)
        return cost, H, b

    base = normal_equations(plain, None)
    newest = normal_equations(frame, refs[2])
    both = normal_equations(frame, stacked)
    # each older reference at half the weight: at half the Huber scale and cap too, so its whole term scales by 0.5^2
    halved = replace(frame, w_frame=frame.w_frame * 0.5)
    for a, b_, c0, c1, c2 in zip(both, newest, base, normal_equations(halved, refs[1]),
                                 normal_equations(halved, refs[0]), strict=True):
        torch.testing.assert_close(a - b_, (c1 - c0) + (c2 - c0), rtol=1e-6, atol=1e-9)


def test_tracker_keeps_older_frames_at_a_fading_weight(room):
    """``sdf_frame_refs`` older references follow the accepted frames at ``min(1, fade / n)`` until that falls below
    ``FRAME_REFS_MIN_WEIGHT``; with 0 there are none;
    relocalisation against a keyframe (``referenced_to``) compares with that keyframe alone and puts the history
    back."""
    cap, cfg, mapper = room
    tr = tracker_for(cfg, mapper, method="sdf", sdf_frame_refs=2, sdf_frame_refs_fade=2)
    for k in range(4):
        tr.remember(frame_to_device(cap[k], "cpu"), cap[k].T_world_cam)
        filled = min(k, 2)
        weight = min(1.0, 2 / (k + 1))
        expected = torch.tensor([weight] * filled + [0.0] * (2 - filled), dtype=torch.float64)
        torch.testing.assert_close(tr._reference.older_weights, expected, rtol=0, atol=1e-12)
    saved = tr._reference
    with tr.referenced_to(frame_to_device(cap[0], "cpu"), cap[0].T_world_cam):
        assert not tr._reference.older_weights.any()
    assert tr._reference is saved and tr._accepted == 4
    for k in range(4, 9):  # the weight falls to 2 / 8 = FRAME_REFS_MIN_WEIGHT at the 8th frame, below it at the 9th
        f = cap[k % 8]
        tr.remember(frame_to_device(f, "cpu"), f.T_world_cam)
        assert (tr._reference.older_depth is None) == (k == 8)
    plain = tracker_for(cfg, mapper, method="sdf", sdf_frame_refs=0)
    plain.remember(frame_to_device(cap[0], "cpu"), cap[0].T_world_cam)
    plain.remember(frame_to_device(cap[1], "cpu"), cap[1].T_world_cam)
    assert plain._reference.older_depth is None


def test_older_frames_track_a_perturbed_frame(room):
    """With three older references the tracker still recovers a known perturbation (the same test as without)."""
    cap, cfg, mapper = room
    tr = tracker_for(cfg, mapper, method="sdf", sdf_frame_refs=3)
    for k in (3, 4, 5):
        tr.remember(frame_to_device(cap[k], "cpu"), cap[k].T_world_cam)
    f = cap[6]
    out = tr.track(frame_to_device(f, "cpu"), perturb(f.T_world_cam))
    dt, dr = pose_error(out.T_world_cam, f.T_world_cam)
    assert not out.lost and dt < 0.01 and dr < 0.5, (dt, dr)


def test_frame_term_sharpens_tracking_on_a_coarse_map():
    """A map given 5 optimisation rounds is too blurred to place a frame well; the previous frame's depth
    (``remember``) is not. Same frame, prior and sampled points, with and without the term."""
    cap = SyntheticCapture(SyntheticConfig(n_frames=8, width=96, height=72, seed=5))
    cfg = load_preset("cpu-small", ["device=cpu", "mapping.first_frame_iters=5", "field.sdf_hidden=64",
                                    "field.color_hidden=64"])
    mapper = make_mapper(cfg)
    mapper.integrate(frame_to_device(cap[0], "cpu"), cap[0].T_world_cam)
    f, prev = cap[2], cap[1]
    errors = {}
    for w in (0.0, 2.0):
        tr = Tracker(TrackingConfig(method="sdf", sdf_w_frame=w), cfg.render, use_color=False)
        tr.set_map(mapper.voxels.snapshot(), mapper.decoder)
        tr.remember(frame_to_device(prev, "cpu"), prev.T_world_cam)
        assert (tr._reference is None) == (w == 0)  # nothing is kept without the term
        res = tr.track(frame_to_device(f, "cpu"), perturb(f.T_world_cam, 0.3))
        errors[w] = pose_error(res.T_world_cam, f.T_world_cam)
    assert errors[2.0][0] < 0.004 and errors[2.0][1] < 0.2, errors
    assert errors[2.0][0] < 0.5 * errors[0.0][0], errors


def wall_frame(t_cam, h=72, w=96, f=80.0, wall_z=2.07, period_m=0.3, amplitude=0.35, fine_period_m=None,
               fine_amplitude=0.15):
    """An RGB-D frame of the textured wall ``Z = wall_z`` (world; not on a voxel face) seen by a camera moved
    by ``t_cam`` (no rotation; OpenCV axes, so the camera looks along +Z). The wall's gray level is a smooth checker of
    period 0.3 m in world X and Y (~12 pixels; ``period_m``, ``amplitude``): depth alone cannot tell where along
    the wall the camera is. With ``fine_period_m`` a finer checker (``fine_amplitude``) lies on top of it."""
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.full((h, w), wall_z - t_cam[2])
    X = (u - K[0, 2]) / f * z + t_cam[0]
    Y = (v - K[1, 2]) / f * z + t_cam[1]
    gray = 0.5 + amplitude * np.sin(2 * np.pi * X / period_m) * np.sin(2 * np.pi * Y / period_m)
    if fine_period_m is not None:
        gray = gray + fine_amplitude * np.sin(2 * np.pi * X / fine_period_m) * np.sin(2 * np.pi * Y / fine_period_m)
    color = np.repeat((gray * 255).round().astype(np.uint8)[..., None], 3, -1)
    T = np.eye(4)
    T[:3, 3] = t_cam
    return RGBDFrame(depth_m=z.astype(np.float32), K=K, timestamp_s=0.0, color=color, T_world_cam=T)


def test_photometric_residuals_on_a_ramp():
    """Against a gray ramp on a fronto-parallel wall: a point moved along x by d (image shift f d / z pixels)
    has residual slope * f d / z, its world gradient is the ramp's slope through the projection, and points
    in front of the reference's surface (occluders) are not used."""
    h, w, f, z0, slope = 48, 64, 50.0, 2.0, 0.01  # gray = 0.2 + slope * u
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    color = torch.as_tensor(np.repeat((0.2 + slope * u)[..., None], 3, -1), dtype=torch.float32)
    data = FrameData(0, 0.0, torch.full((h, w), z0), color, torch.as_tensor(K), torch.arange(h * w))
    ref = depth_reference(data, np.eye(4), images=gray_images(data.color))
    uu, vv = torch.meshgrid(torch.arange(8.0, w - 8), torch.arange(8.0, h - 8), indexing="xy")
    uu, vv = uu.reshape(-1), vv.reshape(-1)
    p_cam = torch.stack([(uu - K[0, 2]) / f * z0, (vv - K[1, 2]) / f * z0, torch.full_like(uu, z0)], -1)
    gray = 0.2 + slope * uu
    for d in (0.0, 0.013, -0.021):  # metres along x: 0, 0.33 and -0.53 pixels
        T = torch.eye(4, dtype=torch.float64)
        T[0, 3] = d
        r, g_world, ok = photometric_residuals(ref, p_cam, gray, T, max_dist_m=0.05)
        assert bool(ok.all())
        torch.testing.assert_close(r, torch.full_like(r, slope * f * d / z0), atol=1e-5, rtol=0)
        torch.testing.assert_close(g_world[:, 0], torch.full_like(r, slope * f / z0), atol=1e-5, rtol=0)
        torch.testing.assert_close(g_world[:, 1], torch.zeros_like(r), atol=1e-5, rtol=0)
    in_front = p_cam * 0.9  # same pixels, 0.2 m nearer than the reference's surface
    assert not photometric_residuals(ref, in_front, gray, torch.eye(4, dtype=torch.float64), 0.05)[2].any()


def photometric_setup(room, n_points, perturbation):
    """The room's map, frame 6 as the reference (with gray images), frame 7's points (with gray levels) and a
    pose ``perturbation`` x :func:`perturb` away from frame 7's."""
    cap, _, mapper = room
    f, f_ref = cap[7], cap[6]
    ref_data = frame_to_device(f_ref, "cpu")
    ref = depth_reference(ref_data, f_ref.T_world_cam, images=gray_images(ref_data.color))
    pts = sample_points(frame_to_device(f, "cpu"), n_points, torch.Generator().manual_seed(0), with_gray=True)
    return mapper, ref, pts, torch.as_tensor(perturb(f.T_world_cam, perturbation))


def test_photometric_term_normal_equations_match_autograd_jacobian(room):
    """The photometric term adds J^T W J and J^T W r, J from autograd of the bilinear-interpolated residuals
    (the 2x2 cell each point falls in and the occlusion test are held fixed)."""
    mapper, ref, pts, T = photometric_setup(room, n_points=256, perturbation=0.05)
    w = 0.5
    plain = SdfSolverConfig(huber_m=1.0, max_residual_m=0.08)
    both = SdfSolverConfig(huber_m=1.0, max_residual_m=0.08, w_photo=w, huber_photo=100.0)  # Huber off
    _, H0, b0, _, _ = linearize(mapper.voxels, mapper.decoder, pts, T, plain, ref)
    _, H1, b1, _, _ = linearize(mapper.voxels, mapper.decoder, pts, T, both, ref)
    _, _, ok = photometric_residuals(ref, pts.p_cam, pts.gray, T, 0.05)
    assert int(ok.sum()) > 100

    def residuals(xi):
        return w * photometric_residuals(ref, pts.p_cam.to(torch.float64), pts.gray.to(torch.float64),
                                         perturb_right(T, xi), 0.05)[0][ok]

    J = torch.autograd.functional.jacobian(residuals, torch.zeros(6, dtype=torch.float64))
    r = residuals(torch.zeros(6, dtype=torch.float64))
    n = pts.p_cam.shape[0]
    assert float(J.abs().max()) > 0
    torch.testing.assert_close(H1 - H0, J.T @ J / n, rtol=2e-3, atol=1e-5)
    torch.testing.assert_close(b1 - b0, J.T @ r / n, rtol=2e-3, atol=1e-6)


def test_photometric_term_finds_motion_along_a_textured_wall():
    """Sliding along a flat wall changes neither the map's SDF nor the previous frame's depth, so geometry
    alone cannot tell where along the wall the camera went: from the same prior it ends at the same pose
    whatever the motion (the map's rim decides where); the wall's texture (``sdf_w_photo``, against the
    previous frame's image) follows each motion."""
    cfg = load_preset("cpu-small", TINY)
    prev = wall_frame(np.zeros(3))
    motions = (np.array([0.012, -0.008, 0.0]), np.array([-0.015, 0.006, 0.0]))  # 29 mm apart
    mapper = make_mapper(cfg)
    mapper.integrate(frame_to_device(prev, "cpu"), prev.T_world_cam)
    ends = {}
    for w in (0.0, 0.1):
        for k, t_cam in enumerate(motions):  # a fresh tracker each: the same sampled pixels for both motions
            # the sharp term alone (the blurred stage before it: test_blurred_photometric_stage_widens_the_basin)
            tr = tracker_for(cfg, mapper, method="sdf", sdf_w_photo=w, sdf_w_photo_blur=0.0)
            tr.remember(frame_to_device(prev, "cpu"), prev.T_world_cam)
            assert (tr._reference.gray is None) == (w == 0)
            cur = wall_frame(t_cam)
            res = tr.track(frame_to_device(cur, "cpu"), prev.T_world_cam)  # prior: the previous pose
            assert not res.lost, res.reason
            ends[w, k] = res.T_world_cam
    geometric_spread = pose_error(ends[0.0, 0], ends[0.0, 1])[0]
    assert geometric_spread < 0.005, geometric_spread  # the motions differ by 29 mm, geometry's ends by < 5
    for k, t_cam in enumerate(motions):
        along = np.linalg.norm(ends[0.1, k][:2, 3] - t_cam[:2])  # in the wall's plane: the texture's part
        depth = abs(ends[0.1, k][2, 3] - t_cam[2])  # off the wall: the map's, its zero set a few mm off
        da = pose_error(ends[0.1, k], wall_frame(t_cam).T_world_cam)[1]
        assert along < 0.002 and depth < 0.004 and da < 0.1, (k, along, depth, da)
    # without colour the term is off (and no gray image is kept)
    tr = tracker_for(cfg, mapper, use_color=False, method="sdf", sdf_w_photo=0.1)
    tr.remember(frame_to_device(prev, "cpu"), prev.T_world_cam)
    assert tr._reference.gray is None
    for bad in ({"sdf_w_photo": -0.1}, {"sdf_huber_photo": 0.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            TrackingConfig(**bad)


def test_blurred_photometric_stage_widens_the_basin(monkeypatch):
    """A wall with a weak coarse and a strong fine checker (0.4 and 0.08 m: ~31 and ~6 pixels), the camera slid
    47 mm along it (~3.6 pixels): against the sharp image alone the solver ends in a fine-texture minimum
    (~50 mm off); with the blurred stage first (``sdf_w_photo_blur``) it reaches the true pose, which the
    sharp image then polishes."""
    cfg = load_preset("cpu-small", TINY)
    kw = {"h": 144, "w": 192, "f": 160.0, "period_m": 0.4, "amplitude": 0.25, "fine_period_m": 0.08,
          "fine_amplitude": 0.2}
    prev, cur = wall_frame(np.zeros(3), **kw), wall_frame(np.array([0.04, -0.024, 0.0]), **kw)
    mapper = make_mapper(cfg)
    mapper.integrate(frame_to_device(prev, "cpu"), prev.T_world_cam)
    calls, fields = [], []  # evaluations (what Tracker.sdf_stages tells the benchmarks to expect), field queries
    real_linearize, real_terms = tracking_sdf.linearize_terms, tracking_sdf.pose_terms
    monkeypatch.setattr(tracking_sdf, "linearize_terms", lambda *a, **k: calls.append(1) or real_linearize(*a, **k))
    monkeypatch.setattr(tracking_sdf, "pose_terms", lambda *a, **k: fields.append(1) or real_terms(*a, **k))
    errors = {}
    for w in (0.0, 0.3):
        tr = tracker_for(cfg, mapper, method="sdf", sdf_w_photo=0.1, sdf_w_photo_blur=w)
        tr.remember(frame_to_device(prev, "cpu"), prev.T_world_cam)
        assert (tr._reference.gray_blurred is None) == (w == 0)
        assert tr.sdf_stages() == tr.config.sdf_levels + (w > 0)
        calls.clear()
        fields.clear()
        res = tr.track(frame_to_device(cur, "cpu"), prev.T_world_cam)
        assert len(calls) == res.iterations + tr.sdf_stages()
        # the finest stage starts where the blurred one ended, on its points: it reuses that field query
        assert len(fields) == len(calls) - (w > 0)
        assert not res.lost, res.reason
        errors[w] = pose_error(res.T_world_cam, cur.T_world_cam)
    assert errors[0.0][0] > 0.02, errors
    assert errors[0.3][0] < 0.005 and errors[0.3][1] < 0.1, errors
    # both sides are blurred alike, so at the true pose the blurred residuals vanish (up to 8-bit rounding and
    # the replicated image edges), where the sharp gray levels against the blurred image would not
    ref = tr._reference.blurred()
    data = frame_to_device(cur, "cpu")
    images = gray_images(data.color, 2.0)
    pts = sample_points(data, 512, torch.Generator().manual_seed(0), with_gray=True, blurred=images.blurred)
    r, _, ok = photometric_residuals(ref, pts.p_cam, pts.gray_blurred, torch.as_tensor(cur.T_world_cam), 0.05)
    r_sharp = photometric_residuals(ref, pts.p_cam, pts.gray, torch.as_tensor(cur.T_world_cam), 0.05)[0]
    assert int(ok.sum()) > 400
    assert float(r[ok].abs().median()) < 2e-3 < 0.01 < float(r_sharp[ok].abs().median()), (r, r_sharp)
    # the stage needs the sharp term: without it (or without colour) no blurred image is kept
    for kw_off, color in (({"sdf_w_photo": 0.0}, True), ({}, False)):
        tr = tracker_for(cfg, mapper, use_color=color, method="sdf", **kw_off)
        tr.remember(frame_to_device(prev, "cpu"), prev.T_world_cam)
        assert tr._reference.gray_blurred is None
    for bad in ({"sdf_w_photo_blur": -0.1}, {"sdf_photo_blur_px": -1.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            TrackingConfig(**bad)


def test_gaussian_blur_matches_a_direct_convolution():
    """The separable blur against a direct 2-D sum over the truncated kernel (edges replicated): same values,
    a constant image unchanged, the total of an interior impulse kept."""
    img = torch.rand(20, 27, generator=torch.Generator().manual_seed(0))
    sigma = 1.7
    r = int(3 * sigma + 0.5)
    x = np.arange(-r, r + 1)
    k1 = np.exp(-0.5 * (x / sigma) ** 2)
    k2 = np.outer(k1, k1) / k1.sum() ** 2
    padded = np.pad(img.numpy().astype(np.float64), r, mode="edge")
    ref = np.zeros(img.shape)
    for i in range(img.shape[0]):
        for j in range(img.shape[1]):
            ref[i, j] = (padded[i:i + 2 * r + 1, j:j + 2 * r + 1] * k2).sum()
    torch.testing.assert_close(gaussian_blur(img, sigma), torch.as_tensor(ref, dtype=torch.float32), atol=1e-5, rtol=0)
    torch.testing.assert_close(gaussian_blur(torch.full((9, 9), 0.3), 1.0), torch.full((9, 9), 0.3))
    impulse = torch.zeros(31, 31)
    impulse[15, 15] = 1.0
    assert abs(float(gaussian_blur(impulse, 2.0).sum()) - 1.0) < 1e-5


@pytest.mark.parametrize("use_color", [False, True])
def test_sdf_tracker_recovers_a_known_perturbation(room, use_color):
    cap, cfg, mapper = room
    f = cap[7]
    prior = perturb(f.T_world_cam)
    tr = tracker_for(cfg, mapper, use_color=use_color, method="sdf", sdf_w_color=0.1 if use_color else 0.0)
    res = tr.track(frame_to_device(f, "cpu"), prior)
    dt0, da0 = pose_error(prior, f.T_world_cam)
    dt, da = pose_error(res.T_world_cam, f.T_world_cam)
    assert dt0 > 0.04 and da0 > 2.0
    assert not res.lost, res.reason
    assert dt < 0.008 and da < 0.3, (dt, da)
    assert res.depth_residual_m < 0.01


def test_sdf_tracker_then_render_refinement(room):
    cap, cfg, mapper = room
    f = cap[7]
    tr = tracker_for(cfg, mapper, method="sdf", refine_iters=5, rays=256, sdf_converge_tol=0.0, check_every=1)
    res = tr.track(frame_to_device(f, "cpu"), perturb(f.T_world_cam))
    dt, da = pose_error(res.T_world_cam, f.T_world_cam)
    assert not res.lost and dt < 0.008 and da < 0.3, (dt, da)
    assert res.iterations == 2 * 6 + 5  # sdf levels x iterations (no early stop) + the render refinement's
    # the refinement starts at the sdf tracker's pose and takes small steps (lr_device_prior): it stays near it
    # (with the render tracker's own lr, Adam's ~1 cm first steps left it 16 mm off the answer here)
    alone = tracker_for(cfg, mapper, method="sdf", sdf_converge_tol=0.0).track(frame_to_device(f, "cpu"),
                                                                            perturb(f.T_world_cam))
    assert pose_error(res.T_world_cam, alone.T_world_cam)[0] < 0.004


def test_sdf_tracker_stops_once_converged(room):
    """With a convergence tolerance the levels end early, at a pose within a fraction of the tolerance's
    scale of the one all iterations reach; the test is only read every check_every iterations."""
    cap, cfg, mapper = room
    f = cap[7]
    data, prior = frame_to_device(f, "cpu"), perturb(f.T_world_cam)
    full = tracker_for(cfg, mapper, method="sdf", sdf_iters=8, sdf_converge_tol=0.0).track(data, prior)
    early = tracker_for(cfg, mapper, method="sdf", sdf_iters=8, sdf_converge_tol=1e-4, check_every=1).track(data, prior)
    assert full.iterations == 16 and early.iterations < full.iterations
    dt, da = pose_error(early.T_world_cam, full.T_world_cam)
    assert dt < 1e-3 and da < 0.05, (dt, da)
    assert pose_error(early.T_world_cam, f.T_world_cam)[0] < 0.008
    # read back every 5th iteration: a level ends after 0 or 5 iterations (the test passed) or runs all 8
    sparse = tracker_for(cfg, mapper, method="sdf", sdf_iters=8, sdf_converge_tol=1e-4,
                         check_every=5).track(data, prior)
    assert sparse.iterations in {a + b for a in (0, 5, 8) for b in (0, 5, 8)}, sparse.iterations
    assert sparse.iterations >= early.iterations


def test_sdf_tracker_coarse_levels_stop_at_their_own_tolerance(room):
    """``sdf_coarse_converge_tol`` ends the coarser levels (0: they run every iteration); the finest level
    still polishes the pose to ``sdf_converge_tol``, so a loose coarse tolerance costs no accuracy. (On this
    96x72 map the finest level's cost is flat within ~2 mm around its minimum, so the two need not end at the
    same pose; each ends ~3 mm from the true one.)"""
    cap, cfg, mapper = room
    f = cap[7]
    data, prior = frame_to_device(f, "cpu"), perturb(f.T_world_cam)

    def track(coarse_tol: float):  # noqa: ANN202
        return tracker_for(cfg, mapper, method="sdf", sdf_iters=8, sdf_converge_tol=1e-4, check_every=1,
                           sdf_coarse_converge_tol=coarse_tol).track(data, prior)

    tight, loose, never = track(1e-4), track(3e-3), track(0.0)
    assert never.iterations >= 8  # the coarse level ran all its iterations
    assert loose.iterations < tight.iterations < never.iterations + 8
    (dt_loose, da_loose), (dt_tight, da_tight) = (pose_error(r.T_world_cam, f.T_world_cam) for r in (loose, tight))
    assert dt_loose < 0.008 and dt_loose < dt_tight + 5e-4 and da_loose < da_tight + 0.05, \
        (dt_loose, dt_tight, da_loose, da_tight)
    with pytest.raises(ConfigError, match="sdf_coarse_converge_tol"):
        TrackingConfig(sdf_coarse_converge_tol=-1.0)


@pytest.mark.parametrize("method", ["sdf", "render"])
def test_a_frame_that_does_not_fit_the_map_is_lost(room, method):
    """Every depth 0.6 m beyond the mapped surface: no pose makes the frame agree with the map."""
    cap, cfg, mapper = room
    f = cap[7]
    g = f.with_(depth_m=np.where(f.depth_m > 0, f.depth_m + 0.6, 0).astype(np.float32))
    tr = tracker_for(cfg, mapper, use_color=False, method=method, rays=192, iters=15)
    res = tr.track(frame_to_device(g, "cpu"), f.T_world_cam)
    assert res.lost, (res.depth_residual_m, res.valid_rays)
    np.testing.assert_allclose(res.T_world_cam, f.T_world_cam)  # a lost frame keeps its prior


def test_sdf_tracker_device_prior_holds_the_pose(room):
    cap, cfg, mapper = room
    f = cap[7]
    prior = perturb(f.T_world_cam)
    tr = tracker_for(cfg, mapper, method="sdf", device_prior_weight=1e6)
    held = tr.track(frame_to_device(f, "cpu"), prior, prior_from_device=True)
    dt, da = pose_error(held.T_world_cam, prior)
    assert dt < 0.003 and da < 0.1, (dt, da)


def test_masked_median_matches_boolean_indexing():
    g = torch.Generator().manual_seed(3)
    for n in (1, 2, 7, 100):
        x = torch.rand(n, generator=g)
        m = torch.rand(n, generator=g) < 0.6
        want = x[m].median() if m.any() else torch.tensor(0.0)
        assert float(masked_median(x, m)) == pytest.approx(float(want))


def test_sdf_tracker_on_real_7scenes_frames(shared_data):
    """Map frames 0-20 of redkitchen at their reference poses, then track frame 25 from its reference pose and
    from a 4 cm / 2.7 deg perturbation of it. The reference poses are KinectFusion's (good to ~1-2 cm and
    under a degree), so the map's optimum sits ~0.7 deg from them; the perturbed start must reach the same
    optimum as the reference start (within a few mm), and both must stay within the reference's own accuracy."""
    cap = open_capture(shared_data / "sevenscenes_redkitchen", stride=5, limit=30)
    cfg = load_preset("cpu-small", TINY + ["mapping.max_depth_m=4.0", "loss.w_color=0.1"])
    mapper = make_mapper(cfg)
    frames = list(cap.frames(0, 6))
    for f in frames[:5]:
        mapper.integrate(frame_to_device(f, "cpu", max_depth_m=4.0), f.T_world_cam)
    f = frames[5]
    data = frame_to_device(f, "cpu", max_depth_m=4.0)
    tr = tracker_for(cfg, mapper, method="sdf", sdf_points=4096)
    at_ref = tr.track(data, f.T_world_cam)
    res = tr.track(data, perturb(f.T_world_cam))
    assert not res.lost and not at_ref.lost, (res.reason, at_ref.reason)
    dt, da = pose_error(res.T_world_cam, f.T_world_cam)
    assert dt < 0.015 and da < 1.0, (dt, da)
    # both starts end within a few mm of each other (the map of 5 frames at 0.2 m voxels is flat to a few mm
    # along the kitchen's dominant planes; more iterations do not close the gap)
    dt, da = pose_error(res.T_world_cam, at_ref.T_world_cam)
    assert dt < 0.006 and da < 0.25, (dt, da)
    # the paper's tracker on the same frame: it closes most of the gap (its Adam steps end a little short)
    rd = tracker_for(cfg, mapper, method="render", rays=256, iters=30).track(data, perturb(f.T_world_cam))
    dt, da = pose_error(rd.T_world_cam, f.T_world_cam)
    assert not rd.lost and dt < 0.03 and da < 1.2, (dt, da)


def test_spd_solvers_match_lapack_and_step_nowhere_on_a_degenerate_system():
    """The CPU path (Cholesky) and the device path (elimination, what CUDA runs) against LAPACK's solve; a
    matrix that is not positive definite gives no step on the CPU path."""
    from voxfusion.core.slam.tracking_sdf import solve_spd, solve_spd_elimination

    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        J = torch.randn(50, 6, generator=g, dtype=torch.float64)
        A = J.T @ J + 1e-3 * torch.eye(6, dtype=torch.float64)
        b = torch.randn(6, generator=g, dtype=torch.float64)
        for solve in (solve_spd, solve_spd_elimination):
            torch.testing.assert_close(solve(A, b), torch.linalg.solve(A, b), rtol=1e-9, atol=1e-10)
    indefinite = torch.diag(torch.tensor([1.0, 2.0, -1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
    assert torch.equal(solve_spd(indefinite, torch.ones(6, dtype=torch.float64)), torch.zeros(6, dtype=torch.float64))
    nan = torch.full((6, 6), float("nan"), dtype=torch.float64)
    assert torch.equal(solve_spd(nan, torch.ones(6, dtype=torch.float64)), torch.zeros(6, dtype=torch.float64))


def test_compiled_linearize_matches_linearize_as_the_map_grows(room):
    """``tracking.compile``: the compiled residuals and normal equations (every term: SDF, frame-to-frame,
    photometric) are the plain function's, and stay so when the map has grown between calls (dynamic shapes:
    its tables change size every frame)."""
    from voxfusion.core.compiled import CompiledFunction

    mapper, ref, pts, T = photometric_setup(room, n_points=512, perturbation=0.1)
    scfg = SdfSolverConfig(w_frame=1.0, w_photo=0.1)
    compiled = CompiledFunction(linearize, "tracking.compile")
    grown = mapper.voxels.snapshot()
    grown.allocate(torch.rand(200, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float32) * 4 - 2)
    for voxels in (mapper.voxels.snapshot(), grown):
        want = linearize(voxels, mapper.decoder, pts, T, scfg, ref)
        got = compiled(voxels, mapper.decoder, pts, T, scfg, ref)
        assert not compiled.failed
        cost, H, b, r, ok = want
        assert int(ok.sum()) > 100 and float(H.abs().max()) > 0
        torch.testing.assert_close(got[0], cost, rtol=1e-5, atol=1e-9)
        torch.testing.assert_close(got[1], H, rtol=1e-4, atol=1e-6 * float(H.abs().max()))
        torch.testing.assert_close(got[2], b, rtol=1e-4, atol=1e-6 * float(b.abs().max()))
        torch.testing.assert_close(got[3], r, rtol=1e-4, atol=1e-6)
        assert torch.equal(got[4], ok)
    assert grown.n_voxels > mapper.voxels.n_voxels


def test_stages_on_the_same_points_share_the_field_query(room, monkeypatch):
    """The blurred photometric stage and the finest level evaluate the same points against the same reference
    depth: at the pose where one ends the other starts from its field and frame-to-frame terms instead of
    querying the field again, and the solution is the one without sharing, bit for bit."""
    cap, cfg, mapper = room
    frame = frame_to_device(cap[6], "cpu")
    tr = tracker_for(cfg, mapper, method="sdf", sdf_points=1024, sdf_w_photo=0.1, sdf_w_photo_blur=0.3)
    tr.remember(frame_to_device(cap[5], "cpu"), cap[5].T_world_cam)
    images = tr._gray_images(frame)
    finest = sample_points(frame, 1024, torch.Generator().manual_seed(3), with_gray=True, blurred=images.blurred)
    levels = [finest.prefix(256), finest]
    scfg = SdfSolverConfig(iters=4, w_color=0.2, w_frame=1.0, w_photo=0.1, w_photo_blurred=0.3)
    T0 = torch.as_tensor(perturb(cap[6].T_world_cam, 0.3))
    fields = []
    real_terms = tracking_sdf.pose_terms
    monkeypatch.setattr(tracking_sdf, "pose_terms", lambda *a, **k: fields.append(1) or real_terms(*a, **k))
    shared = tracking_sdf.solve_pose(mapper.voxels, mapper.decoder, levels, T0, scfg, tr._reference)
    n_shared = len(fields)
    assert n_shared == shared.iterations + 3 - 1  # 3 stages, each evaluates its start; the finest reuses
    shares = tracking_sdf._shares_pose_terms
    monkeypatch.setattr(tracking_sdf, "_shares_pose_terms", lambda a, b: False)
    fields.clear()
    alone = tracking_sdf.solve_pose(mapper.voxels, mapper.decoder, levels, T0, scfg, tr._reference)
    assert len(fields) == n_shared + 1 and alone.iterations == shared.iterations
    for name in ("T", "cost", "inlier_fraction", "median_residual_m", "n_valid"):
        assert torch.equal(getattr(shared, name), getattr(alone, name)), name
    # compiled (here: the compiled function's stand-in, the plain one), the stages share nothing
    monkeypatch.setattr(tracking_sdf, "_shares_pose_terms", shares)
    monkeypatch.setattr(tracking_sdf, "COMPILED_LINEARIZE", tracking_sdf.linearize_terms)
    fields.clear()
    compiled = tracking_sdf.solve_pose(mapper.voxels, mapper.decoder, levels, T0, replace(scfg, compile=True),
                                       tr._reference)
    assert len(fields) == compiled.iterations + 3 and torch.equal(compiled.T, shared.T)
    # what may be shared: the same point tensor and reference geometry, the options the field terms depend on
    ref = tr._reference
    same = (finest, scfg, ref)
    assert shares(same, (finest.blurred(), scfg, ref.blurred()))
    assert not shares(same, (levels[0], scfg, ref))
    assert not shares(same, (finest, scfg, None))
    assert not shares(same, (finest, replace(scfg, w_frame=0.5), ref))
    assert not shares(same, (finest, scfg, replace(ref, T_ref_world=ref.T_ref_world.clone())))


def test_reused_pose_terms_give_what_a_fresh_evaluation_gives(room):
    """:func:`linearize_terms` from terms computed beforehand at the same pose (what the finest stage reuses) is
    the fresh evaluation, bit for bit, with every term on: the SDF, the colour head against the points' own gray
    levels, frame-to-frame and photometric; terms reduced to residuals cannot be reused."""
    mapper, ref, pts, T = photometric_setup(room, n_points=512, perturbation=0.1)
    scfg = SdfSolverConfig(w_color=0.2, w_frame=1.0, w_photo=0.1)
    terms = tracking_sdf.pose_terms(mapper.voxels, mapper.decoder, pts, T, scfg, ref)
    assert all(t is not None for t in terms)  # every term present
    fresh = tracking_sdf.linearize_terms(mapper.voxels, mapper.decoder, pts, T, scfg, ref)
    reused = tracking_sdf.linearize_terms(mapper.voxels, mapper.decoder, pts, T, scfg, ref, terms)
    for a, b in zip((*fresh[:3], *fresh[3]), (*reused[:3], *reused[3]), strict=True):
        assert torch.equal(a, b)
    # the colour term compares with the points' gray levels: other gray levels, another system
    other = tracking_sdf.SdfPoints(pts.p_cam, pts.gray.flip(0))
    assert not torch.equal(tracking_sdf.linearize_terms(mapper.voxels, mapper.decoder, other, T, scfg, ref, terms)[2],
                           reused[2])
    with pytest.raises(ValidationError):
        tracking_sdf.linearize_terms(mapper.voxels, mapper.decoder, pts, T, scfg, ref,
                                     terms.where(torch.tensor(True), terms, residuals_only=True))


def test_map_costs_are_linearizes_costs_at_every_pose_in_one_batch(room):
    """The batched map-term cost (what ranks start poses after a gap) is :func:`linearize`'s cost at each pose, in
    pose chunks of any size, including poses that see the map only in part or not at all."""
    cap, cfg, mapper = room
    frame = frame_to_device(cap[6], "cpu")
    pts = sample_points(frame, 700, torch.Generator().manual_seed(4))
    scfg = SdfSolverConfig(huber_m=0.01, max_residual_m=0.08)
    T6 = cap[6].T_world_cam
    poses = [perturb(T6, s) for s in (0.0, 0.3, 1.0, 3.0)] + [T6 @ se3_exp(torch.tensor(
        [0.0, 0.0, 0.0, 0.0, np.deg2rad(a), 0.0], dtype=torch.float64)).numpy() for a in (40.0, 180.0)]
    T = torch.as_tensor(np.stack(poses))
    want = torch.stack([linearize(mapper.voxels, mapper.decoder, pts, T[k], scfg)[0] for k in range(len(poses))])
    for max_points in (1 << 18, 1400, 1):  # all at once, two poses per chunk, one
        got = tracking_sdf.map_costs(mapper.voxels, mapper.decoder, pts.p_cam, T, scfg, max_points=max_points)
        assert got.dtype == torch.float64 and got.shape == (len(poses),)
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
    assert want[0] < want[2] < want[3] and want[-1] > 10 * want[0]  # a meaningful spread of costs
    with pytest.raises(tracking_sdf.ShapeError):
        tracking_sdf.map_costs(mapper.voxels, mapper.decoder, pts.p_cam, T[0], scfg)
