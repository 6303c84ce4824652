"""The sdf tracker's solver stages as CUDA graphs (core/slam/tracking_graphs.py) against the eager solver.

On a CPU: the stages (start and step, every term on) never wait for the host and never copy from it, which is what
capture requires. With CUDA: the replayed solution is the eager one, a new map snapshot is captured again, and a
stage that cannot be captured leaves the tracker eager after one warning.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import replace

import numpy as np
import pytest
import torch
from hostwaits import HostData, HostWaits  # tests/core/hostwaits.py: pytest puts this folder on the path

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.framedata import frame_to_device
from voxfusion.core.lie import se3_exp
from voxfusion.core.reconstruct import make_mapper
from voxfusion.core.slam import tracking_graphs, tracking_sdf
from voxfusion.core.slam.presets import load_preset
from voxfusion.core.slam.tracking import Tracker, TrackingConfig
from voxfusion.core.slam.tracking_sdf import (
    SdfSolverConfig,
    sample_points,
    solve_pose,
    solver_prior,
    solver_stages,
    stage_start,
    stage_step,
)

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

TINY = ["mapping.map_every=1", "mapping.rays_per_frame=192", "mapping.iters=8", "mapping.first_frame_iters=40",
        "field.sdf_hidden=64", "field.color_hidden=64"]
EVERY_TERM = SdfSolverConfig(iters=3, w_color=0.2, w_frame=1.0, w_photo=0.1, w_photo_blurred=0.3,
                             prior_info=(50.0, 20.0))


def build_room(device: str):
    cap = SyntheticCapture(SyntheticConfig(n_frames=9, width=96, height=72, seed=5))
    cfg = load_preset("cpu-small", [f"device={device}", *TINY])
    mapper = make_mapper(cfg)
    for f in cap.frames(0, 6):
        mapper.integrate(frame_to_device(f, device), f.T_world_cam)
    return cap, cfg, mapper


def perturbed(T: np.ndarray) -> np.ndarray:
    xi = torch.tensor([0.02, -0.015, 0.01, np.deg2rad(1.5), np.deg2rad(-1.0), np.deg2rad(0.8)], dtype=torch.float64)
    return T @ se3_exp(xi).numpy()


def solver_inputs(cap, cfg, mapper, index: int, device: str, seed: int = 3, snapshot=None):
    """Two levels of a frame's points with every gray level, and a tracker on ``snapshot`` (default: a new one of
    the mapper's map) holding the previous frame as the reference (blurred image too) and the two before it as older
    references (one slot of three still empty)."""
    tr = Tracker(TrackingConfig(method="sdf", sdf_w_photo=0.1, sdf_w_photo_blur=0.3, sdf_frame_refs=3,
                                sdf_frame_refs_fade=2), cfg.render, use_color=True)
    tr.set_map(*(snapshot or (mapper.voxels.snapshot(), mapper.decoder)))
    for k in (index - 3, index - 2, index - 1):
        tr.remember(frame_to_device(cap[k], device), cap[k].T_world_cam)
    frame = frame_to_device(cap[index], device)
    images = tr._gray_images(frame)
    gen = torch.Generator(device=device).manual_seed(seed)
    finest = sample_points(frame, 512, gen, with_gray=True, blurred=images.blurred)
    return tr, [finest.prefix(128), finest]


def test_the_detectors_see_what_they_look_for():
    x = torch.ones(3)
    with HostWaits() as waits, HostData() as data:
        float(x.sum())
        x[x > 0]
        torch.tensor([1.0, 2.0])
    assert any("_local_scalar_dense" in s for s in waits.seen) and any("index" in s for s in waits.seen)
    assert data.seen == ["tensor"]
    with HostWaits() as waits:
        x[..., 0] = 1.0  # a scalar written by indexing: a host-to-device copy on a GPU (capture refuses it)
    assert any("lift_fresh" in s for s in waits.seen)


@pytest.mark.parametrize("solver", ["cpu", "gpu"])
def test_solver_stages_never_wait_for_the_host_nor_copy_from_it(solver, monkeypatch):
    """Every term on; the 6x6 solve as on a CPU (Cholesky) and as on a GPU (elimination, what the graphs record)."""
    if solver == "gpu":
        monkeypatch.setattr(tracking_sdf, "solve_spd", tracking_sdf.solve_spd_elimination)
    cap, cfg, mapper = build_room("cpu")
    tr, levels = solver_inputs(cap, cfg, mapper, 6, "cpu")
    ref = tr._reference
    stages = solver_stages(levels, EVERY_TERM, ref)
    assert len(stages) == 3 and stages[2].shares and stages[1].keeps  # coarse, blurred, finest sharing its terms
    prior = solver_prior(EVERY_TERM, levels, torch.device("cpu"))
    T0 = torch.as_tensor(perturbed(cap[6].T_world_cam))
    xi0 = torch.zeros(6, dtype=torch.float64)

    def run_stages() -> None:
        state = None
        for stage in stages:
            T, xi = (T0, xi0) if state is None else (state.T, state.xi)
            state = stage_start(tr.voxels, tr.decoder, stage, prior, T, xi, None if state is None else state.terms)
            for _ in range(2):
                state = stage_step(tr.voxels, tr.decoder, stage, prior, state)

    run_stages()  # first use: constants made once per device (what the graphs' warm-up does)
    with HostWaits() as waits, HostData() as data:
        run_stages()
    assert waits.seen == [] and data.seen == []


def solve_both(tracker: Tracker, levels, T0: torch.Tensor, cfg: SdfSolverConfig, graphs):
    eager = solve_pose(tracker.voxels, tracker.decoder, levels, T0, cfg, tracker._reference)
    replayed = graphs.solve(tracker.voxels, tracker.decoder, levels, T0, cfg, tracker._reference)
    return eager, replayed


def assert_same_solution(eager, replayed, exact: bool = False) -> None:
    assert replayed is not None
    assert replayed.iterations == eager.iterations
    if exact:
        for name in ("T", "cost", "inlier_fraction", "median_residual_m", "n_valid"):
            assert torch.equal(getattr(replayed, name), getattr(eager, name)), name
    torch.testing.assert_close(replayed.T, eager.T, rtol=0, atol=1e-9)
    torch.testing.assert_close(replayed.cost, eager.cost, rtol=1e-9, atol=0)
    torch.testing.assert_close(replayed.inlier_fraction, eager.inlier_fraction, rtol=0, atol=0)
    assert int(replayed.n_valid) == int(eager.n_valid)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=cuda)])
def test_replayed_stages_give_the_eager_solution(device):
    """On CUDA the graphs; on a CPU their stand-in (each block run again at replay, outputs copied into the static
    ones), which exercises everything around them: the static inputs, the stages' hand-over, the prior, recapture."""
    cap, cfg, mapper = build_room(device)
    record = tracking_graphs.record_eagerly if device == "cpu" else None
    graphs = tracking_graphs.SolverGraphs(torch.device(device), record=record)
    solver = replace(EVERY_TERM, iters=4, converge_tol=3e-4, coarse_converge_tol=3e-3, check_every=2)
    snapshot = (mapper.voxels.snapshot(), mapper.decoder)
    for index in (6, 7):  # two frames on one snapshot, one capture: the second copies its inputs into the graphs
        tr, levels = solver_inputs(cap, cfg, mapper, index, device, seed=index, snapshot=snapshot)
        T0 = torch.as_tensor(perturbed(cap[index].T_world_cam), device=device)
        eager, replayed = solve_both(tr, levels, T0, solver, graphs)
        assert_same_solution(eager, replayed, exact=device == "cpu")
        assert graphs.captures == 1 and not graphs.failed
    # a device prior on this frame: the same graphs, the prior's information copied in
    eager, replayed = solve_both(tr, levels, T0, replace(solver, prior_info=(400.0, 100.0)), graphs)
    assert_same_solution(eager, replayed, exact=device == "cpu")
    assert graphs.captures == 1
    # a mapping round that allocates nothing: a new snapshot (another decoder too) of the same structure, copied in
    mapper.optimize(2)
    tr.set_map(mapper.voxels.snapshot(), copy.deepcopy(mapper.decoder))
    eager, replayed = solve_both(tr, levels, T0, solver, graphs)
    assert_same_solution(eager, replayed, exact=device == "cpu")
    assert graphs.captures == 1
    # a frame that allocates voxels: copied into the spare rows, captured again only if the grid's box moved
    n_voxels, box = mapper.voxels.n_voxels, grid_box(tr.voxels)
    mapper.integrate(frame_to_device(cap[8], device), cap[8].T_world_cam)
    assert n_voxels < mapper.voxels.n_voxels <= tracking_graphs.MIN_CAPACITY_ROWS
    tr.set_map(mapper.voxels.snapshot(), copy.deepcopy(mapper.decoder))
    eager, replayed = solve_both(tr, levels, T0, solver, graphs)
    assert_same_solution(eager, replayed, exact=device == "cpu")
    captures = 1 + (grid_box(tr.voxels) != box)
    assert graphs.captures == captures
    # without the reference: another signature, captured again
    eager = solve_pose(tr.voxels, tr.decoder, levels, T0, solver, None)
    assert_same_solution(eager, graphs.solve(tr.voxels, tr.decoder, levels, T0, solver, None), exact=device == "cpu")
    assert graphs.captures == captures + 1 and not graphs.failed


