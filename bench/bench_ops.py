"""Operators and host synchronisations per tracking and per mapping iteration (a proxy for GPU launch cost).

Usage (from the repository root)::

    python bench/bench_ops.py                      # writes bench/results/ops.json
    python bench/bench_ops.py --label before --out /tmp/ops_before.json   # e.g. on an older checkout

On a GPU every operator is at least one kernel launch (~5-10 us of host time) and every read of a device
value by the host (``float(t)``, ``int(t.sum())``, ``t[mask]``, ``torch.nonzero``) stalls the host until
the device has caught up, so these counts, taken with ``torch.profiler`` on the CPU, predict where a GPU
loop will wait. The map is the synthetic room (320x240, seed 0) mapped at its reference poses over its
first 10 frames with the ``cpu`` sizes; then:

* ``tracking/render``: the paper's tracker (Adam through the volume renderer), per iteration;
* ``tracking/sdf``: the geometric tracker (Levenberg-Marquardt on point-to-SDF residuals), per iteration
  (one field evaluation + one backward pass + a 6x6 solve);
* ``mapping/band`` and ``mapping/voxels``: one :meth:`Mapper.optimize` iteration (window of keyframes,
  render, losses, Adam) with the fixed-shape band sampler and with the paper's voxel sampler (``mapping``
  on a checkout that has only the latter); this map has one or two keyframes, so the window is small;
* ``mapping/band x4``: one :meth:`Mapper.step` over a window of 4 frames (frames 6-9, the first held fixed),
  the size of a running session's window at the ``cpu`` preset (3 keyframes + the newest frame);
* ``render/occlusion 256x192`` (and ``... fixed walk``): one depth image (AR occlusion, ``with_color`` false) at
  frame 10's pose as a GPU renders it (one call of 65536 rays, the GPU's event budget), with the walk of
  data-dependent shapes and with the fixed-shape walk (:func:`~voxfusion.core.render.render_rays_fixed`, a GPU's
  default); "per iteration" is per image there. Each row also reads one small tensor back with ``.tolist()`` (the
  chunk sizes; the sample count with the walk's doubt flag), which runs no operator on a CPU and is not counted;
  ``... static budget (one CUDA graph)``: the same image as
  :func:`~voxfusion.core.render.volume.render_rays_static`, the body of its CUDA graph (``render.cuda_graphs``),
  with budgets measured on a fixed-walk render: no read-back; its one ``nonzero_static`` (which waits for nothing
  on CUDA from PyTorch 2.6) counted apart;
* ``fuse/7 frames in turn`` and ``... in one pass``: a realtime mapping round's fusion of the 7 frames tracked
  since the last round (what an H100 session fed at 30 Hz fused per round), with ``Mapper.integrate`` per frame and
  with ``Mapper.integrate_batch`` (one allocation, surface-mark and evidence update); "per iteration" is per round
  (each call fuses into its own copy of the same map, made beforehand).

Where the engine computes one thing in two forms, one for a CPU and one with fewer operators for a GPU (the trilinear
weights, ``core/map/field.py``; the C kernels of ``core/native``, which replace operators on a CPU only), the GPU's
form is counted (``--cpu-forms``: the CPU's). The band rows count the
fixed-shape path a GPU runs (``mapping.compact_samples: false``); ``mapping/band
compact`` is the CPU default, which evaluates only the samples inside the map (one read-back per iteration).

Counted: every ``aten::`` operator event (nested ones included, so a composite op counts with its parts),
and the ones that make the host wait on a GPU: ``_local_scalar_dense`` (``.item()``, ``float()``,
``int()``, ``bool()``), ``nonzero`` (boolean-mask indexing, ``torch.nonzero``), ``masked_select``,
``unique`` variants and ``repeat_interleave`` without an output size; for mapping also the syncs outside
``Optimizer.step`` (the CPU build of fused Adam reads its step counters in the kernel; CUDA's does not).
Methods the checked-out engine does
not have are skipped, so the same script measures an older checkout (``--label before``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections import Counter
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

from bench.machine import machine_info  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.eval.report import write_json  # noqa: E402
from voxfusion.core.framedata import frame_to_device  # noqa: E402
from voxfusion.core.reconstruct import make_mapper  # noqa: E402
from voxfusion.core.slam.presets import load_preset  # noqa: E402
from voxfusion.core.slam.tracking import Tracker, TrackingConfig  # noqa: E402

SYNC_OPS = ("aten::_local_scalar_dense", "aten::nonzero", "aten::nonzero_static", "aten::masked_select",
            "aten::_unique", "aten::_unique2", "aten::unique_dim", "aten::unique_consecutive",
            "aten::repeat_interleave", "aten::is_nonzero", "aten::equal")


def use_gpu_forms() -> None:
    """Run the GPU's forms on this machine where the engine has two (the same numbers, fewer operators); a checkout
    without them is left as it is."""
    try:
        from voxfusion.core.map import field
    except ImportError:  # a checkout from before core/map/
        from voxfusion.core import field  # type: ignore[no-redef]

    if hasattr(field, "_trilinear_weights_outer"):
        field._trilinear_weight_columns = field._trilinear_weights_outer
        field._trilinear_weight_backward = field._trilinear_backward_outer
    # the CPU's C kernels (core/native, since 2026-11-29) do not run on a GPU: count the operators they replace
    os.environ["VOXFUSION_NATIVE"] = "0"


def count_ops(fn, repeats: int) -> dict[str, float]:
    """Profile ``fn()`` ``repeats`` times (after one warm-up call); operator and sync counts per call."""
    fn()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(repeats):
            fn()
    events = list(prof.events())
    names = Counter(e.name for e in events if e.name.startswith("aten::"))
    syncs = {k: v / repeats for k, v in names.items() if k in SYNC_OPS}
    # the CPU build of fused Adam reads each parameter's step counter inside its kernel; CUDA's keeps them on
    # the device, so those reads say nothing about a GPU loop: counted apart
    steps = [e.time_range for e in events if e.name.startswith("Optimizer.step")]
    in_optimizer = sum(1 for e in events if e.name in SYNC_OPS
                       and any(r.start <= e.time_range.start <= r.end for r in steps)) / repeats
    return {"aten_ops": sum(names.values()) / repeats, "host_syncs": sum(syncs.values()), "sync_ops": syncs,
            "host_syncs_in_optimizer": in_optimizer}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--label", default="after", help="name of this measurement in the JSON (default after)")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "ops.json")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cpu-forms", action="store_true",
                   help="count the CPU's form where the engine has a CPU and a GPU form (default: the GPU's)")
    args = p.parse_args(argv)
    if not args.cpu_forms:
        use_gpu_forms()
    torch.manual_seed(0)
    cfg = load_preset("cpu-small", ["device=cpu"])
    cap = SyntheticCapture(SyntheticConfig(n_frames=12))
    mapper = make_mapper(cfg)
    for f in cap.frames(0, 10):
        mapper.integrate(frame_to_device(f, "cpu"), f.T_world_cam)
    frame = frame_to_device(cap[10], "cpu")
    prior = cap[10].T_world_cam

    rows: dict[str, dict] = {}
    known = {f.name for f in dataclasses.fields(TrackingConfig)}
    scenarios = {"tracking/render": dict(rays=256, iters=10, min_iters=10, converge_tol=0.0)}
    if "method" in known:
        scenarios["tracking/render"]["method"] = "render"
        scenarios["tracking/sdf"] = dict(method="sdf", sdf_points=2048, sdf_levels=2, sdf_iters=6)
    for name, kw in scenarios.items():
        tcfg = TrackingConfig(**kw)
        tracker = Tracker(tcfg, cfg.render, use_color=True)
        tracker.set_map(mapper.voxels.snapshot(), mapper.decoder)
        if hasattr(tracker, "remember"):  # the previous frame: the frame-to-frame term's reference (sdf)
            tracker.remember(frame_to_device(cap[9], "cpu"), cap[9].T_world_cam)
        # iterations of the very calls that are counted (a converging tracker runs a different number per
        # call: each draws other points), averaged like the counts
        iterations: list[int] = []
        c = count_ops(lambda t=tracker, log=iterations: log.append(t.track(frame, prior).iterations), args.repeats)
        its = sum(iterations[-args.repeats:]) / args.repeats
        # the sdf tracker evaluates each stage once more than it iterates (the starting point); a checkout
        # older than Tracker.sdf_stages has one stage per level
        stages = tracker.sdf_stages() if hasattr(tracker, "sdf_stages") else tcfg.sdf_levels
        per_call = its + (stages if kw.get("method") == "sdf" else 0)
        rows[name] = {"iterations_per_frame": its, "evaluations_per_frame": per_call,
                      "aten_ops_per_iteration": c["aten_ops"] / per_call,
                      "host_syncs_per_iteration": c["host_syncs"] / per_call,
                      "host_syncs_per_frame": c["host_syncs"], "sync_ops_per_frame": c["sync_ops"]}
    iters = 5
    samplers = {"mapping": None}  # the checked-out default
    if "sampler" in {f.name for f in dataclasses.fields(type(mapper.config))}:
        samplers = {"mapping/band": "band", "mapping/voxels": "voxels"}
    default_config = mapper.config
    # the GPU path (every shape fixed, nothing read back) is what these counts stand for; the CPU default
    # evaluates only the samples inside the map (one read-back per iteration), counted as its own row
    fixed = {"compact_samples": False} if hasattr(default_config, "compact_samples") else {}
    if fixed:
        samplers["mapping/band compact"] = "band"
    for name, sampler in samplers.items():
        if sampler is not None:
            extra = {} if name.endswith("compact") else fixed
            mapper.config = dataclasses.replace(default_config, sampler=sampler, **extra)
        c = count_ops(lambda: mapper.optimize(iters, newest=mapper.keyframes[-1]), args.repeats)
        rows[name] = {"iterations_per_round": iters, "aten_ops_per_iteration": c["aten_ops"] / iters,
                      "host_syncs_per_iteration": c["host_syncs"] / iters,
                      "host_syncs_outside_optimizer_per_iteration":
                          (c["host_syncs"] - c["host_syncs_in_optimizer"]) / iters,
                      "sync_ops_per_round": c["sync_ops"]}
    mapper.config = default_config
    # the CPU preset's window in a running session: the newest frame and 3 keyframes (mapper.step on 4 frames)
    from voxfusion.core.slam.mapping import Keyframe

    window = [Keyframe.create(frame_to_device(cap[i], "cpu"), torch.as_tensor(cap[i].T_world_cam), fixed=i == 6)
              for i in (6, 7, 8, 9)]
    mapper.config = dataclasses.replace(default_config, **fixed)
    c = count_ops(lambda: mapper.step(window), args.repeats)
    mapper.config = default_config
    rows["mapping/band x4"] = {"aten_ops_per_iteration": c["aten_ops"], "host_syncs_per_iteration": c["host_syncs"],
                               "host_syncs_outside_optimizer_per_iteration":
                                   c["host_syncs"] - c["host_syncs_in_optimizer"],
                               "sync_ops_per_iteration": c["sync_ops"]}

    # the occlusion render (256x192 depth, AR) as a GPU runs it: one call of 65536 rays with the GPU's event budget;
    # the walk with data-dependent shapes (the CPU's) and the fixed-shape walk (the GPU's default), depth alone
    try:  # the render package (since 2026-11-28); older checkouts had flat modules
        from voxfusion.core.render import raycast
        from voxfusion.core.render import volume as render
    except ImportError:
        from voxfusion.core import raycast, render

    image = {"render/occlusion 256x192": False, "render/occlusion 256x192 fixed walk": True}
    K = cap[10].K * torch.tensor([[256 / cap.width], [192 / cap.height], [1.0]]).numpy()
    snap = mapper.voxels.snapshot()
    budget = raycast._event_budget
    raycast._event_budget = lambda device: budget(torch.device("cuda"))
    try:
        for name, fixed in image.items():
            if fixed and not hasattr(render, "render_rays_fixed"):
                continue
            kw = {"chunk": 65536, "with_color": False, "fixed_walk": fixed} if hasattr(render, "render_rays_fixed") \
                else {"chunk": 65536}
            c = count_ops(lambda kw=kw: render.render_depth_image(snap, mapper.decoder, K, cap[10].T_world_cam, 256,
                                                                  192, cfg.render, **kw), args.repeats)
            rows[name] = {"aten_ops_per_iteration": c["aten_ops"], "host_syncs_per_iteration": c["host_syncs"],
                          "sync_ops_per_iteration": c["sync_ops"]}
        if hasattr(render, "render_rays_static"):  # the body of the occlusion render's CUDA graph (render_graphs)
            o, d = render.camera_rays(K, cap[10].T_world_cam, width=256, height=192)
            sized = render.render_budget(snap, render.render_rays_fixed(snap, mapper.decoder, o, d, cfg.render))
            c = count_ops(lambda: render.render_rays_static(snap, mapper.decoder, o, d, cfg.render, sized, False),
                          args.repeats)
            static = c["sync_ops"].pop("aten::nonzero_static", 0.0)  # waits for nothing on CUDA (PyTorch >= 2.6)
            rows["render/occlusion 256x192 static budget (one CUDA graph)"] = {
                "aten_ops_per_iteration": c["aten_ops"], "host_syncs_per_iteration": c["host_syncs"] - static,
                "sync_ops_per_iteration": c["sync_ops"], "nonzero_static_per_iteration": static}
    finally:
        raycast._event_budget = budget

    # a realtime round's fusion: the 7 frames tracked since the last round (an H100 session fed at 30 Hz fused ~7
    # per round), fused one by one (integrate, optimize=False) and in one pass (integrate_batch)
    import copy

    fuse_cfg = load_preset("cpu-small", ["device=cpu", "mapping.first_frame_iters=1"])
    fuse_cap = SyntheticCapture(SyntheticConfig(n_frames=13))
    fuse_frames = [(frame_to_device(f, "cpu"), f.T_world_cam) for f in fuse_cap.frames()]
    base = make_mapper(fuse_cfg)
    for f, T in fuse_frames[:6]:
        base.integrate(f, T, optimize=False)
    fusions = {"fuse/7 frames in turn": lambda m: [m.integrate(f, T, optimize=False) for f, T in fuse_frames[6:]]}
    if hasattr(base, "integrate_batch"):
        fusions["fuse/7 frames in one pass"] = lambda m: m.integrate_batch(fuse_frames[6:], optimize=False)
    for name, fuse in fusions.items():
        maps = [copy.deepcopy(base) for _ in range(args.repeats + 1)]  # one per call (with the warm-up), made here
        c = count_ops(lambda fuse=fuse, maps=maps: fuse(maps.pop()), args.repeats)
        rows[name] = {"aten_ops_per_iteration": c["aten_ops"], "host_syncs_per_iteration": c["host_syncs"],
                      "sync_ops_per_iteration": c["sync_ops"]}

    print(f"{'scenario':<38}{'aten ops / it':>15}{'host syncs / it':>17}{'outside Adam':>14}")
    for name, r in rows.items():
        outside = r.get("host_syncs_outside_optimizer_per_iteration", r["host_syncs_per_iteration"])
        print(f"{name:<38}{r['aten_ops_per_iteration']:>15.0f}{r['host_syncs_per_iteration']:>17.1f}{outside:>14.1f}")
    result = {"label": args.label, "machine": machine_info(), "command": " ".join(sys.argv),
              "forms": "cpu" if args.cpu_forms else "gpu",
              "map": "synthetic room 320x240 seed 0, frames 0-9 at reference poses, cpu sizes",
              "scenarios": rows}
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
