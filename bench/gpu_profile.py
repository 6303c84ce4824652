"""Where a tracked frame's time goes on a GPU: the geometric tracker with and without its CUDA graphs, and a profile.

Usage (from the repository root, on a CUDA machine; ``bash bench/gpu_lease.sh OUT_DIR`` runs it after the suite
when ``GPU_PROFILE=1``)::

    python bench/gpu_profile.py [--width 640 --height 480] [--frames 30]

An offline :class:`SlamSystem` at the preset :func:`preset_for` picks for the synthetic room on CUDA, once with
``tracking.cuda_graphs=true`` and once with ``false``, in this process: after 8 frames, 12 frames tracked with the map
fixed (ms per tracked frame, median of the last 10, each between ``torch.cuda.synchronize()`` calls), then 6 whole
offline frames (tracking and a mapping round each), then, with the graphs, a ``torch.profiler`` table of 3 more
frames (self CPU time per operator, and the counts of kernel launches, graph launches and host synchronisations).
Prints everything (this is a diagnosis, not a benchmark of record: ``make bench-gpu`` is).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # appended: an installed voxfusion (bench/gpu_lease.sh's layout) wins
    sys.path.append(str(REPO_ROOT))

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.slam import SlamSystem  # noqa: E402
from voxfusion.core.slam.presets import preset_for  # noqa: E402

HOST_CALLS = ("cudaLaunchKernel", "cudaGraphLaunch", "cudaStreamSynchronize", "cudaMemcpyAsync",
              "cudaGraphInstantiate")


def _timed(fn, *args):  # noqa: ANN001, ANN202
    """``(fn(*args), milliseconds)``, the device synchronised before and after."""
    torch.cuda.synchronize()
    t = time.perf_counter()
    out = fn(*args)
    torch.cuda.synchronize()
    return out, (time.perf_counter() - t) * 1e3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", type=int, default=30, help="synthetic frames decoded (at least 29)")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("gpu_profile needs a CUDA device", file=sys.stderr)
        return 2
    cap = SyntheticCapture(SyntheticConfig(n_frames=max(29, args.frames), width=args.width, height=args.height))
    frames = [cap[i] for i in range(len(cap))]
    print(f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}", flush=True)
    for graphs in ("true", "false"):
        choice = preset_for(cap, "cuda", ["mode=offline", f"tracking.cuda_graphs={graphs}"])
        slam = SlamSystem(choice.config)
        for f in frames[:8]:
            slam.process(f)
        tracker = slam.tracker
        times, res = [], None
        for k in range(8, 20):  # the map fixed: tracking alone
            data = slam._to_device(frames[k])
            res, ms = _timed(tracker.track, data, frames[k - 1].T_world_cam)
            times.append(ms)
            tracker.remember(data, res.T_world_cam)
        print(f"graphs={graphs} preset={choice.preset} track ms/frame median {statistics.median(times[2:]):.2f} "
              f"iters {res.iterations} evals {res.iterations + tracker.sdf_stages()}", flush=True)
        whole = [_timed(slam.process, f)[1] for f in frames[20:26]]
        print(f"graphs={graphs} offline process ms/frame {[round(x) for x in whole]}", flush=True)
        g = tracker._graphs
        if g is not None:
            print(f"captures {g.captures}, capture ms total {1e3 * g.capture_s:.1f}, failed {g.failed}", flush=True)
            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                for f in frames[26:29]:
                    slam.process(f)
                torch.cuda.synchronize()
            table = prof.key_averages()
            print(table.table(sort_by="self_cpu_time_total", row_limit=25, max_name_column_width=60))
            for name in HOST_CALLS:
                ev = [e for e in table if e.key == name]
                print(name, ev[0].count if ev else 0, f"{ev[0].cpu_time_total / 1e3:.1f} ms" if ev else "")
        slam.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
