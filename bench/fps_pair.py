"""Frames/s of Vox-Fusion against the TSDF baseline, measured frame by frame in turn in one process, so that both
meet the same machine: on a shared machine a method run a minute after the other can meet a different one (on the
2-core AMD EPYC, `bench/run.py` gave our frames/s as 0.68-0.90 of the baseline's on the same capture within an hour,
2026-11-28). Steadier, not noise-free: seed 1 gave 0.917 / 0.928 / 0.940 in three runs, seed 0 0.930 and 1.088 (our
two intra-op threads lose more than Open3D's kernels when the host takes a core away).

Both methods get the same frames, read before the clock starts (loading excluded, as in `bench/run.py`); frame
``i`` goes to one method and then the other, the order swapped every frame. A method's time for a frame is the wall
clock around its whole call, the frame's upload included on both sides (ours:
:meth:`~voxfusion.core.slam.SlamSystem.process`: upload and depth filter, tracking, fusion and the mapping round; the
baseline's: :meth:`bench.baseline_tsdf.TSDFBaselineRun.step`: the frame into Open3D's images, tracking, integration
and ray cast, where `bench/run.py` leaves the baseline's upload out: ~0.6 ms a frame at 320x240, measured).
Reported: each method's frames/s (frames / its summed processing time), their ratio, and the ratio over each block of
``--block`` frames (min / median / max: how steady the pairing held it), plus both ATEs as a sanity check
(the same poses as `bench/run.py`'s, which evaluates everything else). Accepts `bench/run.py`'s capture
options (``--method`` is ignored: it is always ``voxfusion`` against ``baseline``).

Usage (from the repository root)::

    python bench/fps_pair.py --synthetic --frames 100 --seed 1 --warm
    python bench/fps_pair.py --capture ../shared/data/sevenscenes_redkitchen --max-frames 300

Writes ``bench/results/fps_pair_<name>.json`` (``--out``) with the machine.
"""

from __future__ import annotations

import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402

from bench.baseline_tsdf import TSDFBaselineRun  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from bench.run import _baseline_config, _check_args, _open, _voxfusion_config, build_parser  # noqa: E402
from voxfusion.core.errors import VoxFusionError  # noqa: E402
from voxfusion.core.eval import TrajectoryEvalConfig, compute_ate, write_json  # noqa: E402
from voxfusion.core.slam import SlamSystem  # noqa: E402
from voxfusion.core.trajectory import Trajectory  # noqa: E402

__all__ = ["interleave", "block_ratios", "warm_precompiled", "main"]


