"""Full SLAM on the real iPhone LiDAR capture (Stray Scanner, 942 frames, depth only), with and without the
ARKit device-pose prior, judged two ways: ATE against the ARKit poses (themselves a VIO estimate with
drift, not ground truth) and the GT-free multi-view depth consistency of each trajectory next to ARKit's.

Usage (from the repository root)::

    python bench/bench_stray.py                                  # both variants, iphone-small preset
    python bench/bench_stray.py --prior on --max-frames 300 --set tracking.iters=20

Each variant runs ``voxfusion run`` (offline mode, every frame) in this process; outputs go to
``bench/logs/stray_<variant>/``; the summary, with the machine and the exact config, goes to
``bench/results/stray_iphone_<preset>.json``.
"""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

DEFAULT_CAPTURE = REPO_ROOT.parent / "shared" / "data" / "stray_iphone_lidar"


def run_variant(capture_path: Path, preset: str, overrides: list[str], prior: bool, max_frames: int | None,
                out_root: Path) -> dict:
    """One SLAM run; returns its ATE, depth consistency, speed and lost/keyframe counts."""
    from voxfusion.core.config import config_to_dict
    from voxfusion.core.datasets import open_capture
    from voxfusion.core.run import run_capture, timing_summary
    from voxfusion.core.slam.presets import load_preset

    name = "prior" if prior else "noprior"
    config = load_preset(preset, [*overrides, f"tracking.use_device_prior={str(prior).lower()}"])
    capture = open_capture(capture_path, limit=max_frames)
    result = run_capture(capture, config, out_root / f"stray_{name}", progress=False)
    m = result.metrics
    return {
        "variant": name,
        "frames": len(capture),
        "ate_rmse_cm_aligned": 100 * m["ate_se3"]["rmse_m"],
        "ate_rmse_cm_anchored": 100 * m["ate_none"]["rmse_m"],
        "depth_disagreement_cm": m.get("depth_consistency"),
        "stats": result.stats,
        "speed": timing_summary(result),
        "config": config_to_dict(result.slam.config),
    }


def main(argv: list[str] | None = None) -> int:
    from bench.machine import machine_info
    from voxfusion.core.eval.report import format_table, write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--capture", type=Path, default=DEFAULT_CAPTURE)
    p.add_argument("--preset", default="iphone-small")
    p.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    p.add_argument("--prior", choices=("both", "on", "off"), default="both")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results")
    args = p.parse_args(argv)
    if not args.capture.is_dir():
        print(f"capture not found: {args.capture} (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    variants = {"both": (True, False), "on": (True,), "off": (False,)}[args.prior]
    runs = [run_variant(args.capture, args.preset, args.overrides, v, args.max_frames, REPO_ROOT / "bench" / "logs")
            for v in variants]
    rows = []
    for r in runs:
        dc = r["depth_disagreement_cm"] or {}
        rows.append({"variant": r["variant"], "ATE cm (aligned)": r["ate_rmse_cm_aligned"],
                     "ATE cm (anchored)": r["ate_rmse_cm_anchored"],
                     "depth disagreement cm, ours": " / ".join(f"{v:.2f}" for v in dc.get("estimate", {}).values()),
                     "... ARKit": " / ".join(f"{v:.2f}" for v in dc.get("reference", {}).values()),
                     "lost": r["stats"].frames_lost, "fps": r["speed"]["fps"]})
    print(format_table(rows))
    gaps = next((list(r["depth_disagreement_cm"]["estimate"]) for r in runs if r["depth_disagreement_cm"]), [])
    print(f"(depth disagreement at frame gaps {', '.join(g.split('_')[1] for g in gaps)}; lower is more consistent)")
    suffix = ("" if args.max_frames is None else f"_{args.max_frames}f") + (
        "" if args.prior == "both" else f"_prior_{args.prior}")
    path = write_json(args.out / f"stray_iphone_{args.preset}{suffix}.json", {
        "benchmark": "stray_iphone_slam", "capture": str(args.capture.name), "preset": args.preset,
        "overrides": args.overrides, "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/bench_stray.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine_info(), "runs": runs,
    })
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
