"""The zenoh bridge end to end on loopback: a real server (uvicorn + zenoh peer on a free port) and real
zenoh clients.

* the same synthetic capture streamed over zenoh into one session and over HTTP into another gives
  trajectories that agree; every tracked pose arrives on the ``poses`` key;
* the ``render``, ``mesh``, ``voxels``, ``status`` and ``trajectory`` queryables answer;
* plain ``put``s on ``frames`` are acknowledged on ``acks`` in order; a wrong token, a corrupt frame and an
  unknown session are refused with the HTTP-equivalent status and the bridge keeps working;
* a session whose engine blocks never delays another session or a query; a full per-session queue
  refuses new frames with 429 and keeps the order of the queued ones;
* liveliness tokens for the server and each live session; ``create`` honours the server API key.
"""

from __future__ import annotations

import io
import json
import threading

import numpy as np
import pytest
import trimesh
import zenoh
from srvutil import ServerThread, free_port, wait_until

from voxfusion.clients import Client, ServerError
from voxfusion.clients.zenoh_client import ZenohClient
from voxfusion.clients.zenoh_config import default_zenoh_config_path
from voxfusion.clients.zenoh_keys import SERVERS_LIVELINESS, session_key
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.eval import compute_ate
from voxfusion.core.trajectory import Trajectory
from voxfusion.proto import encode_frame
from voxfusion.server import ServerSettings, SessionManager
from voxfusion.server.zenoh_bridge import BridgeOptions, ZenohBridge

TINY = ["mapping.rays_per_frame=128", "tracking.rays=128", "tracking.iters=10", "mapping.first_frame_iters=30",
        "field.sdf_hidden=32", "field.color_hidden=32", "mesh_res=4"]
N_FRAMES = 10


def _zenoh_config(path, port: int):
    """The shipped server config (loopback peer, scouting off) listening on ``port``."""
    shipped = default_zenoh_config_path("server").read_text()
    assert "tcp/127.0.0.1:7447" in shipped
    path.write_text(shipped.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}"))
    return path


def _raw_session(port: int):
    cfg = zenoh.Config.from_json5(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                                              "scouting": {"multicast": {"enabled": False},
                                                           "gossip": {"enabled": False}}}))
    return zenoh.open(cfg)


def _put(z, key: str, payload: bytes, attachment: bytes) -> None:
    """A frame ``put`` as a streamer that wants every frame must send it: congestion control BLOCK (zenoh's
    default for ``put``, DROP, silently discards messages when the link's queue is full, e.g. on a loaded CI
    machine)."""
    z.put(key, payload, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK)


@pytest.fixture(scope="module")
def frames():
    cap = SyntheticCapture(SyntheticConfig(n_frames=N_FRAMES, width=96, height=72, seed=3))
    return list(cap.frames())


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("zenoh-server")
    port = free_port()
    srv = ServerThread(ServerSettings(data_dir=tmp / "data", device="cpu", zenoh=True,
                                      zenoh_config=_zenoh_config(tmp / "server.json5", port)))
    srv.zenoh_port = port
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def zclient(server):
    client = ZenohClient(connect=[f"tcp/127.0.0.1:{server.zenoh_port}"], timeout_s=120)
    yield client
    client.close()


@pytest.fixture(scope="module")
def streamed(server, zclient, frames):
    """The capture streamed over zenoh (session A) and over HTTP (session B), both finished."""
    poses = []
    zclient.create_session("zenoh", TINY, mode="offline")
    zclient.subscribe_poses(poses.append)
    futures = [zclient.send_frame_async(f) for f in frames]
    seqs = [f.result(timeout=120) for f in futures]
    status_a = zclient.finish(timeout_s=300)
    traj_a = zclient.trajectory()
    with Client(server.url) as http:
        http.create_session("http", TINY, mode="offline")
        for f in frames:
            http.send_frame(f)
        status_b = http.finish(timeout_s=300)
        traj_b = http.trajectory()
    return {"seqs": seqs, "poses": poses, "a": (status_a, traj_a), "b": (status_b, traj_b)}


def _trajectory(poses) -> Trajectory:
    return Trajectory(np.array([p.timestamp_s for p in poses]), np.array([p.T_world_cam for p in poses]))


