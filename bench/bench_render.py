"""Ray-voxel intersection, point lookup and one mapping step: the reference path against the fast path.

Usage (from the repository root)::

    python bench/bench_render.py                              # 0.2 / 0.1 / 0.05 m voxels, 2 devices if any
    python bench/bench_render.py --voxel-sizes 0.2 --repeats 9 --threads 1

Map: the synthetic room (320x240, seed 0), the back-projected depth of every 5th of its first 100 frames
allocated at each voxel size. Scenarios:

* ``intersect/mapping``: 5 frames x 1024 random valid pixels with ``t_far = depth + tr``, the batch of
  :meth:`~voxfusion.core.slam.mapping.Mapper.step`.
* ``intersect/image``: every pixel of one 320x240 view, no ``t_far``, in 4096-ray chunks as
  :func:`~voxfusion.core.render.render_depth_image` casts them (the whole image is timed).
* ``lookup``: 200k random points in the map's bounding box -> voxel index (``field.query``, meshing).
* ``mapping step``: one full :meth:`Mapper.step` (rays, intersection, sampling, MLP, losses, backward,
  Adam) on the same 5 x 1024 rays; ``before`` swaps the renderer's intersection for the reference.

``before`` is :func:`~voxfusion.core.render.intersect_voxels_reference` (all grid-plane crossings, Morton
codes, ``searchsorted``) and the sorted-code point lookup; ``after`` is :func:`intersect_voxels` (dense
index grid, empty-space skipping) and :meth:`VoxelMap.lookup_voxels`. Both run in the same process,
interleaved (before, after, after, before, ...) so a shared machine's load hits both alike; the table
reports medians of wall-clock and of the process CPU time (robust to waiting for a busy CPU). Every
``after`` result is checked identical to ``before`` first. Writes ``bench/results/render.json`` with
:func:`bench.machine.machine_info`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402

import voxfusion.core.render.raycast as raycast  # noqa: E402
import voxfusion.core.render.volume as render  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.eval.report import write_json  # noqa: E402
from voxfusion.core.framedata import frame_to_device, sample_pixels  # noqa: E402
from voxfusion.core.losses import LossConfig  # noqa: E402
from voxfusion.core.map import VoxelMap, morton_encode  # noqa: E402
from voxfusion.core.map.field import FieldConfig  # noqa: E402
from voxfusion.core.map.morton import MORTON_MAX_COORD, MORTON_MIN_COORD  # noqa: E402
from voxfusion.core.render.volume import RenderConfig, camera_rays, intersect_voxels, intersect_voxels_reference  # noqa: E402
from voxfusion.core.slam.mapping import Mapper, MappingConfig  # noqa: E402

WIDTH, HEIGHT, N_FRAMES, EVERY = 320, 240, 100, 5
WINDOW, RAYS_PER_FRAME, IMAGE_CHUNK, LOOKUP_POINTS = 5, 1024, 4096, 200_000


@dataclass(frozen=True)
class Row:
    scenario: str
    voxel_size_m: float
    n_voxels: int
    n_items: int
    """Rays (intersection, step) or points (lookup)."""
    skip_level: int
    """Octree level of the empty-space skipping the fast intersection chose (0: none, -1: not applicable)."""
    before_ms: float
    """Median wall-clock milliseconds of the reference path."""
    after_ms: float
    before_cpu_ms: float
    """Median CPU milliseconds of this process, all threads (excludes waiting for a busy CPU)."""
    after_cpu_ms: float

    @property
    def speedup(self) -> float:
        return self.before_ms / self.after_ms

    @property
    def speedup_cpu(self) -> float:
        return self.before_cpu_ms / max(self.after_cpu_ms, 1e-9)


def _interleaved(before: Callable[[], object], after: Callable[[], object], repeats: int) -> tuple[float, ...]:
    """Median (before wall, after wall, before cpu, after cpu) ms, alternating the order every repeat."""
    before()
    after()  # warm-up (allocator, lazily built grids)
    times: dict[str, list[tuple[float, float]]] = {"before": [], "after": []}
    for i in range(repeats):
        pair = [("before", before), ("after", after)]
        for name, fn in (pair if i % 2 == 0 else pair[::-1]):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            times[name].append((1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)))
    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in times.items()}
    return med["before"][0], med["after"][0], med["before"][1], med["after"][1]


def _sorted_code_lookup(vm: VoxelMap, points: torch.Tensor) -> torch.Tensor:
    """Point lookup through the sorted Morton codes (what :meth:`VoxelMap.lookup_voxels` did before)."""
    ijk = vm.points_to_voxel_coords(points)
    inside = ((ijk >= MORTON_MIN_COORD) & (ijk <= MORTON_MAX_COORD)).all(-1)
    idx = vm.lookup_codes(morton_encode(torch.where(inside[:, None], ijk, torch.zeros_like(ijk))))
    return torch.where(inside, idx, torch.full_like(idx, -1))


def _check_same(a: render.VoxelHits, b: render.VoxelHits, what: str) -> None:
    for name in ("t_entry", "t_exit", "voxel_idx", "hit"):
        if not torch.equal(getattr(a, name), getattr(b, name)):
            raise RuntimeError(f"{what}: fast intersection differs from the reference in {name}")


def _skip_level(vm: VoxelMap, o: torch.Tensor, d: torch.Tensor, t_far: torch.Tensor | None, d_max: float) -> int:
    rays = raycast._clip_rays(vm, o, d, d_max, t_far)
    mean_cells = float(((rays.t1 - rays.t0)[:, None] * rays.d.abs()).sum(-1)[rays.ok].mean()) / vm.voxel_size_m
    grid = raycast._skip_grid(vm, mean_cells)
    return 0 if grid is None else grid.level


def _bench_voxel_size(cap: SyntheticCapture, voxel: float, repeats: int, step_repeats: int, device: str,
                      with_step: bool) -> list[Row]:
    cfg = RenderConfig()
    mapper = Mapper(voxel, FieldConfig(), cfg, LossConfig(),
                    MappingConfig(first_frame_iters=1, iters=1, keyframe_max_interval=1), device=device)
    for i in range(0, N_FRAMES, EVERY):  # allocate only (every frame a keyframe); no optimisation
        mapper.integrate(frame_to_device(cap[i], device), cap[i].T_world_cam, optimize=False)
    vm = mapper.voxels
    window = mapper.keyframes[:WINDOW]
    g = torch.Generator().manual_seed(0)
    parts = []
    for kf in window:
        px = sample_pixels(kf.data, RAYS_PER_FRAME, g)
        o, d = camera_rays(kf.data.K, kf.T_world_cam, px.uv)
        parts.append((o, d, px.depth_m + cfg.truncation_m))
    o, d, t_far = (torch.cat(x) for x in zip(*parts, strict=True))
    m_h = cfg.max_hits_for(voxel)
    rows = []

    def row(scenario: str, n_items: int, level: int, before: Callable[[], object],
            after: Callable[[], object], reps: int) -> None:
        t = _interleaved(before, after, reps)
        rows.append(Row(scenario, voxel, vm.n_voxels, n_items, level, *t))
        r = rows[-1]
        print(f"  {scenario:18s} {voxel:5.2f} m  {r.before_ms:9.1f} -> {r.after_ms:8.1f} ms  x{r.speedup:5.1f}  "
              f"(cpu {r.before_cpu_ms:.1f} -> {r.after_cpu_ms:.1f} ms, x{r.speedup_cpu:.1f})", flush=True)

    _check_same(intersect_voxels(vm, o, d, cfg.max_distance_m, m_h, t_far),
                intersect_voxels_reference(vm, o, d, cfg.max_distance_m, m_h, t_far), "mapping rays")
    row("intersect/mapping", o.shape[0], _skip_level(vm, o, d, t_far, cfg.max_distance_m),
        lambda: intersect_voxels_reference(vm, o, d, cfg.max_distance_m, m_h, t_far),
        lambda: intersect_voxels(vm, o, d, cfg.max_distance_m, m_h, t_far), repeats)

    view = cap[7 * EVERY]
    oi, di = camera_rays(view.K, torch.as_tensor(view.T_world_cam, device=device), width=WIDTH, height=HEIGHT)
    chunks = [(oi[s:s + IMAGE_CHUNK], di[s:s + IMAGE_CHUNK]) for s in range(0, oi.shape[0], IMAGE_CHUNK)]
    for co, cd in chunks:
        _check_same(intersect_voxels(vm, co, cd, cfg.max_distance_m, m_h),
                    intersect_voxels_reference(vm, co, cd, cfg.max_distance_m, m_h), "image rays")
    row("intersect/image", oi.shape[0], _skip_level(vm, oi, di, None, cfg.max_distance_m),
        lambda: [intersect_voxels_reference(vm, co, cd, cfg.max_distance_m, m_h) for co, cd in chunks],
        lambda: [intersect_voxels(vm, co, cd, cfg.max_distance_m, m_h) for co, cd in chunks], repeats)

    lo, hi = vm.voxel_bounds
    pts = ((lo.double() + torch.rand(LOOKUP_POINTS, 3, generator=g, dtype=torch.float64).to(device)
            * (hi - lo + 1).double()) * voxel).float()
    if not torch.equal(vm.lookup_voxels(pts), _sorted_code_lookup(vm, pts)):
        raise RuntimeError("lookup: dense grid differs from the sorted codes")
    row("lookup", LOOKUP_POINTS, -1, lambda: _sorted_code_lookup(vm, pts), lambda: vm.lookup_voxels(pts), repeats)

    if with_step:
        fast = render.intersect_voxels

        def step(impl: Callable[..., render.VoxelHits]) -> None:
            render.intersect_voxels = impl  # the name render_rays calls
            try:
                mapper.generator.manual_seed(1)  # the same rays for before and after
                mapper.step(window)
            finally:
                render.intersect_voxels = fast

        row("mapping step", WINDOW * RAYS_PER_FRAME, _skip_level(vm, o, d, t_far, cfg.max_distance_m),
            lambda: step(intersect_voxels_reference), lambda: step(fast), step_repeats)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--voxel-sizes", type=float, nargs="+", default=[0.2, 0.1, 0.05])
    ap.add_argument("--step-voxel-sizes", type=float, nargs="*", default=[0.2, 0.1],
                    help="voxel sizes that also time a full mapping step (slow on CPU at fine voxels)")
    ap.add_argument("--repeats", type=int, default=7, help="interleaved before/after pairs (median taken)")
    ap.add_argument("--step-repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "render.json")
    args = ap.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cap = SyntheticCapture(SyntheticConfig(n_frames=N_FRAMES, width=WIDTH, height=HEIGHT))
    machine = machine_info()
    print(f"synthetic room {WIDTH}x{HEIGHT}, map from every {EVERY}th of {N_FRAMES} frames; device {args.device}; "
          f"{machine['cpu_model']} ({machine['cpu_usable_cores']} usable cores), torch {torch.get_num_threads()} "
          f"threads; median of {args.repeats} interleaved pairs ({args.step_repeats} for the mapping step)\n")
    rows: list[Row] = []
    for voxel in args.voxel_sizes:
        rows += _bench_voxel_size(cap, voxel, args.repeats, args.step_repeats, args.device,
                                  any(abs(voxel - s) < 1e-12 for s in args.step_voxel_sizes))

    head = (f"{'scenario':18s} {'voxel m':>7s} {'voxels':>7s} {'items':>7s} {'skip':>4s} {'before ms':>10s} "
            f"{'after ms':>9s} {'speedup':>7s} {'cpu before':>10s} {'cpu after':>9s} {'cpu x':>6s}")
    print("\n" + head)
    print("-" * len(head))
    for r in rows:
        skip = "-" if r.skip_level < 0 else str(r.skip_level)
        print(f"{r.scenario:18s} {r.voxel_size_m:7.2f} {r.n_voxels:7d} {r.n_items:7d} {skip:>4s} {r.before_ms:10.1f} "
              f"{r.after_ms:9.1f} {r.speedup:7.1f} {r.before_cpu_ms:10.1f} {r.after_cpu_ms:9.1f} {r.speedup_cpu:6.1f}")

    result = {
        "benchmark": "render",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/bench_render.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "settings": {"width": WIDTH, "height": HEIGHT, "map_frames": f"every {EVERY}th of {N_FRAMES}",
                     "window_frames": WINDOW, "rays_per_frame": RAYS_PER_FRAME, "image_chunk": IMAGE_CHUNK,
                     "lookup_points": LOOKUP_POINTS, "repeats": args.repeats, "step_repeats": args.step_repeats,
                     "torch_threads": torch.get_num_threads(), "device": args.device,
                     "render_config": asdict(RenderConfig())},
        "notes": "before = reference path (all grid-plane crossings, Morton codes + searchsorted; sorted-code point "
                 "lookup), after = fast path (dense index grid, empty-space skipping at octree level skip_level, "
                 "0 = none); results checked identical; before/after interleaved in one process; *_ms median "
                 "wall-clock, *_cpu_ms median CPU time of the process (all threads, including intra-op workers "
                 "spinning while they wait); compare rows of one run, not across runs",
        "machine": machine,
        "rows": [dict(asdict(r), speedup=round(r.speedup, 3), speedup_cpu=round(r.speedup_cpu, 3)) for r in rows],
    }
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
