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
iterations), the same operators, so the same results. The graphs read a copy of the map snapshot
(:class:`StaticMap`, with spare rows for voxels the map allocates): a new snapshot of the same structure is copied into
it; a map that outgrew its spare rows or its index grid's box, or a change of input shapes or options, is captured
again (~75-105 ms of host time per capture on an H100 machine at the paper preset; ``python
bench/bench_map_structure.py``: 1 and 0 captures after the first in 200 mapping rounds of the synthetic room and
7-Scenes, against 71 and 73 without spare rows and 9 and 3 with a tight index-grid box). Capture uses the low-level API
(``CUDAGraph.capture_begin``, thread-local capture mode, a stream of its own) so that it neither synchronises the
device nor empties the allocator's cache under a mapping thread running beside it.

Anything that fails while capturing or replaying (an operator that cannot be captured, a driver refusal) is
logged once at WARNING and the tracker stays eager (:func:`~.tracking_sdf.solve_pose`) for the rest of the
session. The eager path is the reference: CUDA tests hold the replayed solution to it, and CPU tests check that
the stages never wait for the host or copy from it (what capture forbids).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable

import torch

from ..errors import VoxFusionError
from ..map import VoxelMap
from ..map.field import SDFDecoder
from ..map.index_grid import VoxelIndexGrid
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

log = logging.getLogger("voxfusion.tracking")

__all__ = ["SolverGraphs", "CudaGraphRecorder", "record_eagerly", "recorder_for", "Recorder", "WarmUp", "StaticMap",
           "map_signature", "MAP_TENSORS", "GRID_MAP_TENSORS", "MIN_CAPACITY_ROWS", "OOM_BACKOFF_FRAMES"]


def _state_tensors(state: LMState) -> list[torch.Tensor]:
    """Every tensor of ``state`` in a fixed order (its terms' None fields skipped)."""
    *head, terms = state
    return [*head, *(t for t in terms if t is not None)]


def _point_tensors(pts: SdfPoints) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    return pts.p_cam, pts.gray, pts.gray_blurred


def _optional_clone(t: torch.Tensor | None) -> torch.Tensor | None:
    return None if t is None else t.clone()


def _signature(t: torch.Tensor | None) -> tuple | None:
    return None if t is None else (tuple(t.shape), t.dtype, t.device)


def _points_signature(pts: SdfPoints) -> tuple:
    return tuple(_signature(t) for t in _point_tensors(pts))


def _reference_signature(ref: DepthReference | None) -> tuple | None:
    if ref is None:
        return None
    return (ref.baseline_px, *(_signature(getattr(ref, f)) for f in _REFERENCE_INPUTS), _signature(ref.offsets))


_REFERENCE_INPUTS = ("depth_padded", "K", "T_ref_world", "gray", "gray_blurred", "older_depth", "T_older_world",
                     "older_weights")
"""The :class:`DepthReference` tensors a frame copies into the static reference (``offsets`` depends only on the
image width and the baseline, which the capture's key holds)."""


Recorded = LMState | tuple[torch.Tensor | None, ...] | None
"""What a recorded block returns: a solver state, or a tuple of tensors (the occlusion render's,
:mod:`.render.graphs`)."""
Recorder = Callable[[Callable[[], Recorded]], tuple[Recorded, Callable[[], None]]]
"""Records a block: ``record(fn) -> (fn's output, replay)``; after ``replay()`` the output's tensors hold what ``fn``
would return on the inputs' current values. :class:`CudaGraphRecorder` on a GPU; :func:`record_eagerly` (``fn`` run
again at each replay) is its CPU stand-in, for tests of everything around the graphs."""