def grid_box(voxels):
    g = voxels.index_grid()
    return g.origin_xyz, g.shape


@pytest.mark.parametrize("spare", [True, False])
def test_a_growing_map_is_copied_in_until_it_outgrows_its_spare_rows(spare, monkeypatch):
    """Voxels allocated inside the grid's box are copied into the spare rows; without spare rows (capacity = rows)
    every allocation is a new capture, and so is a voxel beyond the grid's box (the box moves). Every replay gives
    the eager solution."""
    if not spare:
        monkeypatch.setattr(tracking_graphs, "_capacity", lambda rows: rows)
    cap, cfg, mapper = build_room("cpu")
    tr, levels = solver_inputs(cap, cfg, mapper, 6, "cpu")
    T0 = torch.as_tensor(perturbed(cap[6].T_world_cam))
    graphs = tracking_graphs.SolverGraphs(torch.device("cpu"), record=tracking_graphs.record_eagerly)
    assert_same_solution(*solve_both(tr, levels, T0, EVERY_TERM, graphs), exact=True)
    expected = 1
    for index in (6, 7, 8):
        before = (grid_box(tr.voxels), tr.voxels.n_voxels)
        mapper.integrate(frame_to_device(cap[index], "cpu"), cap[index].T_world_cam)
        tr.set_map(mapper.voxels.snapshot(), copy.deepcopy(mapper.decoder))
        after = (grid_box(tr.voxels), tr.voxels.n_voxels)
        assert after[1] > before[1] and after[1] <= tracking_graphs.MIN_CAPACITY_ROWS  # grew, within the spare rows
        expected += before[0] != after[0] or not spare
        assert_same_solution(*solve_both(tr, levels, T0, EVERY_TERM, graphs), exact=True)
        assert graphs.captures == expected, (before, after)
    # one voxel two cells beyond the (aligned) box along x: the box moves, a new capture
    (ox, oy, oz), (nx, ny, nz) = before = grid_box(tr.voxels)
    v = tr.voxels.voxel_size_m
    far = torch.tensor([[(ox + nx + 2.5) * v, (oy + ny // 2 + 0.5) * v, (oz + nz // 2 + 0.5) * v]], dtype=torch.float64)
    assert mapper.voxels.allocate(far) == 1
    tr.set_map(mapper.voxels.snapshot(), copy.deepcopy(mapper.decoder))
    assert grid_box(tr.voxels) != before
    assert_same_solution(*solve_both(tr, levels, T0, EVERY_TERM, graphs), exact=True)
    assert graphs.captures == expected + 1


def test_a_map_without_a_dense_grid_and_a_decoder_changed_in_place_replay_as_eager():
    """Sorted-code lookups (a map over its grid budget has no dense grid), and a snapshot's decoder changed in place
    after the capture (its parameters' version counters move): the graphs see what the eager solver sees."""
    cap, cfg, mapper = build_room("cpu")
    mapper.voxels.dense_grid_max_cells = 0
    snapshot = (mapper.voxels.snapshot(), copy.deepcopy(mapper.decoder))
    assert snapshot[0].index_grid() is None
    tr, levels = solver_inputs(cap, cfg, mapper, 6, "cpu", snapshot=snapshot)
    T0 = torch.as_tensor(perturbed(cap[6].T_world_cam))
    graphs = tracking_graphs.SolverGraphs(torch.device("cpu"), record=tracking_graphs.record_eagerly)
    assert_same_solution(*solve_both(tr, levels, T0, EVERY_TERM, graphs), exact=True)
    with torch.no_grad():
        for p in tr.decoder.parameters():
            p.mul_(1.05)
    eager, replayed = solve_both(tr, levels, T0, EVERY_TERM, graphs)
    assert_same_solution(eager, replayed, exact=True)
    assert graphs.captures == 1 and not graphs.failed


def test_a_failed_capture_leaves_graphs_off_and_running_out_of_memory_only_for_a_while(caplog):
    cap, cfg, mapper = build_room("cpu")
    tr, levels = solver_inputs(cap, cfg, mapper, 6, "cpu")
    T0 = torch.as_tensor(perturbed(cap[6].T_world_cam))
    calls = []

    def out_of_memory(fn):  # noqa: ANN001, ANN202
        calls.append(1)
        raise torch.OutOfMemoryError("CUDA out of memory (a stand-in)")

    graphs = tracking_graphs.SolverGraphs(torch.device("cpu"), record=out_of_memory)
    with caplog.at_level(logging.WARNING, logger="voxfusion.tracking"):
        for _ in range(tracking_graphs.OOM_BACKOFF_FRAMES + 2):
            assert graphs.solve(tr.voxels, tr.decoder, levels, T0, EVERY_TERM, tr._reference) is None
    assert not graphs.failed and len(calls) == 2  # tried, backed off for OOM_BACKOFF_FRAMES solves, tried again
    assert sum("out of device memory" in r.getMessage() for r in caplog.records) == 2

    def refused(fn):  # noqa: ANN001, ANN202
        calls.append(1)
        raise RuntimeError("operation not permitted when stream is capturing")

    graphs = tracking_graphs.SolverGraphs(torch.device("cpu"), record=refused)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="voxfusion.tracking"):
        for _ in range(3):
            assert graphs.solve(tr.voxels, tr.decoder, levels, T0, EVERY_TERM, tr._reference) is None
    assert graphs.failed and len(calls) == 3  # one attempt, then eager for good
    assert sum("capture or replay failed" in r.getMessage() for r in caplog.records) == 1


def test_the_stages_read_only_the_map_tensors_the_graphs_copy():
    """The stages on a map with a dense grid whose tensors outside :data:`GRID_MAP_TENSORS` and the grid hold garbage
    give the same solution: a snapshot's other tensors never reach the graphs, so :class:`StaticMap` need not copy
    them (without a grid it copies :data:`MAP_TENSORS`, the map without a grid test's case)."""
    cap, cfg, mapper = build_room("cpu")
    tr, levels = solver_inputs(cap, cfg, mapper, 6, "cpu")
    T0 = torch.as_tensor(perturbed(cap[6].T_world_cam))
    clean = solve_pose(tr.voxels, tr.decoder, levels, T0, EVERY_TERM, tr._reference)
    poisoned = object.__new__(type(tr.voxels))
    poisoned.__dict__.update(tr.voxels.__dict__)
    replaced = []
    for name, value in tr.voxels.__dict__.items():
        if isinstance(value, torch.Tensor) and name not in tracking_graphs.GRID_MAP_TENSORS:
            garbage = torch.full_like(value, True) if value.dtype == torch.bool else torch.full_like(value, -7)
            setattr(poisoned, name, ~value if value.dtype == torch.bool else garbage)
            replaced.append(name)
    assert tr.voxels.index_grid() is not None  # with a dense grid: the sorted codes and activity flags unread too
    assert {"_voxel_codes", "_voxel_hits", "_voxel_surface", "_vertex_codes", "_sorted_voxel_codes",
            "_voxel_active"} <= set(replaced)
    dirty = solve_pose(poisoned, tr.decoder, levels, T0, EVERY_TERM, tr._reference)
    for name in ("T", "cost", "inlier_fraction", "median_residual_m", "n_valid"):
        assert torch.equal(getattr(dirty, name), getattr(clean, name)), name


@cuda
def test_tracker_with_graphs_tracks_as_the_eager_tracker():
    cap, cfg, mapper = build_room("cuda")
    poses = {}
    for graphs in (True, False):
        tr = Tracker(TrackingConfig(method="sdf", cuda_graphs=graphs), cfg.render, use_color=True)
        tr.set_map(mapper.voxels.snapshot(), mapper.decoder)
        tr.remember(frame_to_device(cap[5], "cuda"), cap[5].T_world_cam)
        res = tr.track(frame_to_device(cap[6], "cuda"), perturbed(cap[6].T_world_cam))
        assert not res.lost, res.reason
        assert (tr._graphs is not None) == graphs
        poses[graphs] = res.T_world_cam
    np.testing.assert_allclose(poses[True], poses[False], atol=1e-9, rtol=0)


@cuda
def test_a_stage_that_cannot_be_captured_leaves_the_tracker_eager(monkeypatch, caplog):
    cap, cfg, mapper = build_room("cuda")
    tr, levels = solver_inputs(cap, cfg, mapper, 6, "cuda")
    T0 = torch.as_tensor(perturbed(cap[6].T_world_cam), device="cuda")
    real_step = tracking_graphs.stage_step

    def reads_back(voxels, decoder, stage, prior, state):  # noqa: ANN001, ANN202 - a host read-back: not capturable
        if float(state.cost) < 0:
            raise AssertionError("unreachable")
        return real_step(voxels, decoder, stage, prior, state)

    monkeypatch.setattr(tracking_graphs, "stage_step", reads_back)
    graphs = tracking_graphs.SolverGraphs(torch.device("cuda"))
    with caplog.at_level(logging.WARNING, logger="voxfusion.tracking"):
        assert graphs.solve(tr.voxels, tr.decoder, levels, T0, EVERY_TERM, tr._reference) is None
        assert graphs.solve(tr.voxels, tr.decoder, levels, T0, EVERY_TERM, tr._reference) is None
    assert graphs.failed
    assert len([r for r in caplog.records if "cuda_graphs" in r.getMessage()]) == 1
    # the eager solver still works on the same device afterwards
    sol = solve_pose(tr.voxels, tr.decoder, levels, T0, EVERY_TERM, tr._reference)
    assert torch.isfinite(sol.T).all()
