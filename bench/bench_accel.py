"""The engine's execution options, measured: eager float32 (the reference) against ``torch.compile`` and
mixed precision of the decoder (``field.compile``, ``field.precision``), the compiled geometric tracker
(``tracking.compile``) and the compiled mapping iteration (``mapping.compile``), per tracking and per mapping
iteration.

Usage (from the repository root)::

    python bench/bench_accel.py                 # this machine's device -> bench/results/accel-<device>.json
    python bench/bench_accel.py --smoke --out /tmp/accel.json     # tiny sizes, seconds (the tests run this)

For each variant a map is built from the synthetic room's first ``--map-frames`` frames at their reference
poses (320x240 with the preset ``voxfusion run`` picks on a CPU, ``synthetic+cpu``; 640x480 with the ``paper``
preset on CUDA, where the GPU targets are stated), then:

* ``build_s``: that build, first compilation included (``torch.compile`` compiles on first use, and again
  for each new input kind: with and without colour, with and without gradients); ``tracking_build_s``: the
  first tracked frame, the tracker's compilation included (one graph per solver stage);
* ``mapping_ms_per_iter``: median over ``--rounds`` of :meth:`Mapper.optimize` (``--iters`` iterations), after
  a warm-up round;
* ``tracking_ms_per_frame`` / ``tracking_ms_per_eval``: the geometric (``sdf``) tracker on the next frame from
  its previous frame's pose, median over ``--rounds`` (an evaluation is one field query + backward pass);
  ``tracking_error_mm`` / ``tracking_error_deg``: that pose against the reference pose;
* ``sdf_dev_mm``: the largest SDF difference, at points near the surface, between this variant and the same
  map decoded by the float32 eager reference (0 for the reference itself): what the option alone changes in the
  decoder's arithmetic (0 as well for options that change how a map is trained or tracked, not decoded).

Timed regions are closed by ``torch.cuda.synchronize()`` on CUDA. Keep the variant that wins where it runs:
the engine defaults stay float32 eager until a measurement on that device says otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.machine import machine_info  # noqa: E402
from voxfusion.core.config import apply_overrides  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.eval.report import format_table, write_json  # noqa: E402
from voxfusion.core.framedata import frame_to_device  # noqa: E402
from voxfusion.core.geometry import backproject_depth  # noqa: E402
from voxfusion.core.map import field as field_module  # noqa: E402
from voxfusion.core.slam import mapping as mapping_module  # noqa: E402
from voxfusion.core.slam import tracking_sdf  # noqa: E402
from voxfusion.core.slam.mapping import make_mapper  # noqa: E402
from voxfusion.core.slam.presets import VoxFusionConfig, load_preset, preset_for  # noqa: E402
from voxfusion.core.slam.tracking import Tracker  # noqa: E402

VARIANTS: dict[str, dict[str, object]] = {
    "float32 eager (reference)": {},
    "no CUDA graphs (eager tracker)": {"tracking.cuda_graphs": False},
    "bfloat16": {"field.precision": "bfloat16"},
    "float16": {"field.precision": "float16"},
    "compile": {"field.compile": True},
    "compile + bfloat16": {"field.compile": True, "field.precision": "bfloat16"},
    "tracking compile": {"tracking.compile": True},
    "mapping compile": {"mapping.compile": True},
}
"""Variant name -> configuration options (``section.key``: the decoder's ``field.*``, the geometric tracker's
``tracking.compile`` and ``tracking.cuda_graphs``, a mapping iteration's renderer and losses ``mapping.compile``). The
reference is eager except for the sdf solver's stages, which replay from CUDA graphs on a CUDA device (the engine's
default); ``no CUDA graphs`` runs them eagerly too (on a CPU it is the reference)."""
SMOKE = ["mapping.first_frame_iters=5", "mapping.iters=1", "mapping.rays_per_frame=64", "tracking.sdf_points=256",
         "tracking.sdf_iters=2", "field.sdf_hidden=16", "field.color_hidden=16", "field.geo_feature_dim=8"]
"""``--smoke`` overrides: the same code at tiny sizes."""


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _median_ms(fn, rounds: int, device: torch.device) -> float:  # noqa: ANN001
    times = []
    for _ in range(rounds):
        _sync(device)
        t = time.perf_counter()
        fn()
        _sync(device)
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def _pose_error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (degrees) of ``T_ref^-1 T``."""
    E = np.linalg.inv(T_ref) @ T
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return float(np.linalg.norm(E[:3, 3]) * 1e3), float(angle)


