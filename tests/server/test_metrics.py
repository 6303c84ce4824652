"""``/metrics`` on a real server, parsed with ``prometheus_client``'s own parser: latency histograms by route
template for every kind of route (API, docs, WebSocket, the viewer, a static mount, 404s), the process /
platform / GC collectors, the session series, and the API key in front of it."""

from __future__ import annotations

import sys

import pytest
from fastapi.staticfiles import StaticFiles
from prometheus_client.parser import text_string_to_metric_families
from srvutil import FAST, make_scene, wait_until
from websockets.sync.client import connect

API_KEY = "metrics-api-key-0123"


def scrape(http, **kwargs) -> dict:
    """``/metrics`` parsed: ``{family name: Metric}`` (counter families are named without ``_total``)."""
    r = http.get("/metrics", **kwargs)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    return {f.name: f for f in text_string_to_metric_families(r.text)}


def samples(families: dict, family: str, sample: str | None = None) -> dict:
    """``{frozenset(labels.items()): value}`` of one sample name of a family."""
    name = sample or family
    return {frozenset(s.labels.items()): s.value for s in families[family].samples if s.name == name}


def value(families: dict, family: str, sample: str | None = None, **labels) -> float:
    return samples(families, family, sample)[frozenset(labels.items())]


@pytest.fixture(scope="module")
def scene():
    return make_scene(2, seed=5)


def test_metrics_parse_and_label_every_route_by_its_template(server_factory, scene, tmp_path):
    srv = server_factory()
    api, http = srv.api, srv.api.http
    static = tmp_path / "static"
    (static / "assets").mkdir(parents=True)
    (static / "assets" / "app-0123abcd.js").write_text("console.log(1)\n")
    srv.app.mount("/static-test", StaticFiles(directory=static))  # a mount added after the app started
    sid, token = api.create("metrics", config=FAST)
    for message in scene.messages:
        assert api.post_frame(sid, token, message).status_code == 202
    assert api.post_frame(sid, token, scene.messages[0]).json()["duplicate"] is True
    with connect(f"ws://127.0.0.1:{srv.port}/sessions/{sid}/poses/stream?token={token}", ping_interval=None):
        wait_until(lambda: srv.manager.pose_listener_count(sid), 30, "the WebSocket listener to register")
        first = scrape(http)
        assert value(first, "voxfusion_websocket_connections_open", route="/sessions/{session_id}/poses/stream") == 1
    assert http.get("/docs").status_code == 200
    assert http.get("/openapi.json").status_code == 200
    assert http.get("/healthz").status_code == 200
    assert http.delete("/healthz").status_code == 405  # path matched, method not: still its template
    assert http.get(f"/sessions/{sid}", headers=api.auth(token)).status_code == 200
    assert http.get(f"/sessions/{sid}/view", params={"token": token}).status_code in (200, 503)
    assert http.get("/viewer/assets/nope-0000.js").status_code == 404
    assert http.get("/static-test/assets/app-0123abcd.js").text == "console.log(1)\n"
    assert http.get(f"/no/such/{sid}").status_code == 404
    wait_until(lambda: value(scrape(http), "voxfusion_websocket_connections_open",
                             route="/sessions/{session_id}/poses/stream") == 0, 30, "the WebSocket to close")
    m = scrape(http)

    latency = m["voxfusion_http_request_duration_seconds"]
    assert latency.type == "histogram"
    routes = {dict(labels)["route"] for labels in samples(m, latency.name, latency.name + "_count")}
    assert {"/docs", "/openapi.json", "/healthz", "/metrics", "/sessions", "/sessions/{session_id}",
            "/sessions/{session_id}/frames", "/sessions/{session_id}/view", "/viewer/assets/{name}",
            "/static-test/{path}", "(unmatched)"} <= routes, routes
    all_labels = [v for f in m.values() if f.name.startswith("voxfusion_http_") or "websocket" in f.name
                  for s in f.samples for k, v in s.labels.items() if k == "route"]
    assert all_labels and not any(sid in v or "0123abcd" in v for v in all_labels), "a raw path became a label"
    frames = {"method": "POST", "route": "/sessions/{session_id}/frames"}
    count = value(m, latency.name, latency.name + "_count", **frames)
    assert count == 3
    assert value(m, latency.name, latency.name + "_bucket", **frames, le="+Inf") == count
    assert 0 < value(m, latency.name, latency.name + "_sum", **frames) < 60
    assert value(m, "voxfusion_http_requests", "voxfusion_http_requests_total", **frames, status="202") == 3
    assert value(m, "voxfusion_http_requests", "voxfusion_http_requests_total", method="DELETE", route="/healthz",
                 status="405") == 1
    assert value(m, "voxfusion_http_requests", "voxfusion_http_requests_total", method="GET", route="(unmatched)",
                 status="404") == 1
    assert value(m, "voxfusion_websocket_connections", "voxfusion_websocket_connections_total",
                 route="/sessions/{session_id}/poses/stream") == 1
    # the default collectors
    assert m["python_info"].samples and "python_gc_objects_collected" in m
    if sys.platform.startswith("linux"):
        assert value(m, "process_resident_memory_bytes") > 0 and "process_cpu_seconds" in m
    # the session series, as before the port
    assert value(m, "voxfusion_frames_accepted", "voxfusion_frames_accepted_total") == 2
    assert value(m, "voxfusion_frames_duplicate", "voxfusion_frames_duplicate_total") == 1
    assert value(m, "voxfusion_sessions", state="running") == 1 and value(m, "voxfusion_sessions_open") == 1
    assert value(m, "voxfusion_session_frames_received", "voxfusion_session_frames_received_total", session=sid) == 2
    assert "voxfusion_session_voxels" in m and "voxfusion_frame_bytes" in m
    # frames tracked again after a gap (none in two frames without one)
    assert value(m, "voxfusion_session_frames_retried", "voxfusion_session_frames_retried_total", session=sid) == 0
    assert value(m, "voxfusion_session_frames_relocalised", "voxfusion_session_frames_relocalised_total",
                 session=sid) == 0
    assert value(m, "voxfusion_session_frames_limited", "voxfusion_session_frames_limited_total", session=sid) == 0


def test_metrics_keep_the_api_key(server_factory):
    srv = server_factory(api_key=API_KEY)
    http = srv.api.http
    assert http.get("/metrics").status_code == 401
    assert http.get("/metrics", headers={"X-API-Key": "wrong-key-000"}).status_code == 403
    m = scrape(http, headers={"X-API-Key": API_KEY})
    m = scrape(http, headers={"Authorization": f"Bearer {API_KEY}"})
    requests = samples(m, "voxfusion_http_requests", "voxfusion_http_requests_total")
    by_status = {dict(k)["status"]: v for k, v in requests.items() if dict(k)["route"] == "/metrics"}
    assert by_status == {"401": 1, "403": 1, "200": 1}
