"""Anonymous clients cannot fill every slot: without an API key, one client address beyond loopback holds at
most ``max_sessions_per_client`` open sessions (429 with what to do); loopback clients and API key holders are
not limited. Remote clients are simulated the way a reverse proxy presents them: ``X-Forwarded-For`` from
127.0.0.1, which uvicorn trusts by default (``FORWARDED_ALLOW_IPS``)."""

from __future__ import annotations

import time

from srvutil import FAST

from voxfusion.server.api.deps import client_key

API_KEY = "test-api-key-0123"


def create(http, ip: str | None = None, **headers):
    if ip is not None:
        headers["X-Forwarded-For"] = ip
    return http.post("/sessions", json={"config": FAST}, headers=headers)


def created(r) -> tuple[str, dict]:
    assert r.status_code == 201, r.text
    return r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}


def check_429(r, *words: str) -> None:
    assert r.status_code == 429, r.text
    body = r.json()
    assert set(body) == {"detail", "field"}, body
    for w in words:
        assert w in body["detail"], body


def test_anonymous_clients_beyond_loopback_are_limited(server_factory):
    srv = server_factory(max_sessions=8, session_idle_timeout_s=600)
    http = srv.api.http
    a = [created(create(http, "203.0.113.7")) for _ in range(2)]
    check_429(create(http, "203.0.113.7"), "203.0.113.7", "maximum of 2", "finish", "delete", "API key")
    # other addresses have their own allowance; an IPv6 client is counted by its /64
    created(create(http, "203.0.113.8"))
    created(create(http, "2001:db8::1"))
    created(create(http, "2001:db8::2"))
    check_429(create(http, "2001:db8::3"), "2001:db8::/64")
    created(create(http, "2001:db8:0:1::1"))
    # loopback clients are not limited (the machine's own users; the default --host 127.0.0.1 has no others)
    for _ in range(2):
        created(create(http))
    assert http.get("/healthz").json()["sessions_open"] == 8

    # deleting or finishing one of its sessions gives the client a slot back
    (sid0, auth0), (sid1, auth1) = a
    assert http.delete(f"/sessions/{sid0}", headers=auth0).status_code == 204
    sid2, auth2 = created(create(http, "203.0.113.7"))
    check_429(create(http, "203.0.113.7"))
    assert http.post(f"/sessions/{sid2}/finish", headers=auth2).json()["state"] == "finished"
    sid3, auth3 = created(create(http, "203.0.113.7"))

    # a session closed for idleness frees its slot, and resuming it counts again
    assert srv.manager.close_idle_sessions(now=time.monotonic() + 3600)  # every session here is idle
    sid4, auth4 = created(create(http, "203.0.113.7"))
    sid5, auth5 = created(create(http, "203.0.113.7"))
    check_429(http.post(f"/sessions/{sid1}/resume", headers=auth1), "maximum of 2")
    assert http.delete(f"/sessions/{sid4}", headers=auth4).status_code == 204
    assert http.post(f"/sessions/{sid1}/resume", headers=auth1).status_code == 202


def test_api_key_or_zero_lifts_the_per_client_limit(server_factory, tmp_path):
    keyed = server_factory(api_key=API_KEY, data_dir=tmp_path / "keyed")
    for _ in range(3):
        created(create(keyed.api.http, "203.0.113.7", **{"X-API-Key": API_KEY}))
    unlimited = server_factory(max_sessions_per_client=0, data_dir=tmp_path / "unlimited")
    for _ in range(3):
        created(create(unlimited.api.http, "203.0.113.7"))


def test_client_key():
    assert client_key("127.0.0.1") is None and client_key("127.0.0.2") is None and client_key("::1") is None
    assert client_key("::ffff:127.0.0.1") is None
    assert client_key("192.168.1.20") == "192.168.1.20"
    assert client_key("::ffff:192.168.1.20") == "192.168.1.20"
    assert client_key("2001:db8::1") == client_key("2001:db8::ffff") == "2001:db8::/64"
    assert client_key("not-an-ip") == "not-an-ip"