def interleave(frames: list, step_a, step_b) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Give each frame to ``step_a`` and ``step_b`` in turn (``a`` first on even frames, ``b`` first on odd ones);
    returns their times per frame ``([N], [N])`` in milliseconds (wall clock around each call)."""
    ms_a, ms_b = np.zeros(len(frames)), np.zeros(len(frames))
    for i, frame in enumerate(frames):
        order = ((step_a, ms_a), (step_b, ms_b)) if i % 2 == 0 else ((step_b, ms_b), (step_a, ms_a))
        for step, ms in order:
            t0 = time.perf_counter()
            step(frame)
            ms[i] = (time.perf_counter() - t0) * 1e3
    return ms_a, ms_b


def block_ratios(ms_ours: np.ndarray, ms_base: np.ndarray, block: int) -> np.ndarray:
    """``ours' frames/s / the baseline's`` over consecutive blocks of ``block`` frames (the last, shorter one
    dropped unless it is the only one): the summed baseline time over the summed time of ours, per block."""
    n = len(ms_ours) if len(ms_ours) < block else len(ms_ours) // block * block
    a, b = ms_ours[:n].reshape(-1, min(block, n)), ms_base[:n].reshape(-1, min(block, n))
    return b.sum(1) / a.sum(1)


def warm_precompiled(config, frames: list) -> None:  # noqa: ANN001
    """Run our engine once over ``frames`` and wait for the compile jobs it started (``tracking.precompiled``), so that
    a run after it finds every artifact its variants need."""
    from voxfusion.core.slam.tracking_sdf import PRECOMPILED_LINEARIZE

    print("[fps_pair] warm-up run (precompiled tracker)", file=sys.stderr, flush=True)
    warm = SlamSystem(config)
    for frame in frames:
        warm.process(frame)
    if not PRECOMPILED_LINEARIZE.wait(timeout_s=1800):
        print("[fps_pair] compile jobs still running after 30 min; measuring anyway", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    parser.description = __doc__.split("\n\n")[0]
    parser.add_argument("--block", type=int, default=10, help="frames per block of the blockwise ratio")
    parser.add_argument("--warm", action="store_true",
                        help="first run our engine once over the frames and wait for the precompiled tracker's "
                             "compile jobs (tracking.precompiled), so that the measured run loads every artifact "
                             "it meets, as a machine's later runs do")
    args = parser.parse_args(argv)
    _check_args(parser, args)
    try:
        capture, _, default_name, capture_desc = _open(args)
        name = "fps_pair_" + (args.name or default_name)
        frames = list(capture.frames(0, len(capture)))  # read before the clock starts
        preset, config = _voxfusion_config(args, capture)
        base_preset, base_config = _baseline_config(capture, args)
        if args.warm:
            warm_precompiled(config, frames)
        slam = SlamSystem(config)
        baseline = TSDFBaselineRun(base_config)
        print(f"[fps_pair] voxfusion ({preset}) and baseline ({base_preset}) in turn on {name}, {len(frames)} frames",
              file=sys.stderr, flush=True)
        with baseline.quiet():
            ms_ours, ms_base = interleave(frames, slam.process, baseline.step)
    except VoxFusionError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    fps_ours, fps_base = len(frames) / (ms_ours.sum() / 1e3), len(frames) / (ms_base.sum() / 1e3)
    variants = slam.tracker.precompiled if slam.tracker is not None else None
    blocks = block_ratios(ms_ours, ms_base, args.block)
    ate = {}
    if all(f.T_world_cam is not None for f in frames):
        reference = Trajectory(np.array([f.timestamp_s for f in frames]), np.stack([f.T_world_cam for f in frames]))
        for method, traj in (("voxfusion", slam.trajectory()), ("baseline", baseline.trajectory)):
            ate[method] = compute_ate(traj, reference, TrajectoryEvalConfig(align="se3")).rmse_m * 100
    machine = machine_info()
    doc = {
        "name": name,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": shlex.join(["python", "bench/fps_pair.py", *argv]),
        "machine": machine,
        "capture": {**capture_desc, "name": capture.name, "n_frames": len(frames)},
        "method": "frame by frame in turn, order swapped every frame; loading excluded",
        "voxfusion": {"preset": preset, "fps": fps_ours, "frame_ms_median": float(np.median(ms_ours)),
                      "precompiled": None if variants is None else {
                          "warmed": args.warm, "calls_from_artifacts": variants.served,
                          "calls_rejected_by_guards": variants.fallbacks}},
        "baseline": {"preset": base_preset, "fps": fps_base, "frame_ms_median": float(np.median(ms_base))},
        "fps_ratio": fps_ours / fps_base,
        "block_ratio": {"frames": args.block, "min": float(blocks.min()), "median": float(np.median(blocks)),
                        "max": float(blocks.max())},
        "ate_cm": ate,
    }
    print(f"{name}: {machine['cpu_model']} ({machine['cpu_usable_cores']} cores)")
    print(f"  voxfusion {fps_ours:6.2f} frames/s   baseline {fps_base:6.2f} frames/s   ratio {doc['fps_ratio']:.3f}"
          f"   per {args.block} frames {blocks.min():.3f} / {np.median(blocks):.3f} / {blocks.max():.3f}"
          f" (min / median / max)")
    if variants is not None:
        print(f"  precompiled tracker: {variants.served} evaluations from artifacts, {variants.fallbacks} rejected by "
              f"their guards{' (warmed first)' if args.warm else ''}")
    if ate:
        print("  ATE cm (aligned): " + ", ".join(f"{k} {v:.2f}" for k, v in ate.items()))
    path = write_json(args.out / f"{name}.json", doc)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
