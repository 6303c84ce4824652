"""CUDA graphs of the occlusion render (``render.cuda_graphs``): :meth:`.slam.SlamSystem.render_depth` on a GPU.

An occlusion image (256x192, depth alone) is ~350 operators: on an H100 it took 11.3-12.0 ms eager
(``bench/results/gpu-nvidia-h100-80gb-hbm3-lease-6.json`` to ``-8.json``), where most operators are cheap and each
costs a launch and the host's time to issue it, plus two read-backs (the samples per ray, the samples inside the map).
:class:`OcclusionGraphs` records the whole image once, :func:`~.volume.render_rays_static` with fixed sizes
(:class:`~.volume.RenderBudget`, measured on the camera's first eager render with some headroom) and no read-back,
over a static copy of the map snapshot (:class:`~..slam.tracking_graphs.StaticMap`, its bounds included) and a static
pose; a render then copies the newest snapshot and the pose in, replays, and reads back one flag with the image. Where
the flag says the budget was short (a ray needed more samples, the rays more field queries, or the walk doubts
itself) that image is rendered eagerly and the budget grows (a new capture at the next render); a new map structure
(:func:`~..slam.tracking_graphs.map_signature`), image size, intrinsics or option set is captured again.

The eager :func:`~.volume.render_depth_image` is the reference: the replayed image equals it up to float rounding
(sums over the budget's empty sample columns), which the CPU tests check with
:func:`~..slam.tracking_graphs.record_eagerly` standing in for the graphs (the same static copies, the same budgets),
and the CUDA tests on a GPU. A capture or replay that runs out of device memory leaves the next renders eager for a
while; any other failure is logged once at WARNING and the session renders eagerly from then on. Off by default until
measured on a GPU (``make bench-gpu``'s render section measures both).
"""

from __future__ import annotations

import dataclasses
import logging
import operator
import threading
import time
from collections import OrderedDict

import numpy as np
import torch
from torch.torch_version import TorchVersion

from ..errors import ValidationError, VoxFusionError
from ..map import VoxelMap
from ..map.field import SDFDecoder
from ..slam.tracking_graphs import Recorder, StaticMap, WarmUp, map_signature, recorder_for
from .raycast import grid_walk_planes
from .volume import (
    RenderBudget,
    RenderConfig,
    RenderedImage,
    _as_tensor,
    camera_directions,
    image_chunk_rays,
    image_rays,
    rays_from_directions,
    render_budget,
    render_rays_fixed,
    render_rays_static,
)

log = logging.getLogger("voxfusion.render")

__all__ = ["OcclusionGraphs", "MAX_GRAPHS", "MAX_CAMERAS", "OOM_BACKOFF_RENDERS"]

MAX_GRAPHS = 2
"""Recorded images an :class:`OcclusionGraphs` keeps (each with its static copy of the map and a memory pool about the
eager render's peak), the least recently used dropped first: a depth-only one and one with colour for the session's
camera."""
MAX_CAMERAS = 4
"""Cameras (intrinsics and size) whose ray directions and budget an :class:`OcclusionGraphs` keeps, least recently used
dropped first (with its graphs)."""
OOM_BACKOFF_RENDERS = 30
"""Renders made eagerly after the device ran out of memory while capturing or replaying (then the graphs try again)."""
_NONZERO_STATIC_WAITS = TorchVersion(torch.__version__) < (2, 6)
"""Before PyTorch 2.6 ``torch.nonzero_static`` on CUDA waits for the host, which a capture refuses: no graphs then."""


def _pixel_directions(K: np.ndarray | torch.Tensor, width: int, height: int, device: torch.device) -> torch.Tensor:
    """Camera-frame directions ``[H W, 3]`` float64 of every pixel, row-major (:func:`~.volume.camera_rays`' rays)."""
    v, u = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float64),
                          torch.arange(width, device=device, dtype=torch.float64), indexing="ij")
    Kt = _as_tensor(K, "K", (3, 3), device).to(torch.float64)
    return camera_directions(Kt, torch.stack([u.reshape(-1), v.reshape(-1)], -1))


def _image(depth: torch.Tensor, valid: torch.Tensor, color: torch.Tensor | None, width: int,
           height: int) -> RenderedImage:
    """The flat ``[H W]`` outputs as a :class:`~.volume.RenderedImage` of fresh tensors (a replay overwrites them)."""
    return RenderedImage(depth.reshape(height, width).clone(), None if color is None
                         else color.reshape(height, width, 3).clone(), valid.reshape(height, width).clone())


@dataclasses.dataclass
class _Camera:
    """A camera's ray directions ``[H W, 3]`` (camera frame, on the map's device) and budget (None: not measured)."""

    directions: torch.Tensor
    budget: RenderBudget | None = None