class CudaGraphRecorder:
    """A :data:`Recorder` of CUDA graphs captured on ``stream`` (after the current stream's work; the current stream
    waits for it after), in thread-local capture mode. Unlike ``torch.cuda.graph`` it neither synchronises the
    device nor empties the allocator's cache, which would stall a mapping thread running beside it."""

    def __init__(self, stream: torch.cuda.Stream) -> None:
        self.stream = stream

    def __call__(self, fn: Callable[[], Recorded]) -> tuple[Recorded, Callable[[], None]]:
        graph = torch.cuda.CUDAGraph()
        current = torch.cuda.current_stream(self.stream.device)
        self.stream.wait_stream(current)
        with torch.cuda.stream(self.stream):
            graph.capture_begin(capture_error_mode="thread_local")
            try:
                out = fn()
            except BaseException:
                try:
                    graph.capture_end()
                except Exception:  # noqa: BLE001 - the capture is broken already; fn's error is the one to report
                    pass
                raise
            graph.capture_end()
        current.wait_stream(self.stream)
        return out, graph.replay

    def warm_up(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` eagerly on the capture stream: lazy initialisations (library handles, their workspaces on this
        stream) happen outside any capture."""
        current = torch.cuda.current_stream(self.stream.device)
        self.stream.wait_stream(current)
        with torch.cuda.stream(self.stream):
            fn()
        current.wait_stream(self.stream)


WarmUp = Callable[[Callable[[], None]], None]
"""Runs a block eagerly where its graphs will be captured (:meth:`CudaGraphRecorder.warm_up`)."""


def recorder_for(device: torch.device, record: Recorder | None = None) -> tuple[Recorder, WarmUp | None]:
    """What records a graph user's blocks: ``record`` as given (tests pass :func:`record_eagerly`), without a warm-up;
    None: CUDA graphs on a new stream of ``device`` (:class:`CudaGraphRecorder`) and its warm-up."""
    if record is not None:
        return record, None
    recorder = CudaGraphRecorder(torch.cuda.Stream(device))
    return recorder, recorder.warm_up


def record_eagerly(fn: Callable[[], Recorded]) -> tuple[Recorded, Callable[[], None]]:
    """The CPU stand-in :data:`Recorder`: ``fn`` runs now, and again at each replay, its new output copied into the
    first one's tensors (what a graph replay does to its static outputs)."""
    out = fn()

    def replay() -> None:
        new = fn()
        if out is not None and new is not None:
            _copy_state(out, new)

    return out, replay


def _copy_state(dst: LMState | tuple[torch.Tensor | None, ...], src: LMState | tuple[torch.Tensor | None, ...]) -> None:
    pairs = zip(_state_tensors(dst), _state_tensors(src), strict=True) if isinstance(dst, LMState) \
        else zip(dst, src, strict=True)
    for d, t in pairs:
        if d is not None:
            d.copy_(t)


MAP_TENSORS = ("embeddings", "_voxel_coords", "_voxel_vertex_ids", "_sorted_voxel_codes", "_voxel_perm",
               "_voxel_active")
"""The :class:`~.map.VoxelMap` tensors the solver's stages read, besides its level-0 index grid (the tests run the
stages on a map whose other tensors hold garbage): what :class:`StaticMap` copies."""
GRID_MAP_TENSORS = MAP_TENSORS[:3]
"""Those of them the stages read when the map has a dense level-0 grid (the others serve sorted-code lookups)."""
MIN_CAPACITY_ROWS = 4096
"""With a dense grid the static copies of :data:`GRID_MAP_TENSORS` have room for more rows (voxels, vertices) than the
snapshot holds: the next power of two, at least this many, so a map that allocates voxels is copied in until it
outgrows that, instead of being captured again at every mapping round that allocated. Only the snapshot's rows are
copied in and no stage reads past them, so the spare rows cost memory only (4096 rows: ~0.6 MB). ``python
bench/bench_map_structure.py`` (200 mapping rounds; the grid's box aligned,
:data:`~.map.voxel_map.LEVEL0_GRID_ALIGN`): synthetic room / 7-Scenes 1 / 0 captures after the first, against
71 / 73 without spare rows."""


def _level0_grid(voxels: VoxelMap) -> VoxelIndexGrid | None:
    """The dense index grid the stages' lookups use (None over the map's grid budget: sorted-code lookups)."""
    return voxels.index_grid()  # a snapshot has it built already; the first build reads sizes back (never in capture)


def _capacity(rows: int) -> int:
    return max(MIN_CAPACITY_ROWS, 1 << max(0, rows - 1).bit_length())


def _read_tensors(voxels: VoxelMap) -> tuple[str, ...]:
    """The map tensors the stages read: :data:`GRID_MAP_TENSORS` with a dense grid, else :data:`MAP_TENSORS`."""
    return GRID_MAP_TENSORS if _level0_grid(voxels) is not None else MAP_TENSORS


def _map_tensors(voxels: VoxelMap, decoder: SDFDecoder) -> list[torch.Tensor | None]:
    """What a capture reads of a map, in a fixed order: :func:`_read_tensors`, the level-0 grid's table (None without
    a grid), the voxel bounds (the occlusion render's ray clipping; None for an empty map) and the decoder's
    parameters and buffers."""
    grid = _level0_grid(voxels)
    return [*(getattr(voxels, n) for n in _read_tensors(voxels)), None if grid is None else grid.table,
            *(voxels.voxel_bounds or (None, None)), *decoder.state_dict(keep_vars=True).values()]


class StaticMap:
    """A copy of a map snapshot (``voxels``, ``decoder``) whose tensors stay where they are: the graphs read these.
    :meth:`load` copies a map of the same :func:`map_signature` in (a later snapshot after a mapping round, or the
    same one changed in place: each tensor is copied when it is another tensor or its version counter moved),
    instead of a new capture. With a dense grid the voxel and vertex tables have spare rows (:data:`MIN_CAPACITY_ROWS`),
    which no lookup reaches: the grid holds indices of the snapshot's own voxels only."""

    def __init__(self, voxels: VoxelMap, decoder: SDFDecoder) -> None:
        static = object.__new__(type(voxels))
        static.__dict__.update(voxels.__dict__)  # its other tensors are never read by the stages (MAP_TENSORS)
        grid = _level0_grid(voxels)
        for name in _read_tensors(voxels):
            t = getattr(voxels, name).detach()
            if grid is not None:  # room to grow: the rows past the snapshot's are zeros (valid indices, never used)
                copy_ = t.new_zeros((_capacity(t.shape[0]), *t.shape[1:]))
                copy_[:t.shape[0]] = t
            else:
                copy_ = t.clone()
            setattr(static, name, torch.nn.Parameter(copy_, requires_grad=False) if name == "embeddings" else copy_)
        static._grids = {0: None if grid is None else dataclasses.replace(grid, table=grid.table.clone())}
        if voxels.voxel_bounds is not None:  # the render clips its rays to them; they grow inside the grid's box
            static._bounds = tuple(b.clone() for b in voxels.voxel_bounds)
        self.voxels = static
        self.decoder = decoder.frozen_copy()
        self._targets = _map_tensors(static, self.decoder)
        self._loaded = [(t, None if t is None else t._version) for t in _map_tensors(voxels, decoder)]

    @torch.no_grad()
    def load(self, voxels: VoxelMap, decoder: SDFDecoder) -> None:
        """Copy in what differs from what was last copied (``voxels`` and ``decoder`` of this signature)."""
        for k, (dst, src) in enumerate(zip(self._targets, _map_tensors(voxels, decoder), strict=True)):
            if src is None or dst is None:
                continue
            loaded, version = self._loaded[k]
            if src is not loaded or src._version != version:  # snapshots share their index tables until they change
                (dst if dst.shape == src.shape else dst[:src.shape[0]]).copy_(src)  # spare rows past the snapshot's
                self._loaded[k] = (src, src._version)


def map_signature(voxels: VoxelMap, decoder: SDFDecoder) -> tuple:
    """What a capture depends on besides the values: the map's settings (its Python scalars), the shapes of the
    tensors the stages read (:func:`_read_tensors`; with a dense grid their row capacity, not their rows) and of its
    level-0 index grid (with its Python-int geometry, which the lookups bake in), and the decoder's class,
    configuration and parameter shapes. With a dense grid the count of inactive voxels is left out (only sorted-code
    lookups read it)."""
    grid = _level0_grid(voxels)
    skip = {"_n_inactive"} if grid is not None else set()
    scalars = tuple(sorted((k, v) for k, v in voxels.__dict__.items()
                           if isinstance(v, (bool, int, float, str)) and k not in skip))
    tensors = []
    for name in _read_tensors(voxels):
        t = getattr(voxels, name)
        rows = _capacity(t.shape[0]) if grid is not None else t.shape[0]
        tensors.append(((rows, *t.shape[1:]), t.dtype, t.device))
    grid_sig = None if grid is None else (grid.origin_xyz, grid.shape, grid.level, grid.border, _signature(grid.table))
    params = tuple((k, _signature(v)) for k, v in decoder.state_dict(keep_vars=True).items())
    return (type(voxels), scalars, tuple(tensors), grid_sig, type(decoder), repr(decoder.config), params)


class _GraphSet:
    """The recorded stages of one map snapshot and one input signature, with their static inputs and states."""

    def __init__(self, key: tuple, voxels: VoxelMap, decoder: SDFDecoder, levels: list[SdfPoints],
                 T_init: torch.Tensor, cfg: SdfSolverConfig, reference: DepthReference | None,
                 record: Recorder, warm_up: WarmUp | None) -> None:
        self.key = key
        self.map = StaticMap(voxels, decoder)
        self.voxels, self.decoder = self.map.voxels, self.map.decoder  # what the graphs read
        self.levels = [SdfPoints(*(_optional_clone(t) for t in _point_tensors(p))) for p in levels]
        self.reference = None if reference is None else dataclasses.replace(
            reference, **{f: _optional_clone(getattr(reference, f)) for f in _REFERENCE_INPUTS},
            offsets=reference.offsets.clone())
        self.T0 = T_init.to(torch.float64).clone()
        self.xi0 = torch.zeros(6, dtype=torch.float64, device=self.T0.device)
        self.prior_info = cfg.prior_info
        self.prior: SolverPrior = solver_prior(cfg, self.levels, self.T0.device)
        self.stages = solver_stages(self.levels, cfg, self.reference)
        if warm_up is not None:
            warm_up(self._run_once)
        self.states: list[LMState] = []
        self.replays: list[tuple[Callable[[], None], Callable[[], None]]] = []
        for stage in self.stages:
            previous = self.states[-1] if self.states else None
            state, replay_start = record(lambda st=stage, prev=previous: self._start(st, prev))
            assert state is not None

            def step(st=stage, state=state) -> None:  # noqa: ANN001 - the new state written over the old one
                _copy_state(state, stage_step(self.voxels, self.decoder, st, self.prior, state))

            _, replay_step = record(step)
            self.states.append(state)
            self.replays.append((replay_start, replay_step))

    def _run_once(self) -> None:
        """Each stage's start and one step, eagerly (the warm-up)."""
        state = None
        for stage in self.stages:
            state = self._start(stage, state)
            state = stage_step(self.voxels, self.decoder, stage, self.prior, state)

    def _start(self, stage, previous: LMState | None) -> LMState:  # noqa: ANN001 - a SolverStage
        T, xi = (self.T0, self.xi0) if previous is None else (previous.T, previous.xi)
        return stage_start(self.voxels, self.decoder, stage, self.prior, T, xi,
                           None if previous is None else previous.terms)

    def run(self, voxels: VoxelMap, decoder: SDFDecoder, levels: list[SdfPoints], T_init: torch.Tensor,
            cfg: SdfSolverConfig, reference: DepthReference | None) -> SdfSolution:
        """Copy this frame's inputs (and the snapshot, when it is another one of the same structure) into the static
        buffers and replay the stages."""
        self.map.load(voxels, decoder)
        for static, pts in zip(self.levels, levels, strict=True):
            for dst, src in zip(_point_tensors(static), _point_tensors(pts), strict=True):
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
        for stage, state, (replay_start, replay_step) in zip(self.stages, self.states, self.replays, strict=True):
            replay_start()

            def step(s: LMState, replay: Callable[[], None] = replay_step) -> LMState:
                replay()  # writes the new state over s (the stage's static state)
                return s

            state, n = iterate_stage(state, stage, step)
            iterations += n
        return solution(self.states[-1], cfg, iterations)


OOM_BACKOFF_FRAMES = 30
"""After running out of device memory while capturing, the solves (frames) that run eagerly before another try."""


class SolverGraphs:
    """:func:`~.tracking_sdf.solve_pose` replayed from CUDA graphs (see the module docstring); one per tracker.

    Args:
        device: the CUDA device of the maps it will be given (its capture stream's).
        record: how blocks are recorded (:data:`Recorder`); None: CUDA graphs on a stream of this object's own
            (:class:`CudaGraphRecorder`, warmed up before the first capture of each input signature). Tests pass
            :func:`record_eagerly`.

    :meth:`solve` returns None where the eager solver must run instead: ``cfg.compile`` (the compiled solver is
    not captured); for :data:`OOM_BACKOFF_FRAMES` solves after the device ran out of memory while capturing (logged;
    then it tries again); after any other failure, for good (logged once; :attr:`failed`). :attr:`captures` counts
    the graph sets built (one per map structure and input signature) and :attr:`capture_s` the host seconds they
    took (benchmarks).
    """

    def __init__(self, device: torch.device, record: Recorder | None = None) -> None:
        self._record, self._warm_up = recorder_for(device, record)
        self._warmed: set[tuple] = set()
        """Input signatures (the key without the map's) whose code paths ran eagerly on the capture stream."""
        self._backoff = 0
        self.failed = False
        self.captures = 0
        self.capture_s = 0.0
        self._set: _GraphSet | None = None

    def solve(self, voxels: VoxelMap, decoder: SDFDecoder, levels: list[SdfPoints], T_init: torch.Tensor,
              cfg: SdfSolverConfig, reference: DepthReference | None = None) -> SdfSolution | None:
        """:func:`~.tracking_sdf.solve_pose`'s solution from the graphs of this map structure and input signature
        (captured on first use), or None (run the eager solver)."""
        if self.failed or cfg.compile:
            return None
        if self._backoff > 0:
            self._backoff -= 1
            return None
        try:
            inputs = (dataclasses.replace(cfg, prior_info=(0.0, 0.0)), tuple(_points_signature(p) for p in levels),
                      _reference_signature(reference), _signature(T_init))
            key = (map_signature(voxels, decoder), *inputs)
            if self._set is None or self._set.key != key:
                self._set = None  # the old graphs' memory goes back before the new ones take theirs
                t0 = time.perf_counter()
                warm_up = self._warm_up if inputs not in self._warmed else None
                self._set = _GraphSet(key, voxels, decoder, levels, T_init, cfg, reference, self._record, warm_up)
                self._warmed.add(inputs)
                self.captures += 1
                self.capture_s += time.perf_counter() - t0
            return self._set.run(voxels, decoder, levels, T_init, cfg, reference)
        except VoxFusionError:
            raise  # bad input, not the graphs' failure
        except torch.OutOfMemoryError:  # another session or the mapping thread holds the memory now: later
            self._set = None
            self._backoff = OOM_BACKOFF_FRAMES
            log.warning("tracking.cuda_graphs: out of device memory while capturing; tracking eagerly for %d frames",
                        OOM_BACKOFF_FRAMES)
            return None
        except Exception as e:  # noqa: BLE001 - capture or replay refused: warn once, stay eager
            first_line = str(e).splitlines()[0] if str(e) else ""
            log.warning("tracking.cuda_graphs: CUDA graph capture or replay failed (%s: %s); tracking eagerly",
                        type(e).__name__, first_line)
            self.failed = True
            self._set = None
            return None