def measure_variant(base: VoxFusionConfig, options: dict[str, object], frames: list, map_frames: int,
                    iters: int, rounds: int) -> dict:
    """Build a map with the configuration ``options`` (:data:`VARIANTS`), then time mapping and tracking on it."""
    config = apply_overrides(base, [f"{key}={value}" for key, value in options.items()])
    device = torch.device(config.device)
    compiled = [fn for on, fn in ((config.field.compile, field_module.COMPILED_MLP),
                                  (config.tracking.compile, tracking_sdf.COMPILED_LINEARIZE),
                                  (config.mapping.compile, mapping_module.COMPILED_BAND_LOSS)) if on]
    if compiled:  # a fresh compilation per variant: earlier variants' graphs and failures do not count
        torch._dynamo.reset()
        for fn in compiled:
            fn.reset()
    t0 = time.perf_counter()
    mapper = make_mapper(config, device=device)
    for f in frames[:map_frames]:
        mapper.integrate(frame_to_device(f, device), f.T_world_cam)
    mapper.optimize(iters, newest=mapper.keyframes[-1])  # warm-up (and first compilation) of a full round
    _sync(device)
    build_s = time.perf_counter() - t0
    mapping_ms = _median_ms(lambda: mapper.optimize(iters, newest=mapper.keyframes[-1]), rounds, device) / iters

    tracker = Tracker(config.tracking, config.render, mapper.field_config.use_color, seed=config.seed)
    snapshot = mapper.voxels.snapshot()
    tracker.set_map(snapshot, mapper.decoder)
    target = frames[map_frames]
    data = frame_to_device(target, device)
    prior = frames[map_frames - 1].T_world_cam
    # the previous frame: the reference of the frame-to-frame terms, as in a running session
    tracker.remember(frame_to_device(frames[map_frames - 1], device), prior)
    t0 = time.perf_counter()
    result = tracker.track(data, prior)  # warm-up (and, with tracking.compile, the tracker's compilation)
    _sync(device)
    tracking_build_s = time.perf_counter() - t0
    evals = result.iterations + tracker.sdf_stages()  # each solver stage evaluates its start once
    tracking_ms = _median_ms(lambda: tracker.track(data, prior), rounds, device)
    err_mm, err_deg = _pose_error(np.asarray(tracker.track(data, prior).T_world_cam), target.T_world_cam)

    # what the option alone changes: the same map decoded by the float32 eager reference
    pts = _surface_points(data, target.T_world_cam, 4096, device)
    with torch.no_grad():
        sdf, _, valid = mapper.query(pts)
        reference = dataclasses.replace(mapper.decoder.config, precision="float32", compile=False)
        mapper.decoder.config, fast_config = reference, mapper.decoder.config
        sdf_ref, _, _ = mapper.query(pts)
        mapper.decoder.config = fast_config
    dev_mm = float((sdf - sdf_ref)[valid].abs().max()) * 1e3 if bool(valid.any()) else float("nan")
    return {"options": options, "build_s": build_s, "tracking_build_s": tracking_build_s,
            "mapping_ms_per_iter": mapping_ms,
            "tracking_ms_per_frame": tracking_ms, "tracking_ms_per_eval": tracking_ms / max(evals, 1),
            "tracking_evals": evals, "tracking_error_mm": err_mm, "tracking_error_deg": err_deg,
            "sdf_dev_mm": dev_mm,
            # True: torch.compile failed and this variant's figures are eager ones (one warning logged)
            "compile_fell_back": any(fn.failed for fn in compiled)}


