"""``GET /metrics``: Prometheus text exposition format (version 0.0.4), through ``prometheus_client``.

Series:

* ``voxfusion_sessions{state=...}`` sessions known, by state; ``voxfusion_sessions_open``;
* ``voxfusion_session_frames_{received,tracked,mapped,dropped}_total{session=...}``,
  ``voxfusion_session_{keyframes,voxels,fps,latency_ms,frames_queued}{session=...}`` for open sessions;
* ``voxfusion_frames_accepted_total``, ``voxfusion_frames_duplicate_total``,
  ``voxfusion_frames_rejected_total{status=...}``, ``voxfusion_frame_bytes_total``,
  ``voxfusion_sessions_{created,resumed,deleted}_total``, and any counter another transport (the zenoh
  bridge) adds to ``SessionManager.counters``;
* ``voxfusion_http_requests_total{method, route, status}`` and the latency histogram
  ``voxfusion_http_request_duration_seconds{method, route}`` (``_bucket`` / ``_sum`` / ``_count``, seconds);
* ``voxfusion_websocket_connections_total{route}`` and ``voxfusion_websocket_connections_open{route}``;
* the client library's default collectors: ``process_*`` (CPU, memory, open files), ``python_info`` and
  ``python_gc_*``.

``route`` is the template of the route that served the request (``/sessions/{session_id}/frames``,
``/docs``, ``/viewer/{path}`` for a static mount), never the raw path, so the series stay bounded
(:func:`route_template`); requests no route matches are ``(unmatched)``.

Each app has its own registry (:class:`HttpStats`), so several servers in one process (the tests) never
share series; the session series are read from the manager at scrape time.
"""

from __future__ import annotations

import functools
import re
from collections import Counter as _Tally
from collections.abc import Iterable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector
from starlette.routing import Mount, WebSocketRoute, compile_path
from starlette.types import Scope

from .manager import SessionManager

try:  # FastAPI >= 0.16x includes routers lazily; older versions copy their routes into the app's router
    from fastapi.routing import iter_route_contexts as _iter_route_contexts
except ImportError:  # pragma: no cover - depends on the installed FastAPI
    _iter_route_contexts = None

__all__ = ["CONTENT_TYPE", "UNMATCHED", "HttpStats", "render_metrics", "route_template"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
UNMATCHED = "(unmatched)"
"""``route`` label of requests no route matches (404s of arbitrary paths: never the path itself)."""

LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0)
"""Histogram buckets of request latency, seconds: frames and poses answer in milliseconds, a mesh or a
final ``/finish`` can take minutes on a CPU."""


class HttpStats:
    """The app's Prometheus registry: HTTP request and WebSocket metrics filled by the app's middleware
    (thread-safe), and the process / platform / GC collectors. :func:`render_metrics` adds the sessions."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        GCCollector(registry=self.registry)
        self.requests = Counter("voxfusion_http_requests", "HTTP requests, by method, route and status.",
                                ("method", "route", "status"), registry=self.registry)
        self.latency = Histogram("voxfusion_http_request_duration_seconds",
                                 "Time answering HTTP requests, seconds, by method and route.", ("method", "route"),
                                 buckets=LATENCY_BUCKETS_S, registry=self.registry)
        self.websockets = Counter("voxfusion_websocket_connections", "WebSocket connections opened, by route.",
                                  ("route",), registry=self.registry)
        self.websockets_open = Gauge("voxfusion_websocket_connections_open", "WebSocket connections open, by route.",
                                     ("route",), registry=self.registry)

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        """One HTTP request answered."""
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(method, route).observe(seconds)


# ---------------------------------------------------------------------------------------------- routes
def _route_path(scope: Scope) -> str:
    path: str = scope.get("path", "")
    root = scope.get("root_path", "")
    if root and path.startswith(root) and path != root:
        path = path[len(root):]
    return path


def _flat_routes(routes: Iterable[Any]) -> Iterator[tuple[Any, str | None]]:
    """``(route, path)`` for every route, included routers flattened (``path`` with their prefix)."""
    if _iter_route_contexts is None:
        for route in routes:
            yield route, getattr(route, "path", None)
        return
    for ctx in _iter_route_contexts(list(routes)):
        yield ctx.original_route, ctx.path


@functools.lru_cache(maxsize=1024)
def _regex(template: str) -> re.Pattern[str]:
    return compile_path(template)[0]


def _match(routes: Iterable[Any], kind: str, method: str, path: str, prefix: str) -> tuple[str | None, bool]:
    """``(template, full)`` of the first route that matches ``path``; ``full`` False when only the path
    matched, not the method (a 405), as Starlette's router decides."""
    partial: str | None = None
    for route, route_path in _flat_routes(routes):
        if route_path is None:
            continue
        if isinstance(route, Mount):
            mount = prefix + route_path.rstrip("/")
            if not (path == mount or path.startswith(mount + "/")):
                continue
            inner, full = _match(route.routes, kind, method, path, mount) if route.routes else (None, False)
            template = inner or mount + "/{path}"
            if full or inner is None:
                return template, True
            partial = partial or template
            continue
        template = prefix + route_path
        if not _regex(template).fullmatch(path):
            continue
        route_kind = "websocket" if isinstance(route, WebSocketRoute) else "http"
        if route_kind != kind:
            continue
        methods = getattr(route, "methods", None)
        if kind == "websocket" or not methods or method in methods or (method == "HEAD" and "GET" in methods):
            return template, True
        partial = partial or template
    return partial, False


