"""Hosting benchmark: fairness between sessions, scaling with the session count, and a killed worker.

Usage (from the repository root)::

    python bench/bench_hosting.py                         # ~25 minutes on a 2-core CPU
    python bench/bench_hosting.py --seconds 30 --scaling-seconds 20 --kill-trials 1   # a quick look

A real ``voxfusion serve`` runs in a subprocess on 127.0.0.1 (the server's default preset); this process
streams iPhone-shaped frames (:func:`bench.bench_server.make_messages`) to realtime sessions at 5 fps each,
one sender thread per session, and samples every session's status once a second.

* **fairness**: 3 identical realtime sessions for ``--seconds`` (180): frames tracked by each, and their
  spread ``(max - min) / max`` (target: <= 20 %). Run with session engines in worker processes
  (``--session-workers process``, the default) and, as the baseline in the same run, on threads of the
  server process (``thread``, how every session ran before).
* **scaling**: 1 and 2 sessions for ``--scaling-seconds`` (60) in both modes: total tracked frames/s.
* **ray**: 4 realtime sessions on a local 2-node Ray cluster (``ray.cluster_utils.Cluster``), the worker node
  removed a third of the way in: where the sessions ran, whether the moved ones restarted on the other node,
  acknowledged frames lost.
* **kill**: 3 sessions at 5 fps; after ``--kill-at-s`` (20 s) one session's worker is killed with SIGKILL.
  Reports the other sessions' tracked rate in the windows before and after the kill, whether the killed
  session resumed by itself (a new worker, ``worker_restarts == 1``, tracking again), and acknowledged
  frames lost (202 answers whose frame is not in the session's recording). ``--kill-trials`` (3) times.

Writes ``bench/results/hosting.json`` with :func:`bench.machine.machine_info`.
"""

from __future__ import annotations

import argparse
import os
import signal
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

from bench.bench_server import make_messages  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from voxfusion.core.eval import format_table, write_json  # noqa: E402
from voxfusion.proto import MEDIA_TYPE  # noqa: E402
from voxfusion.proto.recording import RecordingCapture  # noqa: E402
from voxfusion.server.child import ServeProcess  # noqa: E402

RATE_FPS = 5.0


class StreamedSession:
    """A realtime session fed at ``RATE_FPS`` by a thread of its own; its status sampled every second."""

    def __init__(self, server: ServeProcess, name: str, messages: list[bytes]) -> None:
        r = server.http.post("/sessions", json={"name": name})
        r.raise_for_status()
        self.id = r.json()["id"]
        self.auth = {"Authorization": f"Bearer {r.json()['token']}"}
        self.server = server
        self.messages = messages
        self.acked: list[int] = []  # seqs answered 202
        self.refused = 0
        self.samples: list[tuple[float, int, int]] = []  # (time, frames_tracked, worker_restarts)
        self._stop = threading.Event()
        self._sender = threading.Thread(target=self._send, daemon=True)

    def start(self, t0: float) -> None:
        self.t0 = t0
        self._sender.start()

    def _send(self) -> None:
        headers = {**self.auth, "Content-Type": MEDIA_TYPE}
        with httpx.Client(base_url=self.server.url, timeout=120) as client:
            i = 0
            while not self._stop.is_set() and i < len(self.messages):
                wait = self.t0 + i / RATE_FPS - time.perf_counter()
                if wait > 0 and self._stop.wait(wait):
                    break
                r = client.post(f"/sessions/{self.id}/frames", content=self.messages[i], headers=headers)
                if r.status_code == 202:
                    self.acked.append(r.json()["seq"])
                else:
                    self.refused += 1
                i += 1

    def status(self) -> dict:
        return self.server.http.get(f"/sessions/{self.id}", headers=self.auth).json()

    def sample(self) -> dict:
        st = self.status()
        self.samples.append((time.perf_counter(), st["frames_tracked"], st["worker_restarts"]))
        return st

    def stop(self) -> None:
        self._stop.set()
        self._sender.join()

    def tracked_rate(self, t_from: float, t_to: float) -> float:
        """Frames tracked per second between two times (from the 1 s samples)."""
        inside = [(t, n) for t, n, _ in self.samples if t_from <= t <= t_to]
        if len(inside) < 2:
            return float("nan")
        (ta, na), (tb, nb) = inside[0], inside[-1]
        return (nb - na) / (tb - ta)

    def lost_acknowledged(self) -> int:
        """202-answered frames missing from the session's recording."""
        recorded = set(RecordingCapture(self.server_data / "sessions" / self.id).seqs())
        return len(set(self.acked) - recorded)

    def delete(self) -> None:
        self.server.http.delete(f"/sessions/{self.id}", headers=self.auth)