def _surface_points(data, T_world_cam: np.ndarray, n: int, device: torch.device) -> torch.Tensor:  # noqa: ANN001
    """``[<= n, 3]`` world points on the frame's observed surface (every k-th valid pixel)."""
    pts = backproject_depth(data.depth_m.cpu().numpy(), data.K.cpu().numpy(), np.asarray(T_world_cam))
    return torch.from_numpy(pts[::max(1, len(pts) // n)][:n]).to(device, torch.float32)


def run(device: str, smoke: bool, map_frames: int, iters: int, rounds: int,
        variants: list[str] | None = None, overrides: list[str] | None = None,
        budget_s: float | None = None) -> dict:
    """Every variant (``variants``: a subset of :data:`VARIANTS` names) on ``device``, with config ``overrides``
    (``key=value``) on the preset; the JSON-ready result. ``budget_s``: no variant starts after that many seconds
    (the ones left out are listed under ``not_run``)."""
    t_start = time.perf_counter()
    dev = torch.device(device)
    cuda = dev.type == "cuda"
    width, height = (640, 480) if cuda and not smoke else (320, 240)
    overrides = [f"device={device}", *(SMOKE if smoke else []), *(overrides or [])]
    cap = SyntheticCapture(SyntheticConfig(n_frames=map_frames + 1, width=width, height=height, seed=0))
    # the paper preset on CUDA (the GPU targets are stated there); on a CPU what `voxfusion run` picks
    preset = "paper" if cuda and not smoke else preset_for(cap, "cpu").preset
    base = load_preset(preset, overrides, profile=cap.profile)
    frames = list(cap.frames(0, map_frames + 1))
    rows, not_run = {}, []
    for name in variants or list(VARIANTS):
        if budget_s is not None and time.perf_counter() - t_start >= budget_s:
            not_run.append(name)
            continue
        print(f"[accel] {name}", flush=True)
        rows[name] = measure_variant(base, VARIANTS[name], frames, map_frames, iters, rounds)
    ref = rows.get("float32 eager (reference)")
    if ref:
        for r in rows.values():
            r["mapping_speedup"] = ref["mapping_ms_per_iter"] / r["mapping_ms_per_iter"]
            r["tracking_speedup"] = ref["tracking_ms_per_frame"] / r["tracking_ms_per_frame"]
    return {"device": str(dev), "preset": preset, "overrides": overrides, "size": [width, height],
            "map_frames": map_frames, "mapping_iters_per_round": iters, "rounds": rounds, "smoke": smoke,
            "variants": rows, "not_run": not_run}


MAPPING_PATHS = {"eager (compacting; the CPU default)": {"mapping.compact_samples": True},
                 "eager, fixed-shape samples (a GPU's default)": {"mapping.compact_samples": False},
                 "mapping compile (fixed-shape samples)": {"mapping.compile": True}}
"""``--mapping-paths``: the ways one mapping iteration can run, timed on one map in turn."""


def mapping_paths(device: str, smoke: bool, map_frames: int, iters: int, rounds: int) -> dict:
    """ms per mapping iteration of each :data:`MAPPING_PATHS` on one map, the paths alternated round by round (so a
    drift of the machine's speed hits each alike), medians over ``rounds`` after one warm-up round each (the
    compiled path's compilation). The same window sizes and sample counts for every path; the map keeps training."""
    dev = torch.device(device)
    overrides = [f"device={device}", *(SMOKE if smoke else [])]
    cap = SyntheticCapture(SyntheticConfig(n_frames=map_frames, seed=1))
    preset = preset_for(cap, device).preset
    base = load_preset(preset, overrides, profile=cap.profile)
    mapper = make_mapper(base, device=dev)
    for f in cap.frames(0, map_frames):
        mapper.integrate(frame_to_device(f, dev), f.T_world_cam)
    configs = {name: apply_overrides(base, [f"{k}={v}" for k, v in opts.items()]).mapping
               for name, opts in MAPPING_PATHS.items()}
    newest = mapper.keyframes[-1]
    warmup_s = {}
    for name, cfg in configs.items():
        mapper.config = cfg
        t0 = time.perf_counter()
        mapper.optimize(iters, newest=newest)
        _sync(dev)
        warmup_s[name] = time.perf_counter() - t0
    times: dict[str, list[float]] = {name: [] for name in configs}
    for _ in range(rounds):
        for name, cfg in configs.items():
            mapper.config = cfg
            times[name].append(_median_ms(lambda: mapper.optimize(iters, newest=newest), 1, dev) / iters)
    return {"device": str(dev), "preset": preset, "map_frames": map_frames,
            "keyframes": len(mapper.keyframes), "voxels": mapper.voxels.n_voxels, "iters_per_round": iters,
            "rounds": rounds, "ms_per_iter": {k: statistics.median(v) for k, v in times.items()},
            "ms_per_iter_all": times, "first_round_s": warmup_s}


def print_table(result: dict) -> None:
    rows = [{"variant": name, "map ms/it": r["mapping_ms_per_iter"], "x map": r.get("mapping_speedup"),
             "track ms/frame": r["tracking_ms_per_frame"], "x track": r.get("tracking_speedup"),
             "track err mm": r["tracking_error_mm"], "sdf dev mm": r["sdf_dev_mm"], "build s": r["build_s"],
             "track build s": r["tracking_build_s"],
             "eager fallback": "yes" if r.get("compile_fell_back") else ""}
            for name, r in result["variants"].items()]
    print(format_table(rows, columns=list(rows[0]), float_fmt=".2f"))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--smoke", action="store_true", help="tiny sizes (seconds): the same code paths")
    p.add_argument("--map-frames", type=int, default=None,
                   help="frames mapped before timing (default 31: four keyframes, a full window; smoke 3)")
    p.add_argument("--iters", type=int, default=5, help="mapping iterations per timed round")
    p.add_argument("--rounds", type=int, default=None, help="timed rounds (median; default 7, smoke 2)")
    p.add_argument("--variants", nargs="*", choices=list(VARIANTS), default=None)
    p.add_argument("--mapping-paths", action="store_true",
                   help="instead: the mapping iteration's paths (compacting, fixed-shape, compiled) on one map, "
                        "alternated round by round (default rounds 12; writes accel-<device>-mapping-paths.json)")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON path (default bench/results/accel-<device>.json; smoke: not written unless given)")
    args = p.parse_args(argv)
    map_frames = args.map_frames or (3 if args.smoke else 31)
    machine = machine_info()
    if args.mapping_paths:
        result = mapping_paths(args.device, args.smoke, map_frames, 1 if args.smoke else args.iters,
                               args.rounds or (2 if args.smoke else 12))
        rows = [{"path": k, "ms/iter (median)": v, "first round s": result["first_round_s"][k]}
                for k, v in result["ms_per_iter"].items()]
        print(format_table(rows, columns=list(rows[0]), float_fmt=".2f"))
    else:
        rounds = args.rounds or (2 if args.smoke else 7)
        result = run(args.device, args.smoke, map_frames, 1 if args.smoke else args.iters, rounds, args.variants)
        print_table(result)
    out = args.out
    if out is None and not args.smoke:
        cuda = machine.get("cuda_device") if args.device.startswith("cuda") else None
        slug = "".join(c if c.isalnum() else "-" for c in (cuda["name"] if cuda else "cpu").lower()).strip("-")
        out = REPO_ROOT / "bench" / "results" / f"accel-{slug}{'-mapping-paths' if args.mapping_paths else ''}.json"
    if out is not None:
        write_json(out, {"machine": machine, "command": " ".join(sys.argv), **result})
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