def test_zenoh_and_http_sessions_give_the_same_trajectory(streamed, frames):
    status_a, traj_a = streamed["a"]
    status_b, traj_b = streamed["b"]
    assert streamed["seqs"] == list(range(N_FRAMES))
    assert status_a.state.value == status_b.state.value == "finished"
    assert status_a.frames_received == status_b.frames_received == N_FRAMES
    assert [p.seq for p in traj_a] == [p.seq for p in traj_b] == list(range(N_FRAMES))
    Ta, Tb = (np.array([p.T_world_cam for p in t]) for t in (traj_a, traj_b))
    # Same frames, same engine: the sessions differ only by thread timing inside the engine.
    assert np.abs(Ta[:, :3, 3] - Tb[:, :3, 3]).max() < 0.05
    cos = (np.einsum("nij,nij->n", Ta[:, :3, :3], Tb[:, :3, :3]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 3.0
    gt = Trajectory(np.array([f.timestamp_s for f in frames]), np.stack([f.T_world_cam for f in frames]))
    for traj in (traj_a, traj_b):
        assert compute_ate(_trajectory(traj), gt).rmse_m < 0.05


def test_every_tracked_pose_arrives_on_the_poses_key(streamed):
    got = streamed["poses"]
    assert sorted(p.seq for p in got) == list(range(N_FRAMES))
    for p in got:
        assert np.allclose(np.array(p.T_world_cam)[3], [0, 0, 0, 1])


def test_queryables_answer(streamed, zclient, frames):
    _, traj = streamed["a"]
    status = zclient.status()
    assert status.state.value == "finished" and status.frames_tracked == N_FRAMES
    assert zclient.latest_pose().seq == N_FRAMES - 1
    # render: depth at a tracked pose agrees with the frame's own depth
    i = 5
    depth = zclient.render_depth(np.array(traj[i].T_world_cam), frames[i].K, 96, 72)
    assert depth.shape == (72, 96) and depth.dtype == np.float32
    both = (depth > 0) & (frames[i].depth_m > 0)
    assert both.mean() > 0.5
    assert np.median(np.abs(depth[both] - frames[i].depth_m[both])) < 0.1
    png = zclient.render_depth(np.array(traj[i].T_world_cam), frames[i].K, 96, 72, format="png16")
    assert np.abs(png - depth)[both].max() < 0.01  # the same render, mm vs half floats
    # mesh / voxels / trajectory
    mesh = trimesh.load(io.BytesIO(zclient.download_mesh(format="ply")), file_type="ply")
    assert len(mesh.vertices) > 100 and len(mesh.faces) > 100
    voxels = np.load(io.BytesIO(zclient.download_voxels(format="npz")))
    assert len(voxels.files) > 0
    tum = zclient.trajectory_tum().strip().splitlines()
    assert len([line for line in tum if not line.startswith("#")]) == N_FRAMES


def test_queries_check_the_token_and_the_session(server, zclient, streamed):
    other = ZenohClient(connect=[f"tcp/127.0.0.1:{server.zenoh_port}"], session_id=zclient.session.id,
                        token="not-the-token")
    try:
        with pytest.raises(ServerError) as err:
            other.status()
        assert err.value.status == 403
        other.attach("0" * 32, zclient.session.token)
        with pytest.raises(ServerError) as err:
            other.status()
        assert err.value.status == 404
        other.attach(zclient.session.id, zclient.session.token)
        reply = other._get(session_key(zclient.session.id, "render"), payload=b'{"width": 0}',
                           attachment=zclient.session.token.encode())
    except ServerError as e:
        assert e.status == 422 and e.field == "body"
    else:
        pytest.fail(f"a malformed render request was answered: {reply.payload[:80]!r}")
    finally:
        other.close()


def test_liveliness_tokens(server, zclient, streamed):
    assert zclient.servers()
    finished_id = zclient.session.id
    wait_until(lambda: finished_id not in zclient.live_sessions(), 10, "the finished session's token to go")
    probe = ZenohClient(connect=[f"tcp/127.0.0.1:{server.zenoh_port}"])
    try:
        live = probe.create_session("live", TINY)
        assert live.id in probe.live_sessions()
        with Client(server.url) as http:  # a session created over HTTP gets its token from the sync thread
            h = http.create_session("over-http", TINY)
            wait_until(lambda: h.id in probe.live_sessions(), 10, "the HTTP session's liveliness token")
    finally:
        probe.close()


def test_put_frames_are_acknowledged_in_order_and_refusals_do_not_stop_the_bridge(server, frames):
    with Client(server.url) as http:
        h = http.create_session("puts", TINY)
    z = _raw_session(server.zenoh_port)
    acks, done = [], threading.Event()

    def on_ack(sample):
        acks.append(json.loads(sample.payload.to_bytes()))
        if len(acks) == 6:
            done.set()

    sub = z.declare_subscriber(session_key(h.id, "acks"), on_ack)
    key = session_key(h.id, "frames")
    try:
        _put(z, key, encode_frame(frames[0], seq=0, session=h.id), attachment=h.token.encode())
        _put(z, key, encode_frame(frames[1], seq=1, session=h.id), attachment=b"wrong-token")
        bad = bytearray(encode_frame(frames[1], seq=1, session=h.id))
        bad[-1] ^= 0xFF  # breaks the CRC
        _put(z, key, bytes(bad), attachment=h.token.encode())
        _put(z, key, encode_frame(frames[1], seq=1, session=h.id), attachment=h.token.encode())
        _put(z, key, encode_frame(frames[2], seq=2, session=h.id), attachment=h.token.encode())
        _put(z, session_key("f" * 32, "frames"), encode_frame(frames[3], seq=3), attachment=h.token.encode())
        _put(z, key, encode_frame(frames[3], seq=3, session=h.id), attachment=h.token.encode())
        assert done.wait(60), acks
    finally:
        sub.undeclare()
        z.close()
    ok = [a["seq"] for a in acks if a["ok"]]
    refused = sorted((a["status"], a.get("field")) for a in acks if not a["ok"])
    assert ok == [0, 1, 2, 3]
    assert refused == [(400, "crc"), (403, "Authorization")]
    assert server.manager.status(h.id).frames_received == 4
    assert server.manager.counters[("zenoh_frames_rejected_total", "404")] >= 1


def test_a_blocked_session_never_delays_another_and_a_full_queue_refuses_in_order(server, frames, tmp_path,
                                                                                    monkeypatch):
    manager = server.manager
    port = free_port()
    bridge = ZenohBridge(manager, _zenoh_config(tmp_path / "b.json5", port),
                         options=BridgeOptions(ingest_queue_frames=2))
    bridge.start()
    gate = threading.Event()
    with Client(server.url) as http:
        slow = http.create_session("slow", TINY)
        fast = http.create_session("fast", TINY)
    original = manager.submit_frame_bytes

    def submit(session_id, data):
        if session_id == slow.id:
            gate.wait(60)
        return original(session_id, data)

    monkeypatch.setattr(manager, "submit_frame_bytes", submit)
    z = _raw_session(port)
    acks: list[dict] = []
    sub = z.declare_subscriber(session_key(slow.id, "acks"), lambda s: acks.append(json.loads(s.payload.to_bytes())))
    client = ZenohClient(connect=[f"tcp/127.0.0.1:{port}"], session_id=fast.id, token=fast.token)
    try:
        for i in range(5):  # 1 taken by the (blocked) worker, 2 queued, 2 refused at once
            _put(z, session_key(slow.id, "frames"), encode_frame(frames[i], seq=i, session=slow.id),
                  attachment=slow.token.encode())
        wait_until(lambda: len(acks) >= 2, 30, "the two refusals")
        assert [(a["ok"], a["status"], a["seq"]) for a in acks] == [(False, 429, 3), (False, 429, 4)]
        # meanwhile the other session takes frames and every query is answered
        assert [client.send_frame(f) for f in frames[:2]] == [0, 1]
        assert client.status().frames_received == 2
        gate.set()
        wait_until(lambda: len(acks) >= 5, 60, "the queued frames")
        assert [a["seq"] for a in acks[2:]] == [0, 1, 2] and all(a["ok"] for a in acks[2:])
    finally:
        gate.set()
        client.close()
        sub.undeclare()
        z.close()
        bridge.close()


def test_create_over_zenoh_honours_the_api_key(tmp_path):
    settings = ServerSettings(data_dir=tmp_path / "data", device="cpu", api_key="secret-key-123")
    manager = SessionManager(settings)
    manager.open()
    port = free_port()
    bridge = ZenohBridge(manager, _zenoh_config(tmp_path / "k.json5", port))
    try:
        bridge.start()
        assert manager.zenoh_running
        z = _raw_session(port)
        servers = [str(r.ok.key_expr) for r in z.liveliness().get(SERVERS_LIVELINESS, timeout=5) if r.ok]
        assert servers == [f"voxfusion/@v1/servers/{bridge.server_id}"]
        z.close()
        for key, status in ((None, 401), ("wrong-key-000", 403)):
            c = ZenohClient(connect=[f"tcp/127.0.0.1:{port}"], api_key=key)
            with pytest.raises(ServerError) as err:
                c.create_session("x", TINY)
            assert err.value.status == status
            c.close()
        c = ZenohClient(connect=[f"tcp/127.0.0.1:{port}"], api_key="secret-key-123")
        with pytest.raises(ServerError) as err:
            c.create_session("x", ["tracking.no_such_key=1"])
        assert err.value.status == 422 and err.value.field.startswith("config.")
        h = c.create_session("x", TINY)
        assert manager.get(h.id).name == "x"
        c.close()
    finally:
        bridge.close()
        manager.close()
    assert not manager.zenoh_running
