"""The zenoh LAN setup (``--zenoh-secrets``) against rogue peers on loopback.

A real server (uvicorn + zenoh bridge with the rendered ``server-lan`` config: user-password authentication and
access control) and a legitimate client stream a session while two rogues listen on everything:

* a peer **without credentials** subscribes to ``voxfusion/**`` (data and liveliness), serves queryables on
  ``voxfusion/**`` and queries ``voxfusion/**``: it sees no token, no pose, no ack, no session id, and its
  wildcard queries create no session;
* a client **with the client credentials** (a teammate's device gone bad) declares subscribers and
  queryables on the keys that carry tokens (frames, queries): no token, frame or query ever reaches it, and
  liveliness lists no session id to it. (It can subscribe to every session's poses and acks: the client
  credential is one per server, so poses are shared among its holders; tokens, frames and maps are not.)

Also: listening beyond loopback without authentication is refused, and on the plain loopback config a
wildcard query no longer creates a session.
"""

from __future__ import annotations

import json
import threading

import pytest
import zenoh
from srvutil import TINY, ServerThread, free_port, make_scene, wait_until

from voxfusion.clients.zenoh_client import ZenohClient
from voxfusion.clients.zenoh_config import default_zenoh_config_path, ensure_zenoh_secrets, load_zenoh_config
from voxfusion.core.errors import ConfigError
from voxfusion.server import ServerSettings

N_FRAMES = 4