def _transient(e: Exception) -> bool:
    """Whether a capture or replay failure is the device being short of memory for now (torch's out-of-memory error,
    or a library's allocation failing), not something that will fail again."""
    text = str(e)
    return isinstance(e, torch.OutOfMemoryError) or "out of memory" in text or "ALLOC_FAILED" in text


class _ImageGraph:
    """One recorded image: a map structure, a camera (intrinsics and size), options and a budget."""

    def __init__(self, key: tuple, voxels: VoxelMap, decoder: SDFDecoder, d_cam: torch.Tensor, T: torch.Tensor,
                 config: RenderConfig, budget: RenderBudget, with_color: bool, record: Recorder,
                 warm_up: WarmUp | None) -> None:
        self.key = key
        self.map = StaticMap(voxels, decoder)
        self.d_cam = d_cam
        self.T = T.clone()
        dtype = voxels.embeddings.dtype

        def run() -> tuple[torch.Tensor | None, ...]:
            o, d = rays_from_directions(self.d_cam, self.T, dtype)
            got = render_rays_static(self.map.voxels, self.map.decoder, o, d, config, budget, with_color)
            assert got is not None  # the caller checked that the fixed walk applies
            out, doubt = got
            return (*image_rays(out, with_color), doubt)

        if warm_up is not None:
            warm_up(run)
        self.outputs, self.replay = record(run)

    def render(self, voxels: VoxelMap, decoder: SDFDecoder,
               T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, bool]:
        """Replay at pose ``T`` with the snapshot copied in: ``(depth, valid, color, doubt)`` (one read-back)."""
        self.map.load(voxels, decoder)
        self.T.copy_(T)
        self.replay()
        depth, valid, color, doubt = self.outputs
        return depth, valid, color, bool(doubt)


