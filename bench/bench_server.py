"""Streaming-server benchmark: HTTP ingest throughput, pose latency, and sessions held at 5 fps each.

Usage (from the repository root)::

    python bench/bench_server.py                       # ~5 minutes on a 2-core CPU
    python bench/bench_server.py --seconds 10 --sessions 1 2

A real ``voxfusion serve`` runs in a subprocess on 127.0.0.1 (``--device auto``, each session on the
server's default preset: ``cpu-small`` on CPU, ``default`` on CUDA); this process is the client. Frames
are the iPhone shape: 256x192 LiDAR-like depth (``zstd_u16_mm``) + confidence (``zstd_u8``) with a
640x480 JPEG colour image (quality 90) and intrinsics stated for 640x480, rendered from the synthetic room.

Measures:

* **ingest**: frames/s accepted (202, i.e. decoded, checked and fsync'd into the recording) over HTTP by
  one session, from 1 sender and from 4 concurrent senders, and by 2 sessions at once; the session's
  engine runs meanwhile (realtime mode), as it would live. Also the POST round trip (p50 / p95).
* **latency**: frames sent at 5 fps to realtime sessions; for every frame that gets a pose, the time from
  just before its POST to its pose arriving on the session's WebSocket (p50 / p95), the fraction of frames
  that got a pose (realtime tracking skips frames it cannot keep up with) and the tracked rate. Run with
  1, 2 and 4 sessions at once: the session count at which latency or the tracked fraction degrades is
  what this machine holds at 5 fps.

Writes ``bench/results/server.json`` with :func:`bench.machine.machine_info`.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import httpx  # noqa: E402
from websockets.exceptions import ConnectionClosed  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from bench.machine import machine_info  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.eval import format_table, write_json  # noqa: E402
from voxfusion.proto import MEDIA_TYPE, WireIntrinsics, encode_frame  # noqa: E402
from voxfusion.server.child import ServeProcess  # noqa: E402

RATE_FPS = 5.0


def make_messages(n: int, seed: int) -> list[bytes]:
    """``n`` iPhone-shaped frame messages (256x192 depth + confidence, 640x480 JPEG colour)."""
    lidar = SyntheticCapture(SyntheticConfig(n_frames=n, seed=seed, lidar=True))
    vga = SyntheticCapture(SyntheticConfig(n_frames=n, seed=seed, width=640, height=480))
    out = []
    for i in range(n):
        f, c = lidar[i], vga[i]
        out.append(encode_frame(f, seq=i, color=c.color, intrinsics=WireIntrinsics.from_K(c.K, 640, 480),
                                depth_encoding="zstd_u16_mm", color_encoding="jpeg", confidence_encoding="zstd_u8"))
    return out


def _create(server: ServeProcess, name: str) -> tuple[str, dict[str, str]]:
    """A new session: its id and the ``Authorization`` header of its token."""
    r = server.http.post("/sessions", json={"name": name})
    r.raise_for_status()
    body = r.json()
    return body["id"], {"Authorization": f"Bearer {body['token']}"}


def _pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    values = sorted(values)
    return values[min(len(values) - 1, int(round(q * (len(values) - 1))))]


# ---------------------------------------------------------------------------------------------- ingest


def ingest_run(server: ServeProcess, messages: list[bytes], n_sessions: int, senders_per_session: int) -> dict:
    """Post every message to each session as fast as accepted; frames/s per session and round trips."""
    sessions = [_create(server, f"ingest-{k}") for k in range(n_sessions)]
    round_trips: list[float] = []
    refused = 0
    lock = threading.Lock()

    def send(sid: str, auth: dict[str, str], part: list[tuple[int, bytes]]) -> None:
        nonlocal refused
        headers = {**auth, "Content-Type": MEDIA_TYPE}
        with httpx.Client(base_url=server.url, timeout=120) as client:
            for _, data in part:
                while True:
                    t = time.perf_counter()
                    r = client.post(f"/sessions/{sid}/frames", content=data, headers=headers)
                    dt = time.perf_counter() - t
                    if r.status_code == 429:
                        with lock:
                            refused += 1
                        time.sleep(float(r.headers.get("Retry-After", "1")))
                        continue
                    r.raise_for_status()
                    with lock:
                        round_trips.append(dt)
                    break

    threads = []
    for sid, auth in sessions:
        indexed = list(enumerate(messages))
        for k in range(senders_per_session):
            threads.append(threading.Thread(target=send, args=(sid, auth, indexed[k::senders_per_session])))
    t0 = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t0
    for sid, auth in sessions:
        server.http.delete(f"/sessions/{sid}", headers=auth)
    n = len(messages)
    return {"sessions": n_sessions, "senders_per_session": senders_per_session, "frames_per_session": n,
            "wall_s": wall, "accepted_fps_per_session": n / wall, "accepted_fps_total": n * n_sessions / wall,
            "post_ms_p50": 1e3 * _pct(round_trips, 0.5), "post_ms_p95": 1e3 * _pct(round_trips, 0.95),
            "refused_429": refused}


# --------------------------------------------------------------------------------------------- latency


def latency_run(server: ServeProcess, messages: list[bytes], n_sessions: int, seconds: float) -> dict:
    """``n_sessions`` realtime sessions, each sent frames at 5 fps for ``seconds``; pose latency on the
    WebSocket per session."""
    n_frames = min(len(messages), int(seconds * RATE_FPS))
    sessions = [_create(server, f"latency-{k}") for k in range(n_sessions)]
    results = []
    ws_port = server.port

    def run_session(k: int, sid: str, auth: dict[str, str], out: dict) -> None:
        sent: dict[int, float] = {}
        got: dict[int, float] = {}
        acks: list[float] = []
        ready = threading.Event()
        token = auth["Authorization"].split()[1]

        def listen() -> None:
            with connect(f"ws://127.0.0.1:{ws_port}/sessions/{sid}/poses/stream?token={token}",
                         ping_interval=None, open_timeout=60) as ws:
                ready.set()
                try:
                    for text in ws:
                        msg = json.loads(text)
                        if "seq" in msg:
                            got[msg["seq"]] = time.perf_counter()
                except ConnectionClosed:  # the session is deleted after the run
                    pass

        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        ready.wait(60)
        time.sleep(0.5)  # the listener registers after the handshake
        headers = {**auth, "Content-Type": MEDIA_TYPE}
        with httpx.Client(base_url=server.url, timeout=120) as client:
            t0 = time.perf_counter() + 0.05 * k
            for i in range(n_frames):
                wait = t0 + i / RATE_FPS - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                t = time.perf_counter()
                sent[i] = t
                r = client.post(f"/sessions/{sid}/frames", content=messages[i], headers=headers)
                acks.append(time.perf_counter() - t)
                r.raise_for_status()
            send_wall = time.perf_counter() - t0
            time.sleep(3.0)  # let the last frames be tracked
            status = client.get(f"/sessions/{sid}", headers=auth).json()
        lat = [got[i] - sent[i] for i in sent if i in got]
        out.update({"session": k, "frames_sent": n_frames, "send_fps": n_frames / send_wall,
                    "frames_posed": len(lat), "posed_fraction": len(lat) / n_frames,
                    "latency_ms_p50": 1e3 * _pct(lat, 0.5) if lat else None,
                    "latency_ms_p95": 1e3 * _pct(lat, 0.95) if lat else None,
                    "post_ms_p50": 1e3 * _pct(acks, 0.5), "tracked_fps": status["fps"],
                    "frames_dropped": status["frames_dropped"], "engine_latency_ms": status["latency_ms"]})

    outs = [{} for _ in sessions]
    threads = [threading.Thread(target=run_session, args=(k, sid, auth, outs[k]))
               for k, (sid, auth) in enumerate(sessions)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for sid, auth in sessions:
        server.http.delete(f"/sessions/{sid}", headers=auth)
    for o in outs:
        results.append({"sessions": n_sessions, **o})
    return {"sessions": n_sessions, "rate_fps": RATE_FPS, "seconds": seconds, "per_session": results,
            "latency_ms_p50_median": statistics.median([r["latency_ms_p50"] for r in results if r["latency_ms_p50"]]
                                                       or [float("inf")]),
            "posed_fraction_mean": statistics.mean(r["posed_fraction"] for r in results)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="Duration of each 5 fps latency run.")
    ap.add_argument("--ingest-frames", type=int, default=60, help="Frames per session in the ingest runs.")
    ap.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4], help="Session counts of the 5 fps runs.")
    ap.add_argument("--device", default="auto", help="Server --device (auto, cpu, cuda).")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "server.json")
    args = ap.parse_args(argv)

    n_frames = max(args.ingest_frames, int(args.seconds * RATE_FPS))
    print(f"rendering {n_frames} synthetic frames (256x192 depth + 640x480 colour) ...", flush=True)
    messages = make_messages(n_frames, seed=0)
    mean_bytes = statistics.mean(len(m) for m in messages)
    with tempfile.TemporaryDirectory(prefix="voxfusion-bench-server-") as tmp:
        server = ServeProcess(Path(tmp) / "data", "--max-sessions", "16", "--max-pending-frames", "64",
                              device=args.device)
        try:
            ingest = []
            for n_sess, senders in ((1, 1), (1, 4), (2, 1)):
                print(f"ingest: {n_sess} session(s) x {senders} sender(s) ...", flush=True)
                ingest.append(ingest_run(server, messages[: args.ingest_frames], n_sess, senders))
            latency = []
            for n_sess in args.sessions:
                print(f"latency: {n_sess} session(s) at {RATE_FPS:g} fps for {args.seconds:g} s ...", flush=True)
                latency.append(latency_run(server, messages, n_sess, args.seconds))
            health = server.health
        finally:
            server.stop()

    print(f"\nframe message: {mean_bytes / 1024:.1f} KiB mean; server device {health['device']}\n")
    print("HTTP ingest (202 = decoded, checked, fsync'd; engine running)")
    print(format_table([{"sessions": r["sessions"], "senders/session": r["senders_per_session"],
                         "frames/s per session": r["accepted_fps_per_session"],
                         "frames/s total": r["accepted_fps_total"], "POST p50 ms": r["post_ms_p50"],
                         "POST p95 ms": r["post_ms_p95"], "429s": r["refused_429"]} for r in ingest], float_fmt=".1f"))
    print(f"\nPose latency at {RATE_FPS:g} fps per session (POST -> pose on the WebSocket, realtime mode)")
    rows = [{"sessions": r["sessions"], "session": s["session"], "posed %": 100 * s["posed_fraction"],
             "tracked fps": s["tracked_fps"], "latency p50 ms": s["latency_ms_p50"],
             "latency p95 ms": s["latency_ms_p95"], "POST p50 ms": s["post_ms_p50"]}
            for r in latency for s in r["per_session"]]
    print(format_table(rows, float_fmt=".1f"))
    base = latency[0]
    held = [r["sessions"] for r in latency
            if r["posed_fraction_mean"] >= 0.9 * base["posed_fraction_mean"]
            and r["latency_ms_p50_median"] <= 1.5 * base["latency_ms_p50_median"]]
    capacity = max(held) if held else 0
    print(f"\nsessions held at {RATE_FPS:g} fps each without latency growth (p50 <= 1.5x and posed fraction >= 0.9x "
          f"the single-session run): {capacity}")

    result = {
        "benchmark": "server", "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
        "machine": machine_info(), "server_device": health["device"],
        "preset": "server default (cpu-small on CPU, default on CUDA)",
        "frame": {"depth": "256x192 zstd_u16_mm", "confidence": "zstd_u8", "color": "640x480 jpeg q90",
                  "intrinsics_for": "640x480", "mean_bytes": mean_bytes},
        "ingest": ingest, "latency": latency, "sessions_held_at_5fps": capacity,
    }
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