def run_sessions(server: ServeProcess, messages: list[bytes], n: int, seconds: float,
                 during=None) -> list[StreamedSession]:
    """Stream to ``n`` sessions for ``seconds``; ``during(t_elapsed, sessions)`` is called every second."""
    sessions = [StreamedSession(server, f"s{k}", messages) for k in range(n)]
    for s in sessions:
        s.server_data = server.data_dir
    t0 = time.perf_counter() + 0.5
    for k, s in enumerate(sessions):
        s.start(t0 + 0.05 * k)
    while (elapsed := time.perf_counter() - t0) < seconds:
        for s in sessions:
            s.sample()
        if during is not None:
            during(elapsed, sessions)
        time.sleep(max(0.0, 1.0 - (time.perf_counter() - t0 - elapsed)))
    for s in sessions:
        s.stop()
    time.sleep(2.0)  # the last frames are tracked
    for s in sessions:
        s.sample()
    return sessions


class Server(ServeProcess):
    def __init__(self, root: Path, workers: str) -> None:
        self.data_dir = root / f"data-{workers}-{time.monotonic_ns()}"
        super().__init__(self.data_dir, "--session-workers", workers, "--session-idle-timeout-s", "0",
                         "--max-sessions-per-client", "0")


def fairness(root: Path, messages: list[bytes], workers: str, seconds: float) -> dict:
    with Server(root, workers) as server:
        sessions = run_sessions(server, messages, 3, seconds)
        tracked = [s.samples[-1][1] for s in sessions]
        for s in sessions:
            s.delete()
    spread = (max(tracked) - min(tracked)) / max(max(tracked), 1)
    return {"workers": workers, "sessions": 3, "seconds": seconds, "frames_sent": [len(s.acked) for s in sessions],
            "frames_tracked": tracked, "spread": spread, "total_tracked_fps": sum(tracked) / seconds}


def scaling(root: Path, messages: list[bytes], workers: str, seconds: float) -> list[dict]:
    out = []
    with Server(root, workers) as server:
        for n in (1, 2):
            sessions = run_sessions(server, messages, n, seconds)
            tracked = [s.samples[-1][1] for s in sessions]
            for s in sessions:
                s.delete()
            out.append({"workers": workers, "sessions": n, "seconds": seconds, "frames_tracked": tracked,
                        "total_tracked_fps": sum(tracked) / seconds})
    return out


def kill_trial(root: Path, messages: list[bytes], seconds: float, kill_at_s: float) -> dict:
    killed: dict = {}

    def during(elapsed: float, sessions: list[StreamedSession]) -> None:
        if not killed and elapsed >= kill_at_s:
            victim = sessions[0]
            pid = victim.status()["worker_pid"]
            os.kill(pid, signal.SIGKILL)
            killed.update(pid=pid, t=time.perf_counter())

    with Server(root, "process") as server:
        sessions = run_sessions(server, messages, 3, seconds, during)
        victim, others = sessions[0], sessions[1:]
        t_kill = killed["t"]
        window = min(kill_at_s, seconds - kill_at_s) - 2.0
        before = [s.tracked_rate(t_kill - window, t_kill) for s in others]
        after = [s.tracked_rate(t_kill + 1.0, t_kill + 1.0 + window) for s in others]
        st = victim.status()
        resumed_at = next((t - t_kill for t, n, restarts in victim.samples if t > t_kill and restarts and n > 0),
                          None)
        lost = sum(s.lost_acknowledged() for s in sessions)
        result = {"seconds": seconds, "kill_at_s": kill_at_s, "killed_pid": killed["pid"],
                  "victim_new_pid": st["worker_pid"], "victim_worker_restarts": st["worker_restarts"],
                  "victim_state": st["state"], "victim_frames_tracked": st["frames_tracked"],
                  "victim_resumed": st["worker_restarts"] == 1 and st["worker_pid"] != killed["pid"]
                  and st["state"] == "running" and st["frames_tracked"] > 0,
                  "victim_tracking_again_after_s": resumed_at,
                  "others_tracked_fps_before": before, "others_tracked_fps_after": after,
                  "acknowledged_frames_lost": lost,
                  "acknowledged_frames": sum(len(s.acked) for s in sessions)}
        for s in sessions:
            s.delete()
    return result


