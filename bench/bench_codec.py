"""Wire-format benchmark: bytes per frame and encode / decode time of every depth encoding.

Usage (from the repository root)::

    python bench/bench_codec.py                 # real data when ../shared/data exists, plus synthetic
    python bench/bench_codec.py --source synthetic --repeats 50

Scenarios:

* ``iphone``: 256x192 depth (+ confidence, + device pose, intrinsics stated for 1920x1440) with 640x480
  JPEG colour, as the iPhone client sends it. Real: Stray Scanner LiDAR depth / confidence / ARKit pose;
  the Stray capture has no colour, so the colour is a real 640x480 7-Scenes photo. Synthetic: the
  synthetic room in LiDAR mode (256x192) and a 640x480 render of the same room.
* ``vga``: 640x480 depth + 640x480 JPEG colour. Real: 7-Scenes (Kinect). Synthetic: 640x480 render.

Each row encodes / decodes ``--frames`` different frames ``--repeats`` times each (after one warm-up
call) and reports the median time per frame, as the calling thread's CPU time (robust on a shared
machine) and as wall-clock time; bytes are the mean over the frames. All frames are loaded before
anything is timed. The ``raw`` baseline row (``raw_f32_m`` depth +
``raw_rgb8`` colour, uncompressed) is what every other row's compression ratio is measured against.
Writes ``bench/results/codec.json`` (with :func:`bench.machine.machine_info`).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.machine import machine_info  # noqa: E402
from voxfusion.core.datasets.frame import RGBDFrame  # noqa: E402
from voxfusion.core.eval.report import write_json  # noqa: E402
from voxfusion.core.geometry import scale_intrinsics  # noqa: E402
from voxfusion.proto import DEPTH_ENCODINGS, WireIntrinsics, decode_frame, encode_frame  # noqa: E402
from voxfusion.proto.container import unpack_message  # noqa: E402

DATA_DIR = (REPO_ROOT / ".." / "shared" / "data").resolve()
JPEG_QUALITY = 90


@dataclass(frozen=True)
class Sample:
    """One frame to send: the frame (depth resolution) plus what the client would put on the wire."""

    frame: RGBDFrame
    color: np.ndarray | None
    """``[Hc, Wc, 3]`` colour at its own (wire) resolution."""
    intrinsics: WireIntrinsics


@dataclass(frozen=True)
class Row:
    scenario: str
    source: str
    depth_encoding: str
    color_encoding: str
    depth_wh: str
    color_wh: str
    bytes_per_frame: float
    depth_bytes: float
    color_bytes: float
    confidence_bytes: float
    ratio_vs_raw: float
    encode_ms: float
    """Median wall-clock milliseconds per frame."""
    decode_ms: float
    encode_cpu_ms: float
    """Median CPU time of the calling thread per frame (ignores time spent waiting for a shared CPU)."""
    decode_cpu_ms: float


def _iphone_real(n: int) -> list[Sample]:
    from voxfusion.core.datasets import SevenScenesCapture, StrayCapture

    stray = StrayCapture(DATA_DIR / "stray_iphone_lidar", confidence_threshold=None)
    photos = SevenScenesCapture(DATA_DIR / "sevenscenes_redkitchen")
    out = []
    for i in range(n):
        f = stray[100 + 150 * i]
        # ARKit states K for the 1920x1440 colour image; Stray's K was scaled to 256x192: scale it back.
        K_arkit = scale_intrinsics(f.K, (f.width, f.height), (1920, 1440))
        out.append(Sample(f, photos[50 + 80 * i].color, WireIntrinsics.from_K(K_arkit, 1920, 1440)))
    return out


def _iphone_synthetic(n: int) -> list[Sample]:
    from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

    lidar = SyntheticCapture(SyntheticConfig(n_frames=10 * n, lidar=True))
    photo = SyntheticCapture(SyntheticConfig(n_frames=10 * n, width=640, height=480))
    out = []
    for i in range(n):
        f = lidar[10 * i]
        out.append(Sample(f, photo[10 * i].color, WireIntrinsics.from_K(f.K, f.width, f.height)))
    return out


def _vga_real(n: int) -> list[Sample]:
    from voxfusion.core.datasets import SevenScenesCapture

    cap = SevenScenesCapture(DATA_DIR / "sevenscenes_redkitchen")
    return [Sample(f, f.color, WireIntrinsics.from_K(f.K, f.width, f.height))
            for f in (cap[50 + 80 * i] for i in range(n))]


def _vga_synthetic(n: int) -> list[Sample]:
    from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

    cap = SyntheticCapture(SyntheticConfig(n_frames=10 * n, width=640, height=480))
    return [Sample(f, f.color, WireIntrinsics.from_K(f.K, f.width, f.height))
            for f in (cap[10 * i] for i in range(n))]


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    """Median (wall ms, thread CPU ms) of ``repeats`` calls after one warm-up call."""
    fn()  # warm-up: first-call allocations and page faults are not what a running server pays
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.thread_time()
        fn()
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(wall), 1e3 * statistics.median(cpu)


def _measure(scenario: str, source: str, samples: list[Sample], depth_encoding: str, color_encoding: str,
             repeats: int, raw_bytes: float | None) -> Row:
    def enc(s: Sample) -> bytes:
        return encode_frame(s.frame, seq=1, session="bench", depth_encoding=depth_encoding,
                            color_encoding=color_encoding, confidence_encoding="zstd_u8", jpeg_quality=JPEG_QUALITY,
                            color=s.color, intrinsics=s.intrinsics)

    messages = [enc(s) for s in samples]
    for s, m in zip(samples, messages, strict=True):  # every message must decode back to the frame's depth grid
        if decode_frame(m).frame.depth_m.shape != s.frame.depth_m.shape:
            raise RuntimeError(f"{scenario}/{depth_encoding}: decoded depth has the wrong shape")
    parts = [unpack_message(m)[1] for m in messages]
    enc_t = [_median_ms(lambda s=s: enc(s), repeats) for s in samples]
    dec_t = [_median_ms(lambda m=m: decode_frame(m), repeats) for m in messages]
    f, c = samples[0].frame, samples[0].color
    total = float(np.mean([len(m) for m in messages]))
    return Row(
        scenario=scenario, source=source, depth_encoding=depth_encoding, color_encoding=color_encoding,
        depth_wh=f"{f.width}x{f.height}", color_wh="-" if c is None else f"{c.shape[1]}x{c.shape[0]}",
        bytes_per_frame=total, depth_bytes=float(np.mean([len(p.depth) for p in parts])),
        color_bytes=float(np.mean([len(p.color) for p in parts])),
        confidence_bytes=float(np.mean([len(p.confidence) for p in parts])),
        ratio_vs_raw=(raw_bytes / total) if raw_bytes else 1.0,
        encode_ms=statistics.median(t[0] for t in enc_t), decode_ms=statistics.median(t[0] for t in dec_t),
        encode_cpu_ms=statistics.median(t[1] for t in enc_t), decode_cpu_ms=statistics.median(t[1] for t in dec_t),
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", choices=["auto", "real", "synthetic"], default="auto",
                    help="auto: real data when present, and synthetic always")
    ap.add_argument("--frames", type=int, default=4, help="different frames per row")
    ap.add_argument("--repeats", type=int, default=20, help="timed repetitions per frame (median taken)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "codec.json")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)  # one frame at a time, as a server worker decodes it

    have_real = (DATA_DIR / "stray_iphone_lidar").is_dir() and (DATA_DIR / "sevenscenes_redkitchen").is_dir()
    if args.source == "real" and not have_real:
        raise SystemExit(f"real captures not found under {DATA_DIR}")
    sets = []
    if args.source in ("auto", "real") and have_real:
        sets += [("iphone", "real (Stray depth + 7-Scenes colour)", _iphone_real),
                 ("vga", "real (7-Scenes)", _vga_real)]
    if args.source in ("auto", "synthetic"):
        sets += [("iphone", "synthetic", _iphone_synthetic), ("vga", "synthetic", _vga_synthetic)]

    rows: list[Row] = []
    # load everything before timing anything, so every row runs in the same process state (allocator, caches)
    loaded = [(scenario, source, load(args.frames)) for scenario, source, load in sets]
    for scenario, source, samples in loaded:
        raw = _measure(scenario, source, samples, "raw_f32_m", "raw_rgb8", args.repeats, None)
        rows.append(raw)
        for enc in DEPTH_ENCODINGS:
            rows.append(_measure(scenario, source, samples, enc, "jpeg", args.repeats, raw.bytes_per_frame))

    machine = machine_info()
    print(f"\nwire format v1, JPEG quality {JPEG_QUALITY}, confidence zstd_u8; median of {args.repeats} x "
          f"{args.frames} frames; {machine['cpu_model']} ({machine['cpu_usable_cores']} usable cores), "
          "OpenCV 1 thread\n")
    head = (f"{'scenario':8s} {'source':38s} {'depth enc':12s} {'colour':9s} {'depth':8s} {'colour':8s} "
            f"{'KB/frame':>9s} {'depth KB':>9s} {'col KB':>7s} {'ratio':>6s} {'enc cpu':>8s} {'dec cpu':>8s} "
            f"{'enc wall':>9s} {'dec wall':>9s}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r.scenario:8s} {r.source:38s} {r.depth_encoding:12s} {r.color_encoding:9s} {r.depth_wh:8s} "
              f"{r.color_wh:8s} {r.bytes_per_frame / 1e3:9.1f} {r.depth_bytes / 1e3:9.1f} {r.color_bytes / 1e3:7.1f} "
              f"{r.ratio_vs_raw:6.1f} {r.encode_cpu_ms:8.2f} {r.decode_cpu_ms:8.2f} {r.encode_ms:9.2f} "
              f"{r.decode_ms:9.2f}")

    result = {
        "benchmark": "codec",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/bench_codec.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "settings": {"jpeg_quality": JPEG_QUALITY, "confidence_encoding": "zstd_u8", "zstd_level": 3,
                     "png_compression": 1, "frames": args.frames, "repeats": args.repeats, "opencv_threads": 1},
        "notes": "bytes are whole messages (prelude + JSON header + payloads + CRC); ratio_vs_raw = bytes of the "
                 "uncompressed row (raw_f32_m depth + raw_rgb8 colour at the same resolutions) / bytes of the row; "
                 "times are median milliseconds per frame on the CPU named in machine: *_cpu_ms is the calling "
                 "thread's CPU time (robust on a shared machine), *_ms wall-clock (includes waiting for a busy "
                 "CPU); compare rows with each other, not with other runs",
        "machine": machine,
        "rows": [asdict(r) for r in rows],
    }
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
