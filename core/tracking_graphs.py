"""CUDA graphs of the geometric tracker's solver stages (``tracking.cuda_graphs``).

On a GPU the ``sdf`` tracker's work is small (a few thousand points) and its cost is launches: one field
evaluation with its normal equations is ~340 operators, each a kernel launch of several microseconds of host time,
so an iteration took 5.8 ms on an H100 (bench/results/gpu-nvidia-h100-80gb-hbm3-lease.json) though its arithmetic
takes a fraction of that. A CUDA graph records a stage's kernels once and replays them with one launch.

:class:`SolverGraphs` captures, per solver stage (:func:`~.tracking_sdf.solver_stages`), two graphs: the stage's
start (:func:`~.tracking_sdf.stage_start`) and one Levenberg-Marquardt iteration
(:func:`~.tracking_sdf.stage_step`, writing its new state over the old one in place), over static copies of the
frame's inputs (the points of each level, the frame-to-frame reference, the start pose). A frame then copies its
inputs into those buffers and replays: the same loop as the eager :func:`~.tracking_sdf.solve_pose`
(:func:`~.tracking_sdf.iterate_stage`: the convergence test reads the proposed step back every ``check_every``
iterations), the same operators, so the same results. A graph holds the map snapshot's tensors, so a new snapshot
(a mapping round) is captured again; so is a change of shapes or options. Capture uses the low-level API
(``CUDAGraph.capture_begin``, thread-local capture mode, a stream of its own) so that it neither synchronises
the device nor empties the allocator's cache under a mapping thread running beside it.

Anything that fails while capturing or replaying (an operator that cannot be captured, a driver refusal) is
logged once at WARNING and the tracker stays eager (:func:`~.tracking_sdf.solve_pose`) for the rest of the
session. The eager path is the reference: CUDA tests hold the replayed solution to it, and CPU tests check that
the stages never wait for the host or copy from it (what capture forbids).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from .errors import VoxFusionError
from .field import SDFDecoder
from .tracking_sdf import (
    DepthReference,
    LMState,
    SdfPoints,
    SdfSolution,
    SdfSolverConfig,
    SolverPrior,
    iterate_stage,
    solution,
    solver_prior,
    solver_stages,
    stage_start,
    stage_step,
)
from .voxels import VoxelMap

log = logging.getLogger("voxfusion.tracking")

__all__ = ["SolverGraphs"]


def _state_tensors(state: LMState) -> list[torch.Tensor]:
    """Every tensor of ``state`` in a fixed order (its terms' None fields skipped)."""
    *head, terms = state
    return [*head, *(t for t in terms if t is not None)]


def _optional_clone(t: torch.Tensor | None) -> torch.Tensor | None:
    return None if t is None else t.clone()


def _signature(t: torch.Tensor | None) -> tuple | None:
    return None if t is None else (tuple(t.shape), t.dtype, t.device)


def _points_signature(pts: SdfPoints) -> tuple:
    return tuple(_signature(t) for t in (pts.p_cam, pts.gray, pts.gray_blurred))


def _reference_signature(ref: DepthReference | None) -> tuple | None:
    if ref is None:
        return None
    return (ref.baseline_px, *(_signature(getattr(ref, f)) for f in _REFERENCE_INPUTS), _signature(ref.offsets))


_REFERENCE_INPUTS = ("depth_padded", "K", "T_ref_world", "gray", "gray_blurred")
"""The :class:`DepthReference` tensors a frame copies into the static reference (``offsets`` depends only on the
image width and the baseline, which the capture's key holds)."""


@contextmanager
def _capturing(graph: torch.cuda.CUDAGraph, stream: torch.cuda.Stream) -> Iterator[None]:
    """Record the block's kernels into ``graph`` on ``stream`` (after the current stream's work; the current stream
    waits for it after). Unlike ``torch.cuda.graph`` it neither synchronises the device nor empties the cache."""
    current = torch.cuda.current_stream(stream.device)
    stream.wait_stream(current)
    with torch.cuda.stream(stream):
        graph.capture_begin(capture_error_mode="thread_local")
        try:
            yield
        except BaseException:
            try:
                graph.capture_end()
            except Exception:  # noqa: BLE001 - the capture is broken already; the block's error is the one to report
                pass
            raise
        graph.capture_end()
    current.wait_stream(stream)


class _GraphSet:
    """The captured stages of one map snapshot and one input signature, with their static inputs and states."""

    def __init__(self, key: tuple, voxels: VoxelMap, decoder: SDFDecoder, levels: list[SdfPoints],
                 T_init: torch.Tensor, cfg: SdfSolverConfig, reference: DepthReference | None,
                 stream: torch.cuda.Stream, warm_up: bool) -> None:
        self.key = key
        self.voxels, self.decoder = voxels, decoder  # held: the graphs read their tensors
        self.levels = [SdfPoints(p.p_cam.clone(), _optional_clone(p.gray), _optional_clone(p.gray_blurred))
                       for p in levels]
        self.reference = None if reference is None else dataclasses.replace(
            reference, **{f: _optional_clone(getattr(reference, f)) for f in _REFERENCE_INPUTS},
            offsets=reference.offsets.clone())
        self.T0 = T_init.to(torch.float64).clone()
        self.xi0 = torch.zeros(6, dtype=torch.float64, device=self.T0.device)
        self.prior_info = cfg.prior_info
        self.prior: SolverPrior = solver_prior(cfg, self.levels, self.T0.device)
        self.stages = solver_stages(self.levels, cfg, self.reference)
        voxels.index_grid()  # built before capture (a snapshot has it already): building it reads sizes back
        if warm_up:  # lazy initialisations (library handles, workspaces) happen outside any capture
            stream.wait_stream(torch.cuda.current_stream(stream.device))
            with torch.cuda.stream(stream):
                state = None
                for stage in self.stages:
                    state = self._start(stage, state)
                    state = stage_step(voxels, decoder, stage, self.prior, state)
            torch.cuda.current_stream(stream.device).wait_stream(stream)
        self.states: list[LMState] = []
        self.graphs: list[tuple[torch.cuda.CUDAGraph, torch.cuda.CUDAGraph]] = []
        for stage in self.stages:
            g_start, g_step = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
            with _capturing(g_start, stream):
                state = self._start(stage, self.states[-1] if self.states else None)
            with _capturing(g_step, stream):
                new = stage_step(voxels, decoder, stage, self.prior, state)
                for dst, src in zip(_state_tensors(state), _state_tensors(new), strict=True):
                    dst.copy_(src)
            self.states.append(state)
            self.graphs.append((g_start, g_step))

    def _start(self, stage, previous: LMState | None) -> LMState:  # noqa: ANN001 - a SolverStage
        T, xi = (self.T0, self.xi0) if previous is None else (previous.T, previous.xi)
        return stage_start(self.voxels, self.decoder, stage, self.prior, T, xi,
                           None if previous is None else previous.terms)

    def run(self, levels: list[SdfPoints], T_init: torch.Tensor, cfg: SdfSolverConfig,
            reference: DepthReference | None) -> SdfSolution:
        """Copy this frame's inputs into the static buffers and replay the stages."""
        for static, pts in zip(self.levels, levels, strict=True):
            for dst, src in zip(static, (pts.p_cam, pts.gray, pts.gray_blurred), strict=True):
                if dst is not None:
                    dst.copy_(src)
        if reference is not None:
            for f in _REFERENCE_INPUTS:
                dst = getattr(self.reference, f)
                if dst is not None:
                    dst.copy_(getattr(reference, f))
        self.T0.copy_(T_init)
        if cfg.prior_info != self.prior_info:  # the device prior comes and goes with the frames' device poses
            self.prior.info.copy_(solver_prior(cfg, self.levels, self.T0.device).info)
            self.prior_info = cfg.prior_info
        iterations = 0
        for stage, state, (g_start, g_step) in zip(self.stages, self.states, self.graphs, strict=True):
            g_start.replay()
            state, n = iterate_stage(state, stage, lambda s, g=g_step: (g.replay(), s)[1])
            iterations += n
        return solution(self.states[-1], cfg, iterations)


class SolverGraphs:
    """:func:`~.tracking_sdf.solve_pose` replayed from CUDA graphs (see the module docstring); one per tracker.

    Args:
        device: the CUDA device of the maps it will be given.

    :meth:`solve` returns None where the eager solver must run instead: ``cfg.compile`` (the compiled solver is
    not captured), or after a failure (logged once; :attr:`failed`). :attr:`captures` counts the graph sets built
    (one per map snapshot and input signature) and :attr:`capture_s` the host seconds they took (benchmarks).
    """

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.stream = torch.cuda.Stream(device)
        self.failed = False
        self.captures = 0
        self.capture_s = 0.0
        self._set: _GraphSet | None = None

    def solve(self, voxels: VoxelMap, decoder: SDFDecoder, levels: list[SdfPoints], T_init: torch.Tensor,
              cfg: SdfSolverConfig, reference: DepthReference | None = None) -> SdfSolution | None:
        """:func:`~.tracking_sdf.solve_pose`'s solution from the graphs of this snapshot and signature (captured on
        first use), or None (run the eager solver)."""
        if self.failed or cfg.compile:
            return None
        key = (id(voxels), id(decoder), dataclasses.replace(cfg, prior_info=(0.0, 0.0)),
               tuple(_points_signature(p) for p in levels), _reference_signature(reference), _signature(T_init))
        try:
            if self._set is None or self._set.key != key:
                self._set = None  # the old graphs' memory goes back before the new ones take theirs
                t0 = time.perf_counter()
                self._set = _GraphSet(key, voxels, decoder, levels, T_init, cfg, reference, self.stream,
                                      warm_up=self.captures == 0)
                self.captures += 1
                self.capture_s += time.perf_counter() - t0
            return self._set.run(levels, T_init, cfg, reference)
        except VoxFusionError:
            raise  # bad input, not the graphs' failure
        except Exception as e:  # noqa: BLE001 - capture or replay refused: warn once, stay eager
            first_line = str(e).splitlines()[0] if str(e) else ""
            log.warning("tracking.cuda_graphs: CUDA graph capture or replay failed (%s: %s); tracking eagerly",
                        type(e).__name__, first_line)
            self.failed = True
            self._set = None
            return None
