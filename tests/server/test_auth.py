"""Access control: the optional server API key, per-session bearer tokens (stored hashed), WebSocket
auth, and session ids that never become paths."""

from __future__ import annotations

import hashlib
import sqlite3

import pytest
from srvutil import FAST
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from voxfusion.server.auth import SESSION_ID_RE, bearer_token, check_session_id, hash_token, verify_token
from voxfusion.server.errors import ForbiddenError, SessionNotFoundError, UnauthorizedError

API_KEY = "test-api-key-0123"


def test_api_key_guards_creating_and_listing(server_factory):
    srv = server_factory(api_key=API_KEY)
    http = srv.api.http
    r = http.post("/sessions", json={"config": FAST})
    assert r.status_code == 401 and r.json()["field"] == "X-API-Key" and r.headers["WWW-Authenticate"] == "Bearer"
    assert http.post("/sessions", json={"config": FAST}, headers={"X-API-Key": "wrong-key-000"}).status_code == 403
    r = http.post("/sessions", json={"config": FAST}, headers={"X-API-Key": API_KEY})
    assert r.status_code == 201
    sid, token = r.json()["id"], r.json()["token"]
    assert http.post("/sessions", json={"config": FAST},
                     headers={"Authorization": f"Bearer {API_KEY}"}).status_code == 201
    assert http.get("/sessions").status_code == 401
    assert len(http.get("/sessions", headers={"X-API-Key": API_KEY}).json()["sessions"]) == 2
    assert http.get("/metrics").status_code == 401
    assert http.get("/healthz").status_code == 200  # liveness stays open
    # session routes take the session token, not the API key
    assert http.get(f"/sessions/{sid}", headers={"Authorization": f"Bearer {API_KEY}"}).status_code == 403
    assert http.get(f"/sessions/{sid}", headers={"Authorization": f"Bearer {token}"}).status_code == 200


def test_tokens_are_stored_hashed_and_checked_on_every_session_route(server_factory):
    srv = server_factory()
    api = srv.api
    sid, token = api.create("t", config=FAST)
    assert SESSION_ID_RE.fullmatch(sid) and len(token) >= 40
    db = sqlite3.connect(srv.settings.database_path)
    rows = db.execute("SELECT id, token_sha256 FROM sessions").fetchall()
    dump = "\n".join(db.iterdump())
    db.close()
    assert rows == [(sid, hashlib.sha256(token.encode()).hexdigest())]
    assert token not in dump
    routes = [("GET", f"/sessions/{sid}"), ("GET", f"/sessions/{sid}/poses"), ("GET", f"/sessions/{sid}/poses/latest"),
              ("GET", f"/sessions/{sid}/mesh"), ("GET", f"/sessions/{sid}/voxels"), ("POST", f"/sessions/{sid}/frames"),
              ("POST", f"/sessions/{sid}/render"), ("POST", f"/sessions/{sid}/finish"),
              ("POST", f"/sessions/{sid}/resume"), ("DELETE", f"/sessions/{sid}")]
    for method, path in routes:
        assert api.http.request(method, path).status_code == 401, path
        assert api.http.request(method, path, headers={"Authorization": "Bearer nope"}).status_code == 403, path
        assert api.http.request(method, path, headers={"Authorization": "Basic abc"}).status_code == 401, path
    assert api.http.get(f"/sessions/{sid}", headers=api.auth(token)).status_code == 200


def test_websocket_needs_the_token(server_factory):
    srv = server_factory()
    sid, token = srv.api.create("ws", config=FAST)
    base = f"ws://127.0.0.1:{srv.port}/sessions"
    for url, code in ((f"{base}/{sid}/poses/stream", 4401), (f"{base}/{sid}/poses/stream?token=bad", 4403),
                      (f"{base}/{'f' * 32}/poses/stream?token={token}", 4404)):
        with connect(url, ping_interval=None) as ws, pytest.raises(ConnectionClosed) as info:
            ws.recv(timeout=30)
        assert info.value.rcvd.code == code, url
    # the header works as well as the query; a finished session's stream ends at once
    assert srv.api.http.post(f"/sessions/{sid}/finish", headers=srv.api.auth(token)).status_code == 200
    with connect(f"{base}/{sid}/poses/stream", additional_headers=srv.api.auth(token), ping_interval=None) as ws:
        assert '"event": "end"' in ws.recv(timeout=30)


def test_ids_and_tokens_unit():
    with pytest.raises(SessionNotFoundError):
        check_session_id("../../etc/passwd")
    with pytest.raises(SessionNotFoundError):
        check_session_id("A" * 32)  # upper case is not an id we issue
    assert check_session_id("a" * 32) == "a" * 32
    with pytest.raises(UnauthorizedError):
        verify_token(None, hash_token("x"))
    with pytest.raises(ForbiddenError):
        verify_token("y", hash_token("x"))
    verify_token("x", hash_token("x"))
    assert bearer_token("Bearer abc") == "abc" and bearer_token("bearer  abc ") == "abc"
    assert bearer_token("Basic abc") is None and bearer_token("Bearer") is None and bearer_token(None) is None
