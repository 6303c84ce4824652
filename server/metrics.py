"""``GET /metrics``: Prometheus text exposition format (version 0.0.4), written by hand (no dependency).

Series:

* ``voxfusion_sessions{state=...}`` sessions known, by state; ``voxfusion_sessions_open``;
* ``voxfusion_session_frames_{received,tracked,mapped,dropped}_total{session=...}``,
  ``voxfusion_session_{keyframes,voxels,fps,latency_ms,frames_queued}{session=...}`` for open sessions;
* ``voxfusion_frames_accepted_total``, ``voxfusion_frames_duplicate_total``,
  ``voxfusion_frames_rejected_total{status=...}``, ``voxfusion_frame_bytes_total``,
  ``voxfusion_sessions_{created,resumed,deleted}_total``, and any counter another transport (the zenoh
  bridge) adds to ``SessionManager.counters``;
* ``voxfusion_http_requests_total{method, route, status}`` and
  ``voxfusion_http_request_duration_seconds`` (summary: ``_sum`` / ``_count``) ``{method, route}``.
"""

from __future__ import annotations

import threading
from collections import Counter

from .manager import SessionManager

__all__ = ["CONTENT_TYPE", "HttpStats", "render_metrics"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(**labels: str) -> str:
    if not labels:
        return ""
    return "{" + ",".join(f'{k}="{_escape(str(v))}"' for k, v in labels.items()) + "}"


class HttpStats:
    """Request counters filled by the app's middleware (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.requests: Counter[tuple[str, str, int]] = Counter()
        self.seconds: Counter[tuple[str, str]] = Counter()
        self.count: Counter[tuple[str, str]] = Counter()

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        with self._lock:
            self.requests[(method, route, status)] += 1
            self.seconds[(method, route)] += seconds
            self.count[(method, route)] += 1

    def snapshot(self) -> tuple[dict, dict, dict]:
        with self._lock:
            return dict(self.requests), dict(self.seconds), dict(self.count)


def render_metrics(manager: SessionManager, http: HttpStats) -> str:
    """The whole ``/metrics`` page."""
    out: list[str] = []

    def family(name: str, kind: str, help_text: str, samples: list[tuple[dict[str, str], float]]) -> None:
        out.append(f"# HELP {name} {help_text}")
        out.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            out.append(f"{name}{_labels(**labels)} {float(value):.6g}")

    rows = manager.store.all()
    by_state = Counter(r.state for r in rows)
    family("voxfusion_sessions", "gauge", "Sessions known to the server, by state.",
           [({"state": s}, by_state.get(s, 0)) for s in ("created", "running", "finishing", "finished", "failed")])
    statuses = manager.open_statuses()
    family("voxfusion_sessions_open", "gauge", "Sessions holding an engine.",
           [({}, sum(1 for s in statuses if s.state.value in ("created", "running", "finishing")))])
    per_session = [
        ("voxfusion_session_frames_received_total", "counter", "Frames recorded.", "frames_received"),
        ("voxfusion_session_frames_tracked_total", "counter", "Frames tracked.", "frames_tracked"),
        ("voxfusion_session_frames_mapped_total", "counter", "Frames fused into the map.", "frames_mapped"),
        ("voxfusion_session_frames_dropped_total", "counter", "Frames skipped by realtime tracking.",
         "frames_dropped"),
        ("voxfusion_session_keyframes", "gauge", "Keyframes.", "keyframes"),
        ("voxfusion_session_voxels", "gauge", "Allocated voxels.", "voxels"),
        ("voxfusion_session_fps", "gauge", "Frames tracked per second.", "fps"),
        ("voxfusion_session_latency_ms", "gauge", "Mean frame arrival to pose latency, ms.", "latency_ms"),
        ("voxfusion_session_frames_queued", "gauge", "Frames accepted, not yet handed to tracking.",
         "frames_queued"),
    ]
    for name, kind, help_text, attr in per_session:
        family(name, kind, help_text, [({"session": s.id}, getattr(s, attr) or 0.0) for s in statuses])
    helps = {"frames_accepted_total": "Frames recorded and acknowledged (202).",
             "frames_duplicate_total": "Frames re-sent with a seq already recorded.",
             "frame_bytes_total": "Bytes of accepted frame messages.",
             "frames_rejected_total": "Frames refused, by HTTP status.",
             "sessions_created_total": "Sessions created.",
             "sessions_resumed_total": "Sessions resumed (recording replayed).",
             "sessions_deleted_total": "Sessions deleted."}
    counters: dict[str, list[tuple[str, int]]] = {name: [] for name in helps}
    for (name, label), n in sorted(manager.counters.items()):  # other transports (zenoh) add their own
        counters.setdefault(name, []).append((label, n))
    for name, samples in counters.items():
        label_key = "status" if "rejected" in name else "kind"
        if not samples and "rejected" not in name:
            samples = [("", 0)]
        family(f"voxfusion_{name}", "counter", helps.get(name, name.replace("_", " ") + "."),
               [({label_key: label} if label else {}, n) for label, n in samples])
    requests, seconds, count = http.snapshot()
    family("voxfusion_http_requests_total", "counter", "HTTP requests, by method, route and status.",
           [({"method": m, "route": r, "status": str(st)}, n) for (m, r, st), n in sorted(requests.items())])
    name = "voxfusion_http_request_duration_seconds"
    out.append(f"# HELP {name} Time answering requests, by method and route.")
    out.append(f"# TYPE {name} summary")
    for (m, r), v in sorted(seconds.items()):
        out.append(f"{name}_sum{_labels(method=m, route=r)} {v:.6g}")
        out.append(f"{name}_count{_labels(method=m, route=r)} {count[(m, r)]}")
    return "\n".join(out) + "\n"