def ray_trial(root: Path, messages: list[bytes], seconds: float, kill_at_s: float) -> dict:
    """4 realtime sessions on a local 2-node Ray cluster; the worker node is removed at ``kill_at_s``."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2})
    worker = cluster.add_node(num_cpus=2)
    cluster.wait_for_nodes()
    removed: dict = {}
    placed: dict = {}

    def during(elapsed: float, sessions: list[StreamedSession]) -> None:
        if not placed:
            placed.update({s.id: s.status()["worker_node"] for s in sessions})
        if not removed and elapsed >= kill_at_s:
            cluster.remove_node(worker)
            removed["t"] = time.perf_counter()

    try:
        data_dir = root / f"data-ray-{time.monotonic_ns()}"
        with ServeProcess(data_dir, "--ray-address", cluster.address, "--cpus-per-session", "0.5",
                          "--session-idle-timeout-s", "0", "--max-sessions-per-client", "0") as server:
            server.data_dir = data_dir
            sessions = run_sessions(server, messages, 4, seconds, during)
            statuses = {s.id: s.status() for s in sessions}
            moved = [sid for sid, node in placed.items() if node == worker.node_id]
            result = {"seconds": seconds, "remove_node_at_s": kill_at_s, "nodes": 2, "sessions": 4,
                      "sessions_per_node_before": {n: list(placed.values()).count(n) for n in set(placed.values())},
                      "sessions_moved": len(moved),
                      "moved_sessions_restarted": all(statuses[sid]["worker_restarts"] == 1 for sid in moved),
                      "moved_sessions_now_on": sorted({statuses[sid]["worker_node"] for sid in moved}),
                      "states": sorted({st["state"] for st in statuses.values()}),
                      "frames_tracked": [statuses[s.id]["frames_tracked"] for s in sessions],
                      "acknowledged_frames": sum(len(s.acked) for s in sessions),
                      "acknowledged_frames_lost": sum(s.lost_acknowledged() for s in sessions)}
            for s in sessions:
                s.delete()
    finally:
        cluster.shutdown()
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=180.0, help="fairness run length")
    ap.add_argument("--scaling-seconds", type=float, default=60.0)
    ap.add_argument("--kill-trials", type=int, default=3)
    ap.add_argument("--kill-seconds", type=float, default=60.0)
    ap.add_argument("--kill-at-s", type=float, default=25.0)
    ap.add_argument("--modes", nargs="+", default=["process", "thread"], choices=["process", "thread"])
    ap.add_argument("--ray-seconds", type=float, default=40.0, help="Ray run length (0: skip it)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "hosting.json")
    args = ap.parse_args(argv)
    n_frames = int(max(args.seconds, args.scaling_seconds, args.kill_seconds) * RATE_FPS) + 10
    print(f"[hosting] rendering {n_frames} iPhone-shaped frames ...", flush=True)
    messages = make_messages(n_frames, seed=0)
    result: dict = {"machine": machine_info(), "date": datetime.now(UTC).isoformat(timespec="seconds"),
                    "rate_fps": RATE_FPS, "fairness": [], "scaling": [], "kill": [], "ray": None}
    with tempfile.TemporaryDirectory(prefix="vf-hosting-") as tmp:
        root = Path(tmp)
        for mode in args.modes:
            print(f"[hosting] fairness, 3 sessions, {mode} workers, {args.seconds:g} s", flush=True)
            result["fairness"].append(fairness(root, messages, mode, args.seconds))
            print(f"[hosting]   {result['fairness'][-1]}", flush=True)
            print(f"[hosting] scaling, 1 and 2 sessions, {mode} workers", flush=True)
            result["scaling"] += scaling(root, messages, mode, args.scaling_seconds)
            print(f"[hosting]   {result['scaling'][-2:]}", flush=True)
        for k in range(args.kill_trials):
            print(f"[hosting] kill trial {k + 1}/{args.kill_trials}", flush=True)
            result["kill"].append(kill_trial(root, messages, args.kill_seconds, args.kill_at_s))
            print(f"[hosting]   {result['kill'][-1]}", flush=True)
        if args.ray_seconds > 0:
            print(f"[hosting] Ray: 4 sessions on a local 2-node cluster, one node removed, {args.ray_seconds:g} s",
                  flush=True)
            result["ray"] = ray_trial(root, messages, args.ray_seconds, args.ray_seconds / 3)
            print(f"[hosting]   {result['ray']}", flush=True)
    write_json(args.out, result)
    rows = [{"workers": f["workers"], "sessions": 3, "frames tracked": " / ".join(map(str, f["frames_tracked"])),
             "spread": f"{100 * f['spread']:.0f} %", "total tracked fps": f["total_tracked_fps"]}
            for f in result["fairness"]]
    rows += [{"workers": s["workers"], "sessions": s["sessions"],
              "frames tracked": " / ".join(map(str, s["frames_tracked"])), "total tracked fps": s["total_tracked_fps"]}
             for s in result["scaling"]]
    print(format_table(rows, float_fmt=".2f"))
    for k in result["kill"]:
        before = ", ".join(f"{x:.2f}" for x in k["others_tracked_fps_before"])
        after = ", ".join(f"{x:.2f}" for x in k["others_tracked_fps_after"])
        print(f"kill: resumed={k['victim_resumed']} lost={k['acknowledged_frames_lost']} others' tracked fps "
              f"before [{before}] after [{after}]")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
