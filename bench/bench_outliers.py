"""Render-back probe under depth outliers: does a one-frame map render what it was shown?

Usage (from the repository root; set ``OMP_NUM_THREADS=1`` on a shared machine)::

    python bench/bench_outliers.py                                  # every dev capture that exists
    python bench/bench_outliers.py --captures synthetic tum_fr1_desk --fractions 0 0.02

For each capture (the synthetic room and every dev capture under ``../shared/data`` that ``open_capture``
reads), each outlier fraction (default 0, 0.5 and 2 % of the pixels set to random depths in 0.3-1.0 m) and
each first-camera orientation (``axis_aligned``: identity rotation at the reference position; ``rotated``:
that pose rotated 40 deg about the world axis (1, 2, 3)), the first frame is

* mapped by ours (a fresh ``Mapper``, ``first_frame_iters`` iterations of the preset) in several variants:
  ``off`` (depth filter and voxel evidence both switched off: the engine before this fix), ``on`` (the
  defaults), and ``filter_only`` / ``evidence_only``;
* integrated by the TSDF baseline (Open3D, ``bench/baseline_tsdf.py``: one TSDF integration at the same
  pose, 1-2 cm voxels);

and its depth is rendered (ray-cast) back at the same pose and compared with the depth it was given: the
median ``|rendered - observed|`` over pixels valid in both (:func:`voxfusion.core.eval.render_probe.depth_probe`).
Also timed: the depth filter and the evidence update on a 640x480 frame (7-Scenes, else synthetic), on one
CPU thread. Prints a table and writes ``bench/results/outlier_probe.json`` with :func:`bench.machine.machine_info`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.baseline_tsdf import BASELINE_PRESETS, MissingDependencyError, tsdf_render_back  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from voxfusion.core.config import config_to_dict  # noqa: E402
from voxfusion.core.datasets import open_capture, resize_frame  # noqa: E402
from voxfusion.core.datasets.frame import RGBDFrame  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.depth_filter import depth_outlier_mask  # noqa: E402
from voxfusion.core.errors import CaptureError  # noqa: E402
from voxfusion.core.eval.render_probe import (  # noqa: E402
    add_depth_outliers,
    anchor_first_pose,
    depth_probe,
    oblique_rotation,
)
from voxfusion.core.eval.report import format_table, write_json  # noqa: E402
from voxfusion.core.framedata import frame_to_device  # noqa: E402
from voxfusion.core.map import VoxelMap  # noqa: E402
from voxfusion.core.map.evidence import observe_frame  # noqa: E402
from voxfusion.core.reconstruct import make_mapper  # noqa: E402
from voxfusion.core.render.volume import render_depth_image  # noqa: E402
from voxfusion.core.slam.mapping import _backproject  # noqa: E402
from voxfusion.core.slam.presets import VoxFusionConfig, load_preset  # noqa: E402

DATA = REPO_ROOT.parent / "shared" / "data"
CAPTURES = {
    # name: (folder under ../shared/data, or None for the synthetic room; TSDF baseline preset)
    "synthetic": (None, "synthetic"),
    "tum_fr1_desk": ("tum_fr1_desk_9frames", "kinect"),
    "tum_fr3_far": ("tum_fr3_structure_notexture_far_120", "kinect"),
    "sevenscenes": ("sevenscenes_redkitchen", "kinect"),
    "stray_iphone": ("stray_iphone_lidar", "lidar"),
    "scanner3d_corridor": ("scanner3d_iphone_corridor", "lidar"),
}
VARIANTS = {
    "off": ["mapping.depth_filter.enabled=false", "mapping.evidence.enabled=false"],
    "on": [],
    "filter_only": ["mapping.evidence.enabled=false"],
    "evidence_only": ["mapping.depth_filter.enabled=false"],
}
ROTATION_DEG, ROTATION_AXIS = 40.0, (1.0, 2.0, 3.0)


def first_frame(name: str, max_width: int) -> RGBDFrame | None:
    """The capture's first frame, downscaled by an integer factor to at most ``max_width``; None if absent."""
    folder, _ = CAPTURES[name]
    if folder is None:
        frame = SyntheticCapture(SyntheticConfig(n_frames=1))[0]
    else:
        if not (DATA / folder).is_dir():
            return None
        try:
            frame = open_capture(DATA / folder)[0]
        except CaptureError as e:
            print(f"skip {name}: {e}", file=sys.stderr)
            return None
    scale = max(1, -(-frame.width // max_width))
    return resize_frame(frame, frame.width // scale, frame.height // scale) if scale > 1 else frame


def first_pose(frame: RGBDFrame, orientation: str) -> np.ndarray:
    """Axis-aligned camera at the reference position, or that pose rotated about the oblique world axis."""
    T = np.eye(4)
    if frame.T_world_cam is not None:
        T[:3, 3] = frame.T_world_cam[:3, 3]
    return oblique_rotation(ROTATION_DEG, ROTATION_AXIS) @ T if orientation == "rotated" else T


def probe_ours(frame: RGBDFrame, T_world_cam: np.ndarray, config: VoxFusionConfig) -> dict:
    """Map ``frame`` alone (``first_frame_iters``) and render its depth back at the same pose."""
    t0 = time.perf_counter()
    mapper = make_mapper(config, has_color=frame.color is not None)
    m = config.mapping
    data = frame_to_device(frame, mapper.device, m.min_depth_m, m.max_depth_m, m.min_confidence,
                           use_color=frame.color is not None, depth_filter=m.depth_filter)
    mapper.integrate(data, T_world_cam)
    t1 = time.perf_counter()
    img = render_depth_image(mapper.voxels, mapper.decoder, frame.K, T_world_cam, frame.width, frame.height,
                             config.render)
    p = depth_probe(img.depth, frame.depth_m)
    return {"median_abs_cm": 100 * p.median_abs_m, "mean_abs_cm": 100 * p.mean_abs_m,
            "rendered_fraction": p.rendered_fraction, "voxels": mapper.voxels.n_voxels,
            "inactive_voxels": mapper.voxels.n_voxels - mapper.voxels.n_active,
            "depth_pixels_used": data.n_valid, "map_s": t1 - t0, "render_s": time.perf_counter() - t1}


def probe_tsdf(frame: RGBDFrame, T_world_cam: np.ndarray, preset: str) -> dict:
    """The TSDF baseline's render-back: one integration at the pose, ray-cast at the same pose."""
    t0 = time.perf_counter()
    p = depth_probe(tsdf_render_back(frame, T_world_cam, BASELINE_PRESETS[preset][1]), frame.depth_m)
    return {"median_abs_cm": 100 * p.median_abs_m, "mean_abs_cm": 100 * p.mean_abs_m,
            "rendered_fraction": p.rendered_fraction, "s": time.perf_counter() - t0}


def _median_ms(fn, repeats: int) -> float:  # noqa: ANN001
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def time_per_frame_costs(config: VoxFusionConfig, repeats: int) -> dict:
    """Median ms of the depth filter and of the evidence update on one 640x480 frame, one CPU thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        folder = DATA / "sevenscenes_redkitchen"
        if folder.is_dir():
            frame, source = open_capture(folder)[0], "sevenscenes_redkitchen frame 0"
        else:
            frame, source = SyntheticCapture(SyntheticConfig(n_frames=1, width=640, height=480))[0], "synthetic"
        cfg = config.mapping
        raw = frame_to_device(frame, "cpu", cfg.min_depth_m, cfg.max_depth_m, depth_filter=None)
        filtered = frame_to_device(frame, "cpu", cfg.min_depth_m, cfg.max_depth_m, depth_filter=cfg.depth_filter)
        T = torch.as_tensor(frame.T_world_cam if frame.T_world_cam is not None else np.eye(4))
        points = _backproject(filtered, T, cfg.stride_for(frame.width))
        vmap = VoxelMap(config.voxel_size_m, config.field.embed_dim)
        vmap.allocate(points)
        return {
            "frame": f"{source}, {frame.width}x{frame.height}", "torch_threads": 1,
            "depth_filter_ms": _median_ms(lambda: depth_outlier_mask(raw.depth_m, cfg.depth_filter), repeats),
            "depth_filter_dropped_fraction": 1.0 - filtered.n_valid / max(raw.n_valid, 1),
            "evidence_update_ms": _median_ms(lambda: observe_frame(vmap, filtered, T, points, cfg.evidence),
                                             repeats),
        }
    finally:
        torch.set_num_threads(threads)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="+", default=list(CAPTURES), choices=list(CAPTURES))
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.005, 0.02])
    ap.add_argument("--orientations", nargs="+", default=["axis_aligned", "rotated"],
                    choices=["axis_aligned", "rotated"])
    ap.add_argument("--variants", nargs="+", default=["off", "on"], choices=list(VARIANTS),
                    help="our configurations to probe (filter_only / evidence_only: one mechanism alone)")
    ap.add_argument("--max-width", type=int, default=320,
                    help="frames wider than this are downscaled by an integer factor (CPU render time)")
    ap.add_argument("--preset", default="cpu-small")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    ap.add_argument("--seed", type=int, default=0, help="seed of the outlier pixels")
    ap.add_argument("--timing-repeats", type=int, default=20)
    ap.add_argument("--no-baseline", action="store_true", help="skip the TSDF baseline")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "outlier_probe.json")
    args = ap.parse_args(argv)
    base = load_preset(args.preset, ["device=cpu", *args.overrides])
    costs = time_per_frame_costs(base, args.timing_repeats)
    print(f"per frame, one CPU thread, {costs['frame']}: depth filter {costs['depth_filter_ms']:.1f} ms "
          f"(drops {100 * costs['depth_filter_dropped_fraction']:.2f} % of the valid pixels), evidence update "
          f"{costs['evidence_update_ms']:.1f} ms\n")

    rows, table = [], []
    for name in args.captures:
        frame = first_frame(name, args.max_width)
        if frame is None:
            continue
        for orientation in args.orientations:
            T = first_pose(frame, orientation)
            shown = anchor_first_pose([frame], T)[0]
            for fraction in args.fractions:
                noisy = add_depth_outliers(shown, fraction, seed=args.seed)
                row = {"capture": name, "size": f"{frame.width}x{frame.height}", "orientation": orientation,
                       "outlier_fraction": fraction, "ours": {}}
                for variant in args.variants:
                    cfg = load_preset(args.preset, ["device=cpu", *args.overrides, *VARIANTS[variant]])
                    row["ours"][variant] = probe_ours(noisy, T, cfg)
                if not args.no_baseline:
                    try:
                        row["tsdf"] = probe_tsdf(noisy, T, CAPTURES[name][1])
                    except MissingDependencyError as e:
                        row["tsdf"] = {"error": str(e)}
                rows.append(row)
                line = {"capture": name, "size": row["size"], "camera": orientation, "outliers %": 100 * fraction}
                for variant in args.variants:
                    line[f"{variant} cm"] = row["ours"][variant]["median_abs_cm"]
                line["tsdf cm"] = row.get("tsdf", {}).get("median_abs_cm", float("nan"))
                line["inactive (on)"] = row["ours"].get("on", {}).get("inactive_voxels", "")
                table.append(line)
                print("  ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}" for k, v in line.items()),
                      flush=True)

    print("\nmedian |rendered - observed| depth of the first frame at its own pose (cm):")
    print(format_table(table, float_fmt=".2f"))
    result = {
        "benchmark": "outlier_probe",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/bench_outliers.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "settings": {"preset": args.preset, "overrides": args.overrides, "variants": {v: VARIANTS[v]
                                                                                     for v in args.variants},
                     "outlier_depth_range_m": [0.3, 1.0], "outlier_seed": args.seed, "max_width": args.max_width,
                     "rotation": {"deg": ROTATION_DEG, "axis": ROTATION_AXIS},
                     "tsdf_presets": {n: asdict(BASELINE_PRESETS[CAPTURES[n][1]][1]) for n in args.captures},
                     "config_on": config_to_dict(base)},
        "notes": "median_abs_cm: median |rendered - observed| over pixels valid in both, observed = the depth "
                 "given to the method (outliers included); ours = a fresh Mapper on the first frame "
                 "(first_frame_iters), render_depth_image at the same pose; off = depth filter and voxel evidence "
                 "switched off (the engine before this fix); tsdf = Open3D TSDF, one integration + ray cast at "
                 "the same pose. Times are CPU wall-clock on a shared machine.",
        "per_frame_cost": costs,
        "machine": machine_info(),
        "rows": rows,
    }
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