class OcclusionGraphs:
    """:func:`~.volume.render_depth_image` replayed from CUDA graphs (see the module docstring); one per session.

    Args:
        device: the CUDA device of the maps it will be given.
        record: how an image is recorded (:data:`~..slam.tracking_graphs.Recorder`); None: CUDA graphs on a stream of
            this object's own, each camera's render warmed up there before its first capture. Tests pass
            :func:`~..slam.tracking_graphs.record_eagerly`.

    :meth:`render` returns None where the eager render must run instead: a map without a dense index grid or too long
    for the fixed walk; an image of more rays than one eager call renders (:func:`~.volume.image_chunk_rays`); for
    :data:`OOM_BACKOFF_RENDERS` renders after the device ran out of memory (logged); after any other failure, for
    good (logged once: :attr:`failed`). Bad input (sizes, shapes) raises as the eager render does. Budgets are kept
    per camera (intrinsics and size). Thread-safe (one render at a time). :attr:`captures` / :attr:`capture_s` count
    the images recorded and their host seconds, :attr:`replays` and :attr:`fallbacks` the renders replayed and those
    whose budget was short (benchmarks).
    """

    def __init__(self, device: torch.device, record: Recorder | None = None) -> None:
        self._record, self._warm_up = recorder_for(device, record)
        self._lock = threading.Lock()
        self._graphs: OrderedDict[tuple, _ImageGraph] = OrderedDict()
        """At most :data:`MAX_GRAPHS` recorded images by camera and colour, least recently used first (depth-only
        requests and colour ones alternate without a capture each)."""
        self._cameras: OrderedDict[tuple, _Camera] = OrderedDict()
        """At most :data:`MAX_CAMERAS`, least recently used first."""
        self._warmed: set[tuple] = set()
        """Cameras and colour settings whose render ran eagerly on the capture stream before a first capture."""
        self._backoff = 0
        self.failed = torch.device(device).type == "cuda" and record is None and _NONZERO_STATIC_WAITS
        if self.failed:
            log.warning("render.cuda_graphs: PyTorch %s cannot capture the render (nonzero_static waits for the host "
                        "before 2.6); rendering eagerly", torch.__version__)
        self.captures = 0
        self.capture_s = 0.0
        self.replays = 0
        self.fallbacks = 0

    def render(self, voxels: VoxelMap, decoder: SDFDecoder, K: np.ndarray | torch.Tensor,
               T_world_cam: np.ndarray | torch.Tensor, width: int, height: int, config: RenderConfig,
               with_color: bool = True) -> RenderedImage | None:
        """The image :func:`~.volume.render_depth_image` renders (``K`` ``[3, 3]`` for ``width`` x ``height``,
        ``T_world_cam`` ``[4, 4]``), from the graph of this map structure, camera and options, or None."""
        try:
            width, height = operator.index(width), operator.index(height)
        except TypeError as e:
            raise ValidationError("width/height", f"must be integers, got {width!r} x {height!r}") from e
        if width < 1 or height < 1:
            raise ValidationError("width/height", f"must be positive, got {width} x {height}")
        K_host = _as_tensor(K, "K", (3, 3)).detach().cpu().to(torch.float64)  # checked before any graph work
        T = _as_tensor(T_world_cam, "T_world_cam", (4, 4), voxels.device).to(torch.float64)
        if self.failed or width * height > image_chunk_rays(voxels.device):
            return None
        with self._lock:
            if self._backoff > 0:
                self._backoff -= 1
                return None
            try:
                return self._render(voxels, decoder, K_host, T, width, height, config, with_color)
            except VoxFusionError:
                raise  # bad input, not the graphs' failure
            except Exception as e:  # noqa: BLE001 - capture or replay refused: eager for a while, or for good
                self._graphs.clear()
                first_line = str(e).splitlines()[0] if str(e) else ""
                if _transient(e):  # other sessions or the mapping thread hold the memory now: later
                    self._backoff = OOM_BACKOFF_RENDERS
                    log.warning("render.cuda_graphs: out of device memory (%s); rendering eagerly for %d renders",
                                first_line, OOM_BACKOFF_RENDERS)
                else:
                    self.failed = True
                    log.warning("render.cuda_graphs: CUDA graph capture or replay failed (%s: %s); rendering "
                                "eagerly", type(e).__name__, first_line)
                return None

    def _render(self, voxels: VoxelMap, decoder: SDFDecoder, K: torch.Tensor, T: torch.Tensor, width: int,
                height: int, config: RenderConfig, with_color: bool) -> RenderedImage | None:
        grid = voxels.index_grid() if voxels.voxel_bounds is not None else None
        planes = None if grid is None else grid_walk_planes(grid)
        if planes is None:  # no dense grid, or a map too long for the fixed walk
            return None
        camera = (width, height, tuple(K.ravel().tolist()))
        cam = self._camera(camera, K, voxels.device)
        budget = cam.budget
        if budget is not None and budget.planes < planes:
            budget = None  # the grid grew: measure again
        if budget is not None:
            slot = (camera, with_color)
            key = (map_signature(voxels, decoder), config, budget)
            graph = self._graphs.get(slot)
            if graph is None or graph.key != key:
                self._graphs.pop(slot, None)
                graph = None  # the old graph's memory goes back before the new one takes its own
                while len(self._graphs) >= MAX_GRAPHS:
                    self._graphs.popitem(last=False)
                t0 = time.perf_counter()
                warm_up = self._warm_up if slot not in self._warmed else None  # lazy set-ups happen once per stream
                graph = _ImageGraph(key, voxels, decoder, cam.directions, T, config, budget, with_color,
                                    self._record, warm_up)
                self._warmed.add(slot)
                self._graphs[slot] = graph
                self.captures += 1
                self.capture_s += time.perf_counter() - t0
            self._graphs.move_to_end(slot)
            depth, valid, color, doubt = graph.render(voxels, decoder, T)
            self.replays += 1
            if not doubt:
                return _image(depth, valid, color, width, height)
            self.fallbacks += 1
        # eager: the camera's first render, or one its budget fell short of; it sets the budget for the next
        o, d = rays_from_directions(cam.directions, T, voxels.embeddings.dtype)
        out = render_rays_fixed(voxels, decoder, o, d, config, with_color)
        if out is None:
            return None
        measured = render_budget(voxels, out)
        if measured is not None:
            merged = measured if cam.budget is None else RenderBudget(
                *(max(a, b) for a, b in zip(dataclasses.astuple(cam.budget), dataclasses.astuple(measured),
                                            strict=True)))
            # no more queries than the image has samples (the budget's padding is evaluated at every replay)
            cam.budget = dataclasses.replace(merged, queries=min(merged.queries, width * height * merged.samples))
        depth, valid, color = image_rays(out, with_color)
        return _image(depth, valid, color, width, height)

    def _camera(self, camera: tuple, K: torch.Tensor, device: torch.device) -> _Camera:
        """The :class:`_Camera` of ``camera`` (``(width, height, K's values)``), made on first use; the least recently
        used beyond :data:`MAX_CAMERAS` is dropped with its graphs."""
        cam = self._cameras.get(camera)
        if cam is None:
            cam = self._cameras[camera] = _Camera(_pixel_directions(K, camera[0], camera[1], device))
            while len(self._cameras) > MAX_CAMERAS:
                gone, _ = self._cameras.popitem(last=False)
                for slot in [s for s in self._graphs if s[0] == gone]:
                    del self._graphs[slot]
                self._warmed = {s for s in self._warmed if s[0] != gone}
        self._cameras.move_to_end(camera)
        return cam
