"""Ingest benchmark: frames per second one session accepts over zenoh and over HTTP, and the pose
round-trip latency (frame sent -> its pose received).

Usage (from the repository root)::

    python bench/bench_ingest.py                     # 300 frames per transport, 30 paced frames for latency
    python bench/bench_ingest.py --frames 100 --engine tiny

What runs: ``voxfusion serve`` in a subprocess (CPU, zenoh peer on a loopback port, data in a temporary
folder) and the clients of :mod:`voxfusion.clients` in this process. Frames are the iPhone case of
``proto/README.md``: 256x192 depth (``zstd_u16_mm``) + confidence (``zstd_u8``) + 640x480 JPEG colour
(quality 90), ARKit intrinsics for 1920x1440: real Stray Scanner depth with real 7-Scenes colour when
``../shared/data`` is present, else the synthetic room (LiDAR mode + a 640x480 render). Messages are
encoded before anything is timed.

* **Throughput** (per transport, one realtime session each, the engine running): the client sends
  ``--frames`` messages as fast as the server acknowledges them and reports accepted frames / second
  from the first send to the last acknowledgement. An acknowledgement means the frame was decoded,
  checked and durably recorded (``fdatasync``) and queued for tracking (HTTP 202 / zenoh reply / zenoh
  ack). Rows: ``zenoh get`` (``ZenohClient.send_frame_async``, up to 16 frames in flight), ``zenoh put``
  (plain puts, at most 32 unacknowledged, acknowledgements on ``.../acks``), ``http``
  (``Client.send_frame_async``: one keep-alive connection, frames in order, up to 16 queued).
* **Pose latency** (per transport, a new realtime session): ``--latency-frames`` frames paced at
  ``--latency-fps``; for each, the time from the send call to the arrival of its pose on the client
  (zenoh: the ``poses`` key; HTTP: the ``/poses/stream`` WebSocket, or polling ``/poses/latest`` every 5 ms
  when the ``websockets`` package is missing). Frames the realtime tracker skipped
  to keep up have no pose (counted). Also the acknowledgement latency (send -> ack) of the same frames.

Writes ``bench/results/ingest.json`` (with :func:`bench.machine.machine_info`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from concurrent.futures import Future
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402

from bench.bench_codec import DATA_DIR, JPEG_QUALITY, _iphone_real, _iphone_synthetic  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from voxfusion.clients import Client  # noqa: E402
from voxfusion.clients.base import BaseClient  # noqa: E402
from voxfusion.clients.zenoh_client import ZenohClient  # noqa: E402
from voxfusion.clients.zenoh_keys import session_key  # noqa: E402
from voxfusion.core.eval.report import write_json  # noqa: E402
from voxfusion.proto import encode_frame  # noqa: E402
from voxfusion.server.child import ServeProcess  # noqa: E402

TINY = ["mapping.rays_per_frame=128", "tracking.rays=128", "tracking.iters=10", "mapping.first_frame_iters=30",
        "field.sdf_hidden=32", "field.color_hidden=32", "mesh_res=4"]


@dataclass(frozen=True)
class ThroughputRow:
    transport: str
    frames: int
    seconds: float
    accepted_fps: float
    mbit_per_s: float
    frames_tracked: int
    frames_dropped: int
    """Frames recorded but skipped by the realtime tracker to keep up (not an ingest loss)."""


@dataclass(frozen=True)
class LatencyRow:
    transport: str
    frames: int
    fps: float
    poses: int
    skipped: int
    pose_median_ms: float | None
    pose_p90_ms: float | None
    pose_max_ms: float | None
    ack_median_ms: float
    ack_p90_ms: float


def _messages(n: int, n_distinct: int) -> tuple[list[bytes], str]:
    have_real = (DATA_DIR / "stray_iphone_lidar").is_dir() and (DATA_DIR / "sevenscenes_redkitchen").is_dir()
    samples = _iphone_real(n_distinct) if have_real else _iphone_synthetic(n_distinct)
    source = "real (Stray depth + 7-Scenes colour)" if have_real else "synthetic"
    out = []
    for i in range(n):
        s = samples[i % len(samples)]
        frame = dataclasses.replace(s.frame, timestamp_s=i / 30.0, index=i)
        out.append(encode_frame(frame, seq=i, depth_encoding="zstd_u16_mm", color_encoding="jpeg",
                                confidence_encoding="zstd_u8", jpeg_quality=JPEG_QUALITY, color=s.color,
                                intrinsics=s.intrinsics))
    return out, source


def _delete(server: ServeProcess, client: BaseClient) -> None:
    server.http.delete(f"/sessions/{client.session.id}", headers={"Authorization": f"Bearer {client.session.token}"})


def _throughput(name: str, client: BaseClient, server: ServeProcess, messages: list[bytes], overrides: list[str]) -> \
        ThroughputRow:
    client.create_session(f"bench-{name}", overrides or None, mode="realtime")
    n = len(messages)
    if name == "zenoh put":
        z = client._z  # the client's zenoh session: plain puts, acks on .../acks
        got, refused, done = [0], [], threading.Event()
        window = threading.Semaphore(32)  # puts have no flow control: keep at most 32 unacknowledged

        def on_ack(sample) -> None:
            body = json.loads(sample.payload.to_bytes())
            window.release()
            if not body.get("ok"):
                refused.append(body)
                done.set()
            got[0] += 1
            if got[0] == n:
                done.set()

        sub = z.declare_subscriber(session_key(client.session.id, "acks"), on_ack)
        client.status()  # the server knows the subscription once it answers (see ZenohClient.subscribe_poses)
        pub = z.declare_publisher(session_key(client.session.id, "frames"),
                                  congestion_control=sys.modules["zenoh"].CongestionControl.BLOCK)
        token = client.session.token.encode()
        t0 = time.perf_counter()
        for m in messages:
            if not window.acquire(timeout=600) or refused:
                break
            pub.put(m, attachment=token)
        if not done.wait(600) or refused:
            raise SystemExit(f"zenoh put: {got[0]} of {n} acks; refused: {refused[:1]}")
        seconds = time.perf_counter() - t0
        sub.undeclare()
        pub.undeclare()
    else:
        t0 = time.perf_counter()
        futures = [client.send_bytes_async(m) for m in messages]
        for f in futures:
            f.result(timeout=600)
        seconds = time.perf_counter() - t0
    st = client.status()
    _delete(server, client)
    mbit = 8 * sum(len(m) for m in messages) / seconds / 1e6
    return ThroughputRow(name, n, seconds, n / seconds, mbit, st.frames_tracked, st.frames_dropped)


def _latency(name: str, client: BaseClient, server: ServeProcess, messages: list[bytes], fps: float,
             overrides: list[str]) -> LatencyRow:
    client.create_session(f"bench-latency-{name}", overrides or None, mode="realtime")
    arrived: dict[int, float] = {}
    stop = threading.Event()
    if isinstance(client, ZenohClient):
        client.subscribe_poses(lambda pose: arrived.setdefault(pose.seq, time.perf_counter()))
        reader = None
    else:
        try:
            from websockets.sync.client import connect
        except ImportError:  # no WebSocket client: poll /poses/latest every 5 ms instead
            connect = None
        url = f"ws://127.0.0.1:{server.port}/sessions/{client.session.id}/poses/stream?token={client.session.token}"
        connected = threading.Event()

        def read() -> None:
            if connect is None:
                connected.set()
                while not stop.is_set():
                    pose = client.latest_pose()
                    if pose is not None:
                        arrived.setdefault(pose.seq, time.perf_counter())
                    time.sleep(0.005)
                return
            with connect(url) as ws:
                connected.set()
                while not stop.is_set():
                    try:
                        body = json.loads(ws.recv(timeout=0.2))
                    except TimeoutError:
                        continue
                    if "seq" in body:
                        arrived.setdefault(int(body["seq"]), time.perf_counter())

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        connected.wait(10)
        time.sleep(0.5)  # the WebSocket handler registers its pose listener after the handshake
    sent: dict[int, float] = {}
    acked: dict[int, float] = {}
    futures: list[Future[int]] = []
    t_start = time.perf_counter()
    for i, m in enumerate(messages):
        due = t_start + i / fps
        while (left := due - time.perf_counter()) > 0:
            time.sleep(min(0.002, left))
        sent[i] = time.perf_counter()
        fut = client.send_bytes_async(m)
        fut.add_done_callback(lambda f, i=i: acked.setdefault(i, time.perf_counter()))
        futures.append(fut)
    for f in futures:
        f.result(timeout=300)
    deadline = time.perf_counter() + 30
    while time.perf_counter() < deadline:  # wait for the tracker to catch up with the last frames
        st = client.status()
        if st.frames_tracked + st.frames_dropped >= len(messages) and st.frames_queued == 0:
            break
        time.sleep(0.05)
    time.sleep(0.3)  # let the last poses travel
    stop.set()
    if reader is not None:
        reader.join(timeout=5)
    _delete(server, client)
    lat = sorted(1e3 * (arrived[i] - sent[i]) for i in sent if i in arrived)
    ack = sorted(1e3 * (acked[i] - sent[i]) for i in sent)

    def pct(xs: list[float], q: float) -> float:
        return float(np.percentile(xs, q))

    return LatencyRow(name, len(messages), fps, len(lat), len(messages) - len(lat),
                      statistics.median(lat) if lat else None, pct(lat, 90) if lat else None,
                      max(lat) if lat else None, statistics.median(ack), pct(ack, 90))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per throughput run")
    ap.add_argument("--repeats", type=int, default=3, help="throughput runs per transport (interleaved)")
    ap.add_argument("--latency-frames", type=int, default=30, help="paced frames per latency run")
    ap.add_argument("--latency-fps", type=float, default=5.0, help="send rate of the latency runs")
    ap.add_argument("--engine", choices=["server-default", "tiny"], default="server-default",
                    help="server-default: the server's CPU preset (cpu-small); tiny: 128 rays, 10 tracking "
                         "iterations (isolates ingest from engine load)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "ingest.json")
    args = ap.parse_args(argv)
    overrides = TINY if args.engine == "tiny" else []

    load_before = os.getloadavg()[0]
    messages, source = _messages(args.frames, 6)
    latency_messages = messages[: args.latency_frames]
    mean_kb = float(np.mean([len(m) for m in messages])) / 1e3
    tmp = Path(tempfile.mkdtemp(prefix="voxfusion-bench-ingest-"))
    server = ServeProcess(tmp / "data", "--max-pending-frames", "64", zenoh=True)
    throughput: list[ThroughputRow] = []
    latency: list[LatencyRow] = []
    try:
        zc = ZenohClient(connect=[server.zenoh_endpoint], max_in_flight=16, timeout_s=120)
        hc = Client(server.url, max_in_flight=16)
        for _ in range(args.repeats):  # interleaved, so a busy spell of a shared machine hits every transport
            for name, client in (("zenoh get", zc), ("zenoh put", zc), ("http", hc)):
                throughput.append(_throughput(name, client, server, messages, overrides))
                print(f"  {throughput[-1]}", flush=True)
        for name, client in (("zenoh", zc), ("http", hc)):
            latency.append(_latency(name, client, server, latency_messages, args.latency_fps, overrides))
            print(f"  {latency[-1]}", flush=True)
        zc.close()
        hc.close()
    finally:
        server.stop()

    machine = machine_info()
    print(f"\ningest, one session per row, realtime mode, engine {args.engine}; frames: {source}, 256x192 "
          f"zstd_u16_mm depth + zstd_u8 confidence + 640x480 JPEG q{JPEG_QUALITY}, mean {mean_kb:.1f} KB; "
          f"{machine['cpu_model']} ({machine['cpu_usable_cores']} usable cores), server and client on this machine; "
          f"1-min load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after\n")
    head = f"{'transport':10s} {'runs':>4s} {'frames':>6s} {'accepted fps median':>20s} {'min':>6s} {'max':>6s} " \
           f"{'Mbit/s':>7s} {'tracked':>8s} {'skipped':>8s}"
    print(head)
    print("-" * len(head))
    summary = {}
    for name in dict.fromkeys(r.transport for r in throughput):
        rows = [r for r in throughput if r.transport == name]
        fps = [r.accepted_fps for r in rows]
        summary[name] = {"runs": len(rows), "accepted_fps_median": statistics.median(fps), "accepted_fps_min": min(fps),
                         "accepted_fps_max": max(fps),
                         "mbit_per_s_median": statistics.median(r.mbit_per_s for r in rows)}
        print(f"{name:10s} {len(rows):4d} {rows[0].frames:6d} {statistics.median(fps):20.1f} {min(fps):6.1f} "
              f"{max(fps):6.1f} {summary[name]['mbit_per_s_median']:7.1f} {sum(r.frames_tracked for r in rows):8d} "
              f"{sum(r.frames_dropped for r in rows):8d}")
    print()
    head = f"{'transport':10s} {'frames':>6s} {'fps':>5s} {'poses':>6s} {'pose median ms':>15s} {'p90':>7s} " \
           f"{'max':>7s} {'ack median ms':>14s} {'p90':>7s}"
    print(head)
    print("-" * len(head))

    def f(x: float | None) -> str:
        return "-" if x is None else f"{x:.0f}"

    for r in latency:
        print(f"{r.transport:10s} {r.frames:6d} {r.fps:5.1f} {r.poses:6d} {f(r.pose_median_ms):>15s} "
              f"{f(r.pose_p90_ms):>7s} {f(r.pose_max_ms):>7s} {r.ack_median_ms:14.1f} {r.ack_p90_ms:7.1f}")

    result = {
        "benchmark": "ingest",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/bench_ingest.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "settings": {"frames": args.frames, "repeats": args.repeats, "latency_frames": args.latency_frames,
                     "latency_fps": args.latency_fps,
                     "engine": args.engine, "engine_overrides": overrides, "source": source,
                     "mean_message_bytes": mean_kb * 1e3, "depth": "256x192 zstd_u16_mm",
                     "color": f"640x480 jpeg q{JPEG_QUALITY}", "confidence": "zstd_u8", "session_mode": "realtime",
                     "zenoh_max_in_flight": 16, "http_max_in_flight": 16},
        "targets": {"zenoh_fps": 60, "http_fps": 30},
        "notes": "accepted fps: frames acknowledged per second by one session (decoded, checked, fdatasync'ed to "
                 "its recording, queued for tracking) from the first send to the last acknowledgement, with the "
                 "session's engine running (the realtime tracker skips frames it cannot keep up with: 'skipped'); "
                 "server (voxfusion serve subprocess) and client share this machine's CPU cores. Pose latency: "
                 "send call -> the frame's pose received by the client (zenoh poses key / HTTP WebSocket), frames "
                 "paced at latency_fps.",
        "machine": machine,
        "load_average_1min_before_after": [load_before, os.getloadavg()[0]],
        "throughput_summary": summary,
        "throughput": [asdict(r) for r in throughput],
        "latency": [asdict(r) for r in latency],
    }
    write_json(args.out, result)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
