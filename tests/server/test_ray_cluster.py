"""Session workers on a real local Ray cluster of two nodes (``ray.cluster_utils.Cluster``: a head and a
worker node on loopback, each its own raylet): sessions spread over both nodes, and when one node goes away
its sessions restart on the other, replaying their recordings, with nothing acknowledged lost."""

from __future__ import annotations

import pytest
from srvutil import FAST, ServerThread, make_scene, wait_until

from voxfusion.proto.recording import RecordingCapture
from voxfusion.server import ServerSettings

ray = pytest.importorskip("ray")
from ray.cluster_utils import Cluster  # noqa: E402

N_SESSIONS = 4
N_FRAMES = 6


@pytest.fixture
def cluster():
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 2})
    worker = c.add_node(num_cpus=2)
    c.wait_for_nodes()
    yield c, worker
    c.shutdown()


def test_sessions_spread_over_nodes_and_survive_a_lost_node(cluster, tmp_path):
    c, worker_node = cluster
    srv = ServerThread(ServerSettings(data_dir=tmp_path / "data", device="cpu", zenoh=False, ray_address=c.address,
                                      cpus_per_session=0.5))
    try:
        api = srv.api
        scenes = [make_scene(N_FRAMES, seed=40 + k) for k in range(N_SESSIONS)]
        sessions = [api.create(f"ray-{k}", config=FAST, mode="offline") for k in range(N_SESSIONS)]
        nodes = {sid: api.status(sid, token)["worker_node"] for sid, token in sessions}
        assert set(nodes.values()) == {c.head_node.node_id, worker_node.node_id}, nodes  # both nodes hold sessions
        for k, (sid, token) in enumerate(sessions):
            for m in scenes[k].messages[: N_FRAMES // 2]:
                assert api.post_frame(sid, token, m).status_code == 202
        for sid, token in sessions:
            wait_until(lambda sid=sid, token=token: api.status(sid, token)["frames_tracked"] == N_FRAMES // 2, 180,
                       "every session to track its first frames")

        c.remove_node(worker_node)  # the machine is gone, with its actors
        for k, (sid, token) in enumerate(sessions):
            for m in scenes[k].messages[N_FRAMES // 2:]:
                assert api.post_frame(sid, token, m).status_code == 202
        moved = [sid for sid, node in nodes.items() if node == worker_node.node_id]
        for k, (sid, token) in enumerate(sessions):
            st = wait_until(lambda sid=sid, token=token: (s := api.status(sid, token))["frames_tracked"] == N_FRAMES
                            and s["replay_pending"] == 0 and s, 300, f"session {k} to track every frame")
            assert st["state"] == "running" and st["worker_node"] == c.head_node.node_id
            assert st["worker_restarts"] == (1 if sid in moved else 0)
            assert len(RecordingCapture(srv.settings.sessions_dir / sid)) == N_FRAMES  # nothing acknowledged lost
            done = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token))
            assert done.status_code == 200 and done.json()["state"] == "finished", done.text
            poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
            assert [p["seq"] for p in poses] == list(range(N_FRAMES))  # one pose per frame, in order
        assert moved, "no session was on the removed node"
    finally:
        srv.stop()
