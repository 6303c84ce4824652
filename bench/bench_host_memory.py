"""The engine's C-heap limits (``core/host_memory.py``) against the C library's defaults, end to end.

Usage (from the repository root)::

    python bench/bench_host_memory.py                  # 3 pairs, 100 frames -> bench/results/host_memory.json
    python bench/bench_host_memory.py --pairs 1 --frames 10 --out /tmp/hm.json      # a quick look

Each run is a fresh process (the limits are process-wide and cannot be taken back) running ``SlamSystem``
offline on the synthetic room at the preset ``voxfusion run`` picks on this machine; the reference run sets
``VOXFUSION_HEAP_DEFAULTS=1``. Runs alternate (reference, limits, reference, ...) so a drift in the machine's
speed hits both; the ratio is taken pair by pair. Per run: frames/s (processing time, as ``bench/run.py``
counts it), minor page faults and system CPU seconds during the frames, peak resident memory of the process.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from bench.machine import machine_info  # noqa: E402

_CHILD = """
import json, resource, sys, time
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.slam import SlamSystem
from voxfusion.core.slam.presets import preset_for
from voxfusion.core import host_memory
n, seed = int(sys.argv[1]), int(sys.argv[2])
capture = SyntheticCapture(SyntheticConfig(n_frames=n, seed=seed))
choice = preset_for(capture)
slam = SlamSystem(choice.config)
frames = list(capture.frames(0, n))
before = resource.getrusage(resource.RUSAGE_SELF)
t0 = time.perf_counter()
for frame in frames:
    slam.process(frame)
wall = time.perf_counter() - t0
after = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"preset": choice.preset, "limits_applied": host_memory.retain_freed_memory(), "fps": n / wall,
                  "minor_faults": after.ru_minflt - before.ru_minflt, "sys_s": after.ru_stime - before.ru_stime,
                  "user_s": after.ru_utime - before.ru_utime, "peak_rss_mb": after.ru_maxrss / 1024.0}))
"""


def run_child(frames: int, seed: int, defaults: bool) -> dict:
    """One fresh process; ``defaults``: the C library's heap defaults (the reference)."""
    env = dict(os.environ)
    env.pop("VOXFUSION_HEAP_DEFAULTS", None)
    if defaults:
        env["VOXFUSION_HEAP_DEFAULTS"] = "1"
    out = subprocess.run([sys.executable, "-c", _CHILD, str(frames), str(seed)], env=env, cwd=REPO_ROOT,
                         capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"benchmark run failed (exit {out.returncode}):\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _median(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=3, help="reference/limits pairs (default 3)")
    ap.add_argument("--frames", type=int, default=100, help="synthetic room frames per run (default 100)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "host_memory.json")
    args = ap.parse_args(argv)
    if args.pairs < 1 or args.frames < 2:
        ap.error("--pairs must be >= 1 and --frames >= 2")
    reference, limits = [], []
    for k in range(args.pairs):
        reference.append(run_child(args.frames, args.seed, defaults=True))
        limits.append(run_child(args.frames, args.seed, defaults=False))
        print(f"pair {k + 1}/{args.pairs}: {reference[-1]['fps']:.2f} -> {limits[-1]['fps']:.2f} frames/s, "
              f"{reference[-1]['minor_faults']} -> {limits[-1]['minor_faults']} minor faults", flush=True)
    if any(r["limits_applied"] for r in reference) or not all(r["limits_applied"] for r in limits):
        print("note: this C library did not take the limits (not glibc?): both columns ran its defaults")
    ratios = [b["fps"] / a["fps"] for a, b in zip(reference, limits, strict=True)]
    summary = {
        name: {key: _median(rows, key) for key in ("fps", "minor_faults", "sys_s", "user_s", "peak_rss_mb")}
        for name, rows in (("defaults", reference), ("limits", limits))
    }
    summary["fps_ratio_pairwise"] = {"median": statistics.median(ratios), "min": min(ratios), "max": max(ratios)}
    doc = {
        "name": "host_memory",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/bench_host_memory.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine_info(),
        "workload": {"capture": "synthetic room 320x240", "frames": args.frames, "seed": args.seed,
                     "preset": reference[0]["preset"], "mode": "offline"},
        "summary": summary,
        "runs": {"defaults": reference, "limits": limits},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    d, m = summary["defaults"], summary["limits"]
    ratio = summary["fps_ratio_pairwise"]["median"]
    print(f"medians: {d['fps']:.2f} -> {m['fps']:.2f} frames/s (pairwise ratio {ratio:.3f}),"
          f" {d['minor_faults']:.0f} -> {m['minor_faults']:.0f} minor faults, peak RSS {d['peak_rss_mb']:.0f} -> "
          f"{m['peak_rss_mb']:.0f} MB; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