class Spy:
    """Everything a rogue session observes, as text (payloads, attachments, keys)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.seen: list[str] = []

    def sample(self, sample) -> None:
        parts = [str(sample.key_expr), sample.payload.to_bytes().decode("latin-1")]
        if sample.attachment is not None:
            parts.append(sample.attachment.to_bytes().decode("latin-1"))
        with self.lock:
            self.seen.append(" ".join(parts))

    def query(self, query) -> None:
        parts = [str(query.key_expr)]
        if query.payload is not None:
            parts.append(query.payload.to_bytes().decode("latin-1"))
        if query.attachment is not None:
            parts.append(query.attachment.to_bytes().decode("latin-1"))
        with self.lock:
            self.seen.append(" ".join(parts))

    def text(self) -> str:
        with self.lock:
            return "\n".join(self.seen)


def _rogue(endpoint: str, mode: str, credentials: tuple[str, str] | None) -> zenoh.Session:
    cfg = {"mode": mode, "connect": {"endpoints": [endpoint]},
           "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
    if credentials is not None:
        cfg["transport"] = {"auth": {"usrpwd": {"user": credentials[0], "password": credentials[1]}}}
    return zenoh.open(zenoh.Config.from_json5(json.dumps(cfg)))


def _listen_everywhere(z: zenoh.Session, spy: Spy) -> list:
    """Subscribe to and serve every voxfusion key, data and liveliness (what a rogue would do)."""
    entities = []
    for key in ("voxfusion/**", "voxfusion/@v1/sessions/*/frames", "voxfusion/@v1/sessions/*/poses",
                "voxfusion/@v1/sessions/*/acks"):
        entities.append(z.declare_subscriber(key, spy.sample))
    for key in ("voxfusion/**", "voxfusion/@v1/sessions/*/frames", "voxfusion/@v1/sessions/*/status",
                "voxfusion/@v1/sessions/create"):
        entities.append(z.declare_queryable(key, spy.query))
    entities.append(z.liveliness().declare_subscriber("voxfusion/**", spy.sample, history=True))
    return entities


def _probe(z: zenoh.Session, spy: Spy) -> None:
    """Query everything: wildcard data queries (which must create nothing) and liveliness."""
    for reply in z.get("voxfusion/@v1/**", timeout=2.0):
        if reply.ok is not None:
            spy.sample(reply.ok)
    for reply in z.liveliness().get("voxfusion/**", timeout=2.0):
        if reply.ok is not None:
            spy.seen.append(str(reply.ok.key_expr))


def test_rogue_peers_learn_nothing_on_the_lan_setup(tmp_path):
    secrets = ensure_zenoh_secrets(tmp_path / "secrets")
    assert secrets.created and oct(secrets.credentials.stat().st_mode & 0o777) == "0o600"
    users = dict(line.split(":", 1) for line in secrets.credentials.read_text().splitlines())
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    srv = ServerThread(ServerSettings(data_dir=tmp_path / "data", device="cpu", zenoh=True,
                                      zenoh_secrets=tmp_path / "secrets", zenoh_listen=(endpoint,)))
    outsider_spy, insider_spy = Spy(), Spy()
    insider_credentials = ("voxfusion-client", users["voxfusion-client"])
    outsider = _rogue(endpoint, "peer", None)
    insider = _rogue(endpoint, "client", insider_credentials)
    # separate sessions query, so that a rogue's own queryables never answer its own queries
    outsider_prober = _rogue(endpoint, "peer", None)
    insider_prober = _rogue(endpoint, "client", insider_credentials)
    entities = _listen_everywhere(outsider, outsider_spy) + _listen_everywhere(insider, insider_spy)
    client = ZenohClient(secrets.client_config, connect=[endpoint])
    try:
        assert client.servers(), "the legitimate client must see the server"
        scene = make_scene(N_FRAMES, seed=31)
        handle = client.create_session("lan", TINY, mode="offline")
        poses = []
        client.subscribe_poses(poses.append)
        for frame in scene.capture.frames():
            client.send_frame(frame)
        wait_until(lambda: client.status().frames_tracked == N_FRAMES, 120, "the session to track every frame")
        wait_until(lambda: len(poses) == N_FRAMES, 30, "the client's poses")
        _probe(outsider_prober, outsider_spy)
        _probe(insider_prober, insider_spy)
        sessions_before = srv.manager.health().sessions_total
        threading.Event().wait(1.0)
        token, sid = handle.token, handle.id
        for name, spy in (("without credentials", outsider_spy), ("with client credentials", insider_spy)):
            seen = spy.text()
            assert token not in seen, f"a rogue {name} saw the session token"
            if name == "without credentials":
                assert seen == "", f"a rogue {name} observed: {seen[:300]}"
            else:
                # it can find the server, and (like every holder of the client credentials) subscribe to poses and
                # acks; but it never receives frames or queries (they carry tokens and images), and liveliness
                # does not list session ids to it
                keys = {line.split(" ", 1)[0] for line in spy.seen}
                assert not any(k.endswith("/frames") or "/sessions/create" in k for k in keys), keys
                assert f"voxfusion/@v1/sessions/{sid}" not in keys, "liveliness listed the session id"
        assert srv.manager.health().sessions_total == sessions_before == 1  # wildcard queries created nothing
        # the legitimate client keeps working after all that
        assert client.status().frames_tracked == N_FRAMES
    finally:
        client.close()
        for e in entities:
            e.undeclare()
        for z in (outsider, insider, outsider_prober, insider_prober):
            z.close()
        srv.stop()


def test_listening_beyond_loopback_needs_authentication(tmp_path):
    from voxfusion.server import SessionManager
    from voxfusion.server.zenoh_bridge import ZenohBridge

    manager = SessionManager(ServerSettings(data_dir=tmp_path / "data", device="cpu"))
    manager.open()
    try:
        bridge = ZenohBridge(manager, listen=[f"tcp/0.0.0.0:{free_port()}"])
        with pytest.raises(ConfigError, match="without authentication"):
            bridge.start()
        with pytest.raises(ConfigError, match="is a template"):  # the shipped template is not a config
            load_zenoh_config(default_zenoh_config_path("server-lan"), "server")
    finally:
        manager.close()


def test_wildcard_query_creates_no_session_on_the_loopback_config(tmp_path):
    port = free_port()
    srv = ServerThread(ServerSettings(data_dir=tmp_path / "data", device="cpu", zenoh=True,
                                      zenoh_listen=(f"tcp/127.0.0.1:{port}",)))
    z = _rogue(f"tcp/127.0.0.1:{port}", "client", None)
    try:
        replies = list(z.get("voxfusion/@v1/**", timeout=3.0))
        assert srv.manager.health().sessions_total == 0
        assert all(r.ok is None for r in replies)  # only refusals
    finally:
        z.close()
        srv.stop()


def test_serve_refuses_an_unauthenticated_lan_listener(tmp_path):
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "voxfusion.cli", "serve", "--data-dir", str(tmp_path / "data"), "--port",
           str(free_port()), "--zenoh-listen", f"tcp/0.0.0.0:{free_port()}"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "--zenoh-secrets" in out.stderr and "--zenoh-insecure" in out.stderr, out.stderr
