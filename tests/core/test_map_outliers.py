"""A map renders what it was shown, even when the depth carries isolated outliers (speckle, flying pixels).

Two mechanisms, each tested on its own and then together on real and synthetic captures:

* the neighbourhood-support depth filter (``core/depth_filter.py``), applied where frames enter the engine;
* per-voxel observation evidence with an active mask (``core/map/evidence.py``, ``VoxelMap.set_active``).

The end-to-end probe: map the first frame, render its depth at its own pose, and require a median
``|rendered - observed| <= 2 cm`` with 0.5 % and 2 % of the pixels set to random depths in 0.3-1.0 m, with
the first camera axis-aligned and rotated 40 deg about an oblique world axis; then track the next 10 frames
with the SLAM system and require none lost. Without both mechanisms (``mapping.depth_filter.enabled=false``,
``mapping.evidence.enabled=false``) every one of those end-to-end tests fails: the probe gives 8 cm to 1.8 m
and every tracked frame is lost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn import functional

from voxfusion.core.checkpoint import load_checkpoint, save_checkpoint
from voxfusion.core.datasets import open_capture, resize_frame
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.depth_filter import DepthFilterConfig, depth_outlier_mask, depth_support
from voxfusion.core.errors import CaptureFormatError, ConfigError, ShapeError, ValidationError
from voxfusion.core.eval.render_probe import (
    DepthProbe,
    add_depth_outliers,
    anchor_first_pose,
    depth_probe,
    oblique_rotation,
)
from voxfusion.core.framedata import frame_to_device
from voxfusion.core.geometry import make_intrinsics
from voxfusion.core.map import VoxelMap
from voxfusion.core.map.evidence import EvidenceConfig, free_space_voxels, observe_frame
from voxfusion.core.reconstruct import make_mapper
from voxfusion.core.render.volume import camera_rays, intersect_voxels, intersect_voxels_reference, render_depth_image
from voxfusion.core.slam import SlamSystem
from voxfusion.core.slam.mapping import _backproject
from voxfusion.core.slam.presets import load_preset

PROBE_MAX_M = 0.02
"""Median |rendered - observed| depth of the first frame at its own pose (clean maps give 0.4-1.7 cm)."""
TRACKED_FRAMES = 10
OFF = ["mapping.depth_filter.enabled=false", "mapping.evidence.enabled=false"]


# ---------------------------------------------------------------- depth filter
def _support_reference(depth: torch.Tensor, window_px: int, rel_tol: float) -> torch.Tensor:
    """Plain version of :func:`depth_support`: every offset of the window compared with the centre."""
    r = window_px // 2
    h, w = depth.shape
    ld = torch.where(depth > 0, depth.clamp(min=1e-30).log(), torch.full_like(depth, math.nan))
    pad = functional.pad(ld[None, None], (r, r, r, r), value=math.nan)[0, 0]
    count = torch.zeros(h, w, dtype=torch.int64)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy or dx:
                count += (pad[r + dy:r + dy + h, r + dx:r + dx + w] - ld).abs() <= math.log1p(rel_tol)
    return count


@pytest.mark.parametrize("shape", [(1, 1), (2, 7), (3, 3), (17, 13), (48, 64)])
@pytest.mark.parametrize("window_px", [3, 5, 7])
def test_depth_support_matches_plain_reference(shape, window_px, native_path):
    """The counts from the C loop and from the shifted operators (``native_path``) against every offset compared with
    the centre, invalid pixels (zero, NaN, infinite) included."""
    g = torch.Generator().manual_seed(shape[0] * 100 + shape[1] + window_px)
    levels = 1.0 + torch.randint(0, 4, shape, generator=g).float() * 0.5
    depth = levels * (1.0 + 0.04 * (torch.rand(shape, generator=g) - 0.5))  # some agree within 3 %, some not
    depth[torch.rand(shape, generator=g) < 0.15] = 0.0
    depth[torch.rand(shape, generator=g) < 0.03] = math.nan
    depth[torch.rand(shape, generator=g) < 0.03] = math.inf
    got = depth_support(depth, window_px, 0.03)
    assert got.dtype == torch.uint8 and got.shape == shape
    torch.testing.assert_close(got.long(), _support_reference(depth, window_px, 0.03), rtol=0, atol=0)


def test_depth_filter_drops_isolated_outliers_and_keeps_structures():
    depth = torch.full((40, 60), 2.0)
    depth[:, 30:] = 3.5  # a depth edge: both sides are kept
    depth[10, 10] = 0.6  # isolated outlier
    depth[20, 20:22] = 0.8  # an outlier pair (each has one supporter)
    depth[5:35, 45] = 1.0  # a 1 px wide real pole in front of the far wall (4 in-line supporters)
    depth[30, 5] = 0.0  # invalid stays invalid
    keep = depth_outlier_mask(depth, DepthFilterConfig())
    assert not keep[10, 10] and not keep[20, 20] and not keep[20, 21] and not keep[30, 5]
    assert keep[7:33, 45].all()  # the pole but for its last 2 px at each end (2 and 3 supporters)
    expected_dropped = {(10, 10), (20, 20), (20, 21), (30, 5), (5, 45), (6, 45), (33, 45), (34, 45)}
    dropped = {tuple(p) for p in torch.nonzero(~keep).tolist()}
    assert dropped == expected_dropped
    # switched off: every valid pixel passes
    assert int(depth_outlier_mask(depth, DepthFilterConfig(enabled=False)).sum()) == 40 * 60 - 1


def test_depth_filter_config_and_shape_errors():
    for kwargs, field in [({"window_px": 4}, "window_px"), ({"window_px": 1}, "window_px"),
                          ({"rel_tol": 0.0}, "rel_tol"), ({"min_support": 0}, "min_support"),
                          ({"min_support": 25}, "min_support")]:
        with pytest.raises(ConfigError) as e:
            DepthFilterConfig(**kwargs)
        assert e.value.field == field
    with pytest.raises(ShapeError, match="depth_m"):
        depth_support(torch.ones(2, 3, 4))


def test_frame_to_device_applies_the_filter_for_tracking_and_mapping_alike():
    depth = np.full((24, 32), 2.0, np.float32)
    depth[12, 16] = 0.5
    frame = RGBDFrame(depth_m=depth, K=make_intrinsics(30.0, 30.0, 15.5, 11.5), timestamp_s=0.0)
    on = frame_to_device(frame, "cpu")
    assert on.depth_m[12, 16] == 0 and on.n_valid == 24 * 32 - 1
    off = frame_to_device(frame, "cpu", depth_filter=DepthFilterConfig(enabled=False))
    assert off.depth_m[12, 16] == 0.5 and off.n_valid == 24 * 32
    assert frame_to_device(frame, "cpu", depth_filter=None).n_valid == 24 * 32


# ---------------------------------------------------------------- active mask
def _map_with_inactive_voxel() -> tuple[VoxelMap, int]:
    vm = VoxelMap(0.2, embed_dim=4, seed=0)
    xs = torch.arange(-4, 5, dtype=torch.float64) * 0.2 + 0.1
    wall = torch.cartesian_prod(xs, xs, torch.tensor([2.05], dtype=torch.float64))  # a wall of voxels at z 2.0-2.2
    vm.allocate(wall)
    vm.allocate(torch.tensor([[0.05, 0.05, 1.05]], dtype=torch.float64))  # one voxel in front of it
    idx = int(vm.lookup_voxels(torch.tensor([[0.05, 0.05, 1.05]]))[0])
    active = torch.ones(vm.n_voxels, dtype=torch.bool)
    active[idx] = False
    assert vm.set_active(active) == 1 and vm.set_active(active) == 0
    return vm, idx


def test_inactive_voxel_reads_as_empty_but_stays_allocated():
    vm, idx = _map_with_inactive_voxel()
    p = torch.tensor([[0.05, 0.05, 1.05]])
    assert vm.n_voxels == 82 and vm.n_active == 81
    assert int(vm.lookup_voxels(p)[0]) == -1
    assert int(vm.lookup_codes(vm.voxel_codes[idx:idx + 1])[0]) == -1
    assert int(vm.lookup_allocated(vm.voxel_codes[idx:idx + 1])[0]) == idx
    assert int(vm.lookup_allocated_cells(vm.voxel_coords[idx:idx + 1])[0]) == idx
    assert vm.allocate(p) == 0 and vm.count_new_voxels(p) == (0, 1)  # never re-allocated
    assert vm.index_grid(0).lookup(vm.voxel_coords[idx:idx + 1]).item() == -1
    # the coarse block holding only the inactive voxel is empty; blocks of the wall are not
    assert vm.index_grid(1).lookup(torch.div(vm.voxel_coords[idx:idx + 1], 2, rounding_mode="floor")).item() == -1
    assert vm.index_grid(1).n_occupied > 0
    assert len(vm.active_voxel_coords) == 81
    # the sorted-code fallback agrees with the dense grid
    vm.dense_grid_max_cells = 0
    assert int(vm.lookup_voxels(p)[0]) == -1
    assert int(vm.lookup_allocated_cells(vm.voxel_coords[idx:idx + 1])[0]) == idx


def test_raycasting_skips_inactive_voxels_fast_and_reference_agree():
    vm, idx = _map_with_inactive_voxel()
    o = torch.zeros(50, 3)
    g = torch.Generator().manual_seed(0)
    d = torch.cat([torch.tensor([[0.01, 0.02, 1.0]]), (torch.rand(49, 3, generator=g) - 0.5) * 0.3
                   + torch.tensor([0.0, 0.0, 1.0])])
    fast = intersect_voxels(vm, o, d, 10.0, 20)
    ref = intersect_voxels_reference(vm, o, d, 10.0, 20)
    assert torch.equal(fast.voxel_idx, ref.voxel_idx) and torch.equal(fast.t_entry, ref.t_entry)
    assert not (fast.voxel_idx == idx).any()
    assert fast.hit[0] and float(fast.t_entry[0, 0]) == pytest.approx(2.0, abs=1e-6)  # straight to the wall
    vm.set_active(torch.ones(vm.n_voxels, dtype=torch.bool))  # lifted again: the voxel is hit first
    again = intersect_voxels(vm, o, d, 10.0, 20)
    assert int(again.voxel_idx[0, 0]) == idx


def test_active_mask_and_evidence_survive_state_dict_snapshot_and_old_states():
    vm, idx = _map_with_inactive_voxel()
    vm.add_evidence(torch.tensor([idx, idx, 0]), torch.tensor([idx]), hit_weight=2.0, free_weight=16.0)
    snap = vm.snapshot()
    vm.add_evidence(torch.tensor([0]), torch.tensor([], dtype=torch.int64))
    assert snap.voxel_hits[0] == 2.0 and vm.voxel_hits[0] == 3.0  # the snapshot keeps its own counters
    state = vm.state_dict()
    back = VoxelMap.from_state_dict(state)
    assert torch.equal(back.voxel_active, vm.voxel_active) and torch.equal(back.voxel_hits, vm.voxel_hits)
    assert torch.equal(back.voxel_free, vm.voxel_free) and back.n_active == vm.n_active
    assert int(back.lookup_voxels(torch.tensor([[0.05, 0.05, 1.05]]))[0]) == -1
    old = {k: v for k, v in state.items() if k not in ("voxel_hits", "voxel_free", "voxel_active")}
    legacy = VoxelMap.from_state_dict(old)  # a checkpoint from before the evidence existed
    assert legacy.n_active == legacy.n_voxels and float(legacy.voxel_free.sum()) == 0.0
    with pytest.raises(ValidationError, match="hit_idx"):
        vm.add_evidence(torch.tensor([vm.n_voxels]), torch.tensor([], dtype=torch.int64))
    with pytest.raises(ShapeError, match="active"):
        vm.set_active(torch.ones(3, dtype=torch.bool))


# ---------------------------------------------------------------- evidence
def _wall_frame(width: int = 160, height: int = 120) -> RGBDFrame:
    depth = np.full((height, width), 2.5, np.float32)  # a wall 2.5 m away
    depth[50:52, 70:73] = 0.7  # a small 2 x 3 px blob in front: real, but barely observed (6 of ~900 px)
    return RGBDFrame(depth_m=depth, K=make_intrinsics(100.0, 100.0, (width - 1) / 2, (height - 1) / 2),
                     timestamp_s=0.0, T_world_cam=np.eye(4))


def test_evidence_deactivates_barely_observed_voxel_and_keeps_the_wall():
    frame = _wall_frame()
    data = frame_to_device(frame, "cpu")
    assert data.depth_m[51, 71] == pytest.approx(0.7)  # the blob passes the depth filter
    vm = VoxelMap(0.2, embed_dim=4, seed=0)
    T = torch.eye(4, dtype=torch.float64)
    pts = _backproject(data, T, 1)
    vm.allocate(pts)
    cfg = EvidenceConfig()
    free = free_space_voxels(vm, data.depth_m, data.K, T, 1, cfg.margin_m, 0.1)
    blob = int(vm.lookup_voxels(pts[(pts[:, 2] < 1.0)][:1])[0])
    wall = vm.lookup_voxels(pts[pts[:, 2] > 2.0]).unique()
    assert (free == blob).sum() > 500  # most rays crossed the blob's voxel on their way to the wall
    assert not torch.isin(wall, free).any()  # the wall's own voxels are never free space
    twin = VoxelMap.from_state_dict(vm.state_dict())
    update = observe_frame(vm, data, T, pts, cfg)
    # the same update from the points' voxels looked up by the caller (the mapper's one lookup per frame)
    assert observe_frame(twin, data, T, pts, cfg, point_voxels=twin.locate_surface_points(pts).voxel_idx) == update
    assert torch.equal(twin.voxel_hits, vm.voxel_hits) and torch.equal(twin.voxel_active, vm.voxel_active)
    assert update.n_inactive == 1 and not vm.voxel_active[blob] and vm.voxel_active[wall].all()
    assert update.hit_px == pytest.approx(160 * 120)
    # enough later hits (the object seen up close) bring it back
    vm.add_evidence(torch.full((2000,), blob), torch.tensor([], dtype=torch.int64))
    observe_frame(vm, data, T, pts[:0], cfg)
    assert vm.voxel_active[blob]


@pytest.mark.parametrize(("step_ratio", "min_recall"), [(0.5, 0.75), (0.125, 0.93)])
def test_free_space_sampling_matches_exact_ray_voxel_traversal(step_ratio, min_recall):
    """The sampled traversal never reports a voxel the exact DDA says a ray did not cross before its end
    point, and finds most of those it did (it misses voxels a ray clips by less than a sample step)."""
    frame = SyntheticCapture(SyntheticConfig(n_frames=1, width=64, height=48, seed=2))[0]
    data = frame_to_device(frame, "cpu")
    T = torch.as_tensor(frame.T_world_cam)
    vm = VoxelMap(0.2, embed_dim=4, seed=0)
    vm.allocate(_backproject(data, T, 1))
    g = torch.Generator().manual_seed(0)
    lo, hi = vm.voxel_bounds
    vm.allocate((lo + (hi - lo + 1) * torch.rand(400, 3, generator=g, dtype=torch.float64)) * 0.2)  # free space
    margin, step = 0.1, step_ratio * vm.voxel_size_m
    sampled = free_space_voxels(vm, data.depth_m, data.K, T, 1, margin, step)
    v, u = torch.nonzero(data.depth_m > margin, as_tuple=True)
    t_end = data.depth_m[v, u].double() - margin
    o, d = camera_rays(data.K, T, torch.stack([u, v], -1).double(), dtype=torch.float64)
    hits = intersect_voxels_reference(vm, o, d, 20.0, 200, t_far=t_end)
    end_voxel = vm.lookup_voxels(o + d * t_end[:, None])
    exact = hits.voxel_idx[(hits.voxel_idx >= 0) & (hits.voxel_idx != end_voxel[:, None])]
    n_sampled, n_exact = torch.bincount(sampled, minlength=vm.n_voxels), torch.bincount(exact, minlength=vm.n_voxels)
    assert (n_sampled <= n_exact).all()
    assert n_sampled.sum() >= min_recall * n_exact.sum() and n_exact.sum() > 1000


def test_free_space_of_several_views_sampled_together_is_each_views_own():
    """A realtime round's frames cast their free-space rays together: the same entries as each frame alone (in
    another order), views without a valid pixel adding none."""
    from voxfusion.core.map.evidence import free_space_voxels_many

    cap = SyntheticCapture(SyntheticConfig(n_frames=6, width=64, height=48, seed=2))
    views = []
    vm = VoxelMap(0.2, embed_dim=4, seed=0)
    for i in (0, 3, 5):
        data = frame_to_device(cap[i], "cpu")
        T = torch.as_tensor(cap[i].T_world_cam)
        vm.allocate(_backproject(data, T, 1))
        views.append((data.depth_m, data.K, T))
    views.append((torch.zeros_like(views[0][0]), views[0][1], views[0][2]))  # no valid depth
    each = torch.cat([free_space_voxels(vm, *view, 2, 0.1, 0.1) for view in views])
    together = free_space_voxels_many(vm, views, 2, 0.1, 0.1)
    assert each.numel() > 100 and torch.equal(together.sort().values, each.sort().values)
    assert free_space_voxels_many(vm, views[-1:], 2, 0.1, 0.1).numel() == 0


def test_evidence_config_errors():
    for kwargs, field in [({"free_rays": 0}, "free_rays"), ({"margin_m": -1.0}, "margin_m"),
                          ({"min_hit_ratio": 1.0}, "min_hit_ratio"), ({"sample_step_ratio": 0.0},
                                                                      "sample_step_ratio")]:
        with pytest.raises(ConfigError) as e:
            EvidenceConfig(**kwargs)
        assert e.value.field == field
    assert EvidenceConfig().ray_stride_px(480, 640) == 8 and EvidenceConfig().ray_stride_px(10, 10) == 1


def test_mapper_stores_evidence_in_checkpoints(tmp_path):
    cfg = load_preset("cpu-small", ["device=cpu", "mapping.first_frame_iters=2", "field.sdf_hidden=16",
                                    "field.color_hidden=16"])
    mapper = make_mapper(cfg, has_color=False)
    frame = _wall_frame()
    step = mapper.integrate(frame_to_device(frame, "cpu", use_color=False), frame.T_world_cam)
    assert step.inactive_voxels == 1 and mapper.voxels.n_active == mapper.voxels.n_voxels - 1
    loaded = load_checkpoint(save_checkpoint(tmp_path / "c.pt", mapper, cfg), "cpu").mapper.voxels
    assert torch.equal(loaded.voxel_active, mapper.voxels.voxel_active)
    assert torch.equal(loaded.voxel_free, mapper.voxels.voxel_free)


# ---------------------------------------------------------------- probe helpers
def test_probe_helpers():
    d = np.full((10, 10), 2.0, np.float32)
    frame = RGBDFrame(depth_m=d, K=make_intrinsics(10.0, 10.0, 4.5, 4.5), timestamp_s=0.0, T_world_cam=np.eye(4))
    noisy = add_depth_outliers(frame, 0.05, seed=1)
    changed = noisy.depth_m != 2.0
    assert changed.sum() == 5 and ((noisy.depth_m[changed] >= 0.3) & (noisy.depth_m[changed] <= 1.0)).all()
    rendered = d.copy()
    rendered[0, :] = 0.0
    rendered[1, :] = 2.1
    p = depth_probe(rendered, d)
    assert p.n_pixels == 90 and p.median_abs_m == 0.0 and p.rendered_fraction == pytest.approx(0.9)
    R = oblique_rotation(40.0)
    assert np.allclose(R[:3, :3] @ R[:3, :3].T, np.eye(3)) and np.isclose(np.trace(R[:3, :3]), 1 + 2 * np.cos(
        np.deg2rad(40.0)))
    T1 = np.eye(4)
    T1[:3, 3] = [0.0, 0.0, 0.1]
    moved = anchor_first_pose([frame, frame.with_(T_world_cam=T1)], R)
    assert np.allclose(moved[0].T_world_cam, R) and np.allclose(moved[1].T_world_cam, R @ T1)


# ---------------------------------------------------------------- end to end: synthetic and real captures
CAPTURES = {
    # name: (folder under ../shared/data or None for the synthetic room, downscale factor)
    "synthetic": (None, 1),
    "tum_fr1_desk": ("tum_fr1_desk_9frames", 4),
    "tum_fr3_far": ("tum_fr3_structure_notexture_far_120", 4),
    "sevenscenes": ("sevenscenes_redkitchen", 4),
    "stray_iphone": ("stray_iphone_lidar", 2),
    "scanner3d_corridor": ("scanner3d_iphone_corridor", 2),
}


def _clean_frames(name: str, request: pytest.FixtureRequest) -> list[RGBDFrame]:
    folder, scale = CAPTURES[name]
    n = TRACKED_FRAMES + 1
    if folder is None:
        cap = SyntheticCapture(SyntheticConfig(n_frames=n, width=96, height=72, seed=0))
        return [cap[i] for i in range(n)]
    root: Path = request.getfixturevalue("shared_data") / folder
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    try:
        cap = open_capture(root, limit=n)
    except CaptureFormatError as e:
        pytest.skip(f"open_capture cannot read {folder}: {e.problem[:60]}")
    frames = [cap[i] for i in range(len(cap))]
    return [resize_frame(f, f.width // scale, f.height // scale) for f in frames]


@dataclass
class _FirstFrame:
    slam: SlamSystem
    frames: list[RGBDFrame]
    probe: DepthProbe


_RUNS: dict[tuple, _FirstFrame] = {}


def _first_frame_run(name: str, orientation: str, fraction: float, request: pytest.FixtureRequest,
                     overrides: tuple[str, ...] = ()) -> _FirstFrame:
    """SLAM system that has mapped the first frame (with ``first_frame_iters``), and the render-back probe.

    The first camera is axis-aligned (identity rotation) or rotated 40 deg about the world axis (1, 2, 3);
    the other frames' reference poses follow rigidly. Cached so that the tracking test continues the run.
    """
    key = (name, orientation, fraction, overrides)
    if key not in _RUNS:
        frames = _clean_frames(name, request)
        T_aa = np.eye(4)
        T0 = frames[0].T_world_cam
        T_aa[:3, 3] = T0[:3, 3] if T0 is not None else (0.31, 0.17, 0.23)
        T_first = oblique_rotation(40.0, (1.0, 2.0, 3.0)) @ T_aa if orientation == "rotated" else T_aa
        frames = anchor_first_pose(frames, T_first)
        frames = [add_depth_outliers(f, fraction, seed=1000 + i) for i, f in enumerate(frames)]
        config = load_preset("cpu-small", ["device=cpu", *overrides])
        slam = SlamSystem(config)
        slam.process(frames[0])
        # the probe on every 2nd pixel per axis (exact: pixel (u, v) of the half-size image with K / 2 is
        # pixel (2u, 2v) of the frame), a quarter of the render time
        first, m = frames[0], slam.mapper
        K_half = np.diag([0.5, 0.5, 1.0]) @ first.K
        observed = first.depth_m[::2, ::2]
        img = render_depth_image(m.voxels, m.decoder, K_half, T_first, observed.shape[1], observed.shape[0],
                                 config.render)
        _RUNS[key] = _FirstFrame(slam, frames, depth_probe(img.depth, observed))
    return _RUNS[key]


@pytest.mark.parametrize("fraction", [0.005, 0.02])
@pytest.mark.parametrize("orientation", ["axis_aligned", "rotated"])
@pytest.mark.parametrize("name", list(CAPTURES))
def test_first_frame_renders_what_it_was_shown(name, orientation, fraction, request):
    run = _first_frame_run(name, orientation, fraction, request)
    assert run.probe.median_abs_m <= PROBE_MAX_M, run.probe
    assert run.probe.rendered_fraction > 0.9, run.probe
    if (orientation, fraction) not in TRACKED:
        _RUNS.pop((name, orientation, fraction, ()), None)


TRACKED = [("rotated", 0.02)]
"""Tracking (10 frames each) runs on the hardest combination only (2 % outliers, rotated first camera), so
the file stays fast; the probe above covers all four."""


@pytest.mark.slow
@pytest.mark.parametrize(("orientation", "fraction"), TRACKED)
@pytest.mark.parametrize("name", list(CAPTURES))
def test_tracking_after_outlier_frames_loses_nothing(name, orientation, fraction, request):
    run = _first_frame_run(name, orientation, fraction, request)  # continues the probe test's run
    _RUNS.pop((name, orientation, fraction, ()), None)
    records = [run.slam.process(f) for f in run.frames[1:]]
    lost = [(r.index, r.tracking.reason if r.tracking is not None else "no valid depth") for r in records if r.lost]
    assert len(records) >= min(TRACKED_FRAMES, len(run.frames) - 1) and not lost, lost


@pytest.mark.parametrize("switched_off", ["mapping.depth_filter.enabled=false", "mapping.evidence.enabled=false"])
def test_each_mechanism_alone_restores_the_probe(switched_off, request):
    """The filter alone, and the evidence alone (outliers reach allocation), both keep the synthetic probe
    at 2 % outliers within bounds; with both off it fails by metres (the regression this file guards)."""
    run = _first_frame_run("synthetic", "rotated", 0.02, request, (switched_off,))
    assert run.probe.median_abs_m <= PROBE_MAX_M, run.probe
    _RUNS.pop(("synthetic", "rotated", 0.02, (switched_off,)))


def test_without_either_mechanism_the_probe_fails(request):
    run = _first_frame_run("synthetic", "rotated", 0.02, request, tuple(OFF))
    _RUNS.pop(("synthetic", "rotated", 0.02, tuple(OFF)))
    assert run.probe.median_abs_m > 0.2, run.probe  # phantom surfaces in front of the room