def route_template(routes: Iterable[Any], scope: Scope) -> str:
    """The path template of the route that serves ``scope`` (an HTTP or WebSocket scope), e.g.
    ``/sessions/{session_id}/poses/stream``; ``/viewer/{path}`` for a file of a static mount at
    ``/viewer``; :data:`UNMATCHED` when no route matches.

    ``routes`` is the app's ``router.routes`` (read on every call, so routes added later count too). The
    templates are matched here rather than read back from the scope because not every route records
    itself there (FastAPI's ``/docs`` and ``/openapi.json``, mounts).
    """
    template, _ = _match(routes, scope["type"], scope.get("method", ""), _route_path(scope), "")
    return template or UNMATCHED


# ---------------------------------------------------------------------------------------------- sessions
_PER_SESSION = (
    ("voxfusion_session_frames_received_total", "counter", "Frames recorded.", "frames_received"),
    ("voxfusion_session_frames_tracked_total", "counter", "Frames tracked.", "frames_tracked"),
    ("voxfusion_session_frames_mapped_total", "counter", "Frames fused into the map.", "frames_mapped"),
    ("voxfusion_session_frames_dropped_total", "counter", "Frames skipped by realtime tracking.", "frames_dropped"),
    ("voxfusion_session_frames_retried_total", "counter",
     "Frames tracked again from other starts (after a gap, or a turn before any motion was known).", "frames_retried"),
    ("voxfusion_session_frames_limited_total", "counter",
     "Frames tracked with a cost jump (tracking state limited: the pose may be wrong).", "frames_limited"),
    ("voxfusion_session_frames_relocalised_total", "counter", "Frames placed from a keyframe's pose after a gap.",
     "frames_relocalised"),
    ("voxfusion_session_keyframes", "gauge", "Keyframes.", "keyframes"),
    ("voxfusion_session_voxels", "gauge", "Allocated voxels.", "voxels"),
    ("voxfusion_session_fps", "gauge", "Frames tracked per second.", "fps"),
    ("voxfusion_session_latency_ms", "gauge", "Mean frame arrival to pose latency, ms.", "latency_ms"),
    ("voxfusion_session_frames_queued", "gauge", "Frames accepted, not yet handed to tracking.", "frames_queued"),
    ("voxfusion_session_worker_restarts_total", "counter", "Restarts of the session's dead worker process.",
     "worker_restarts"),
)
_COUNTER_HELP = {"frames_accepted_total": "Frames recorded and acknowledged (202).",
                 "frames_duplicate_total": "Frames re-sent with a seq already recorded.",
                 "frame_bytes_total": "Bytes of accepted frame messages.",
                 "frames_rejected_total": "Frames refused, by HTTP status.",
                 "sessions_created_total": "Sessions created.",
                 "sessions_resumed_total": "Sessions resumed (recording replayed).",
                 "sessions_deleted_total": "Sessions deleted."}


class _Sessions(Collector):
    """The manager's sessions and counters, read when scraped."""

    def __init__(self, manager: SessionManager) -> None:
        self.manager = manager

    def collect(self) -> Iterator[Metric]:
        manager = self.manager
        by_state = _Tally(r.state for r in manager.store.all())
        fam = GaugeMetricFamily("voxfusion_sessions", "Sessions known to the server, by state.", labels=["state"])
        for state in ("created", "running", "finishing", "finished", "failed"):
            fam.add_metric([state], by_state.get(state, 0))
        yield fam
        statuses = manager.open_statuses()
        yield GaugeMetricFamily("voxfusion_sessions_open", "Sessions holding an engine.",
                                value=sum(1 for s in statuses if s.state.value in ("created", "running", "finishing")))
        for name, kind, help_text, attr in _PER_SESSION:
            family = CounterMetricFamily if kind == "counter" else GaugeMetricFamily
            fam = family(name, help_text, labels=["session"])
            for s in statuses:
                fam.add_metric([s.id], float(getattr(s, attr) or 0.0))
            yield fam
        counters: dict[str, list[tuple[str, int]]] = {name: [] for name in _COUNTER_HELP}
        for (name, label), n in sorted(manager.counters.items()):  # other transports (zenoh) add their own
            counters.setdefault(name, []).append((label, n))
        for name, samples in counters.items():
            label_key = "status" if "rejected" in name else "kind"
            if not samples and "rejected" not in name:
                samples = [("", 0)]
            full = f"voxfusion_{name}"
            fam = CounterMetricFamily(full, _COUNTER_HELP.get(name, name.replace("_", " ") + "."))
            for label, n in samples:  # unlabelled when the counter has no label (not label="")
                fam.add_sample(fam.name + "_total", {label_key: label} if label else {}, float(n))
            yield fam


class _Scrape(Collector):
    def __init__(self, *collectors: Collector) -> None:
        self.collectors = collectors

    def collect(self) -> Iterator[Metric]:
        for c in self.collectors:
            yield from c.collect()


def render_metrics(manager: SessionManager, http: HttpStats) -> str:
    """The whole ``/metrics`` page."""
    return generate_latest(_Scrape(_Sessions(manager), http.registry)).decode("utf-8")
