"""How long ``mapping.compile``'s warm-up takes in a fresh process, with torch's compile caches cold and then warm.

Usage (from the repository root, on a CUDA machine; ``--smoke`` runs tiny sizes on a CPU)::

    python bench/bench_compile_warmup.py [--runs 2] [--out-dir bench/results]

A realtime session with ``mapping.compile: true`` maps 1.5x faster per round on an H100 (the GPU suite's
``realtime`` rows) but compiles its mapping step first: ~40-50 s in the suite's process, which a session that
starts on a user's request cannot spend. torch keeps what it compiled on disk (Inductor's FX graph cache and
AOTAutograd's cache, in ``TORCHINDUCTOR_CACHE_DIR``), so a second process compiling the same step may finish much
sooner. This runs :func:`bench.gpu_suite.warm_compiled` (an offline session over 5 frames of the 640x480 synthetic
room at the preset the suite's realtime session gets, with ``mapping.compile=true``) in ``--runs`` fresh
processes, one after another, sharing one new cache folder (the first run finds it empty), and writes the seconds
of each to ``compile-warmup-<gpu>.json``: whether a compiled mapping step could be the CUDA default with the warm-up
done before a session's first frame (a server-wide warm-up process filling the cache).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # appended: an installed voxfusion (bench/gpu_lease.sh's layout) wins
    sys.path.append(str(REPO_ROOT))

RESULT_PREFIX = "WARMUP "


def _one_run(smoke: bool) -> dict:
    """In this (fresh) process: compile the mapping step through an offline warm-up; seconds and graphs."""
    import torch

    from bench import gpu_suite

    sizes = gpu_suite.SMOKE if smoke else gpu_suite.LEASE
    device = "cuda" if torch.cuda.is_available() else "cpu"
    spec = gpu_suite.SessionSpec("synthetic", sizes.width, sizes.height, 6, 1.0, 30.0, device,
                                 (*sizes.overrides, "mapping.compile=true"))
    frames, _, cap = gpu_suite.load_frames(spec)
    config, preset = gpu_suite.session_config(spec, cap)
    t0 = time.perf_counter()
    seconds = gpu_suite.warm_compiled(frames, config)
    return {"preset": preset, "device": device, "warmup_s": seconds, "with_imports_s": time.perf_counter() - t0,
            "graphs": gpu_suite._compiled_graphs()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=2, help="fresh processes, one after another (default 2)")
    p.add_argument("--out-dir", type=Path, default=REPO_ROOT / "bench" / "results")
    p.add_argument("--smoke", action="store_true", help="tiny sizes (a CPU check of the same code)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(RESULT_PREFIX + json.dumps(_one_run(args.smoke)), flush=True)
        return 0
    from bench.machine import machine_info
    from voxfusion.core.eval.report import write_json

    runs = []
    with tempfile.TemporaryDirectory(prefix="voxfusion-inductor-") as cache:
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
        for k in range(args.runs):
            cmd = [sys.executable, "-P", str(Path(__file__).resolve()), "--child", *(["--smoke"] if args.smoke else [])]
            t0 = time.perf_counter()
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, check=False)
            lines = [ln for ln in out.stdout.splitlines() if ln.startswith(RESULT_PREFIX)]
            if out.returncode != 0 or not lines:
                print(out.stdout[-2000:], out.stderr[-4000:], file=sys.stderr)
                raise SystemExit(f"run {k + 1} failed (exit {out.returncode})")
            row = {"run": k + 1, "cache": "cold" if k == 0 else "warm", "process_s": time.perf_counter() - t0,
                   **json.loads(lines[-1][len(RESULT_PREFIX):])}
            runs.append(row)
            print(f"run {row['run']} ({row['cache']} cache): warm-up {row['warmup_s']:.1f} s, process "
                  f"{row['process_s']:.1f} s, {row['graphs']} graphs", flush=True)
    from bench.gpu_suite import _slug

    machine = machine_info()
    import torch

    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    name = f"compile-warmup-{_slug(device)}{'-smoke' if args.smoke else ''}.json"
    result = {"benchmark": "mapping.compile warm-up per fresh process", "machine": machine,
              "command": " ".join(sys.argv), "smoke": args.smoke, "runs": runs}
    write_json(args.out_dir / name, result)
    print(f"wrote {args.out_dir / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
