"""End to end on a real uvicorn server: stream a synthetic capture over HTTP, follow poses on the
WebSocket, check the trajectory (ATE), depth rendered at tracked poses, mesh / voxel downloads, finish."""

from __future__ import annotations

import io
import json
import threading
import urllib.request

import cv2
import numpy as np
import pytest
import trimesh
from srvutil import ServerThread, make_scene, wait_until
from websockets.sync.client import connect

from voxfusion.core.eval import TrajectoryEvalConfig, compute_ate
from voxfusion.core.geometry import opencv_to_opengl
from voxfusion.core.trajectory import Trajectory, read_tum_trajectory
from voxfusion.proto.recording import RecordingCapture

N_FRAMES = 10
ATE_BOUND_M = 0.05
RENDER_BOUND_M = 0.05


@pytest.fixture(scope="module")
def streamed(tmp_path_factory):
    """One offline session (every frame tracked) streamed with a WebSocket listening."""
    from voxfusion.server import ServerSettings

    srv = ServerThread(ServerSettings(data_dir=tmp_path_factory.mktemp("stream") / "data", device="cpu", zenoh=False))
    api = srv.api
    scene = make_scene(N_FRAMES, seed=1)
    sid, token = api.create("desk", mode="offline")
    ws_messages: list[dict] = []
    ws_url = f"ws://127.0.0.1:{srv.port}/sessions/{sid}/poses/stream?token={token}"
    connected = threading.Event()

    def listen() -> None:
        with connect(ws_url, ping_interval=None) as ws:
            connected.set()
            for text in ws:
                ws_messages.append(json.loads(text))

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    assert connected.wait(30)
    wait_until(lambda: srv.manager.pose_listener_count(sid), 30, "the WebSocket listener to register")
    acks = [api.post_frame(sid, token, m) for m in scene.messages]
    wait_until(lambda: api.status(sid, token)["frames_tracked"] >= N_FRAMES, 300, "every frame to be tracked")
    wait_until(lambda: len(ws_messages) >= N_FRAMES, 30, "the WebSocket poses")
    acks.append(api.post_frame(sid, token, scene.messages[3]))  # a retried frame (same seq): acknowledged, not kept
    yield srv, api, scene, sid, token, acks, ws_messages
    srv.stop()
    listener.join(timeout=30)


def test_frames_are_acknowledged_with_their_seq_and_recorded(streamed):
    srv, api, scene, sid, token, acks, _ = streamed
    *acks, again = acks
    assert [a.status_code for a in acks] == [202] * N_FRAMES
    assert [a.json() for a in acks] == [{"seq": i, "session": sid, "duplicate": False, "action": "recorded"}
                                        for i in range(N_FRAMES)]
    cap = RecordingCapture(srv.settings.sessions_dir / sid)
    assert cap.seqs() == list(range(N_FRAMES))
    assert [cap.message(i) for i in range(N_FRAMES)] == scene.messages  # recorded byte for byte
    # the retried frame (same seq) was acknowledged again but not recorded twice
    assert again.status_code == 202 and again.headers["X-Duplicate"] == "true"
    assert again.json() == {"seq": 3, "session": sid, "duplicate": True, "action": "ignored"}
    assert len(RecordingCapture(srv.settings.sessions_dir / sid)) == N_FRAMES


def test_status_counts_frames(streamed):
    _, api, _, sid, token, _, _ = streamed
    st = api.status(sid, token)
    assert st["state"] == "running" and st["mode"] == "offline" and st["name"] == "desk"
    assert st["frames_received"] == N_FRAMES and st["frames_tracked"] == N_FRAMES and st["frames_dropped"] == 0
    assert st["keyframes"] >= 1 and st["voxels"] > 0 and st["map_version"] >= 1 and st["latency_ms"] > 0
    listed = api.http.get("/sessions").json()["sessions"]
    assert [s["id"] for s in listed] == [sid]


def test_websocket_streams_every_pose_in_order(streamed):
    _, _, _, _, _, _, ws_messages = streamed
    poses = ws_messages[:N_FRAMES]
    assert [p["seq"] for p in poses] == list(range(N_FRAMES))
    for p in poses:
        T = np.asarray(p["T_world_cam"])
        assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1]) and p["convention"] == "opencv"


def test_trajectory_matches_ground_truth(streamed, tmp_path):
    _, api, scene, sid, token, _, _ = streamed
    r = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token))
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    poses = r.json()["poses"]
    assert [p["seq"] for p in poses] == list(range(N_FRAMES))
    est = Trajectory(np.array([p["timestamp_s"] for p in poses]), np.array([p["T_world_cam"] for p in poses]))
    ate = compute_ate(est, scene.gt, TrajectoryEvalConfig(align="se3", max_diff_s=1e-3))
    assert ate.n == N_FRAMES and ate.rmse_m < ATE_BOUND_M, ate.rmse_m
    # the TUM text is the same trajectory
    tum = api.http.get(f"/sessions/{sid}/poses", params={"format": "tum"}, headers=api.auth(token))
    assert tum.status_code == 200 and tum.headers["content-type"].startswith("text/plain")
    (tmp_path / "traj.txt").write_text(tum.text)
    np.testing.assert_allclose(read_tum_trajectory(tmp_path / "traj.txt").T_world_cam, est.T_world_cam, atol=1e-6)
    latest = api.http.get(f"/sessions/{sid}/poses/latest", headers=api.auth(token)).json()
    assert latest["seq"] == N_FRAMES - 1


def _render(api, sid, token, T, K, w, h, **extra):
    body = {"T_world_cam": T.tolist(), "width": w, "height": h,
            "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}, **extra}
    r = api.http.post(f"/sessions/{sid}/render", json=body, headers=api.auth(token))
    assert r.status_code == 200, r.text
    return r


def test_depth_rendered_at_tracked_poses_matches_the_input(streamed):
    _, api, scene, sid, token, _, _ = streamed
    poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
    for i in (2, 6, N_FRAMES - 1):
        frame = scene.capture[i]
        h, w = frame.depth_m.shape
        T = np.asarray(poses[i]["T_world_cam"])
        r = _render(api, sid, token, T, frame.K, w, h)
        n_depth, n_mask = int(r.headers["X-Depth-Bytes"]), int(r.headers["X-Mask-Bytes"])
        assert (n_depth, n_mask, int(r.headers["X-Color-Bytes"])) == (w * h * 2, w * h, 0)
        assert r.headers["X-Depth-Units"] == "m" and int(r.headers["X-Map-Version"]) >= 1
        depth = np.frombuffer(r.content[:n_depth], dtype="<f2").reshape(h, w).astype(np.float32)
        mask = np.frombuffer(r.content[n_depth:n_depth + n_mask], dtype=np.uint8).reshape(h, w).astype(bool)
        assert np.array_equal(mask, depth > 0)
        both = mask & (frame.depth_m > 0)
        assert both.mean() > 0.8
        err = np.median(np.abs(depth[both] - frame.depth_m[both]))
        assert err < RENDER_BOUND_M, (i, err)
    # png16 (millimetres) and colour, with the pose in ARKit axes: the same depth
    r16 = _render(api, sid, token, opencv_to_opengl(T), frame.K, w, h, format="png16", convention="arkit",
                  with_color=True)
    nd, nm, nc = (int(r16.headers[k]) for k in ("X-Depth-Bytes", "X-Mask-Bytes", "X-Color-Bytes"))
    mm = cv2.imdecode(np.frombuffer(r16.content[:nd], np.uint8), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and mm.shape == (h, w)
    np.testing.assert_allclose(mm / 1000.0, depth, atol=0.003)
    mask16 = cv2.imdecode(np.frombuffer(r16.content[nd:nd + nm], np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(mask16 > 0, mask)
    color = cv2.imdecode(np.frombuffer(r16.content[nd + nm:nd + nm + nc], np.uint8), cv2.IMREAD_COLOR)
    assert color.shape == (h, w, 3) and color[mask].std() > 5  # textured, not a constant


def test_mesh_downloads_with_a_plain_get(streamed):
    srv, api, _, sid, token, _, _ = streamed
    req = urllib.request.Request(f"{srv.url}/sessions/{sid}/mesh", headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=120) as resp:
        data = resp.read()
        headers = {k.lower(): v for k, v in resp.headers.items()}
    assert headers["content-type"] == "application/octet-stream"
    assert headers["content-disposition"].startswith('attachment; filename="voxfusion-')
    assert headers["content-disposition"].endswith('.ply"')
    mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    assert len(mesh.vertices) > 100 and len(mesh.faces) > 100
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape == (len(mesh.vertices), 4) and colors[:, :3].std() > 5
    # unchanged map: the ETag answers 304
    again = api.http.get(f"/sessions/{sid}/mesh", headers={**api.auth(token), "If-None-Match": headers["etag"]})
    assert again.status_code == 304
    for fmt, ctype in (("glb", "model/gltf-binary"), ("obj", "model/obj")):
        r = api.http.get(f"/sessions/{sid}/mesh", params={"format": fmt}, headers=api.auth(token))
        assert r.status_code == 200 and r.headers["content-type"] == ctype
        assert r.headers["content-disposition"].endswith(f'.{fmt}"')
        assert len(trimesh.load(io.BytesIO(r.content), file_type=fmt, force="mesh").vertices) > 100
    bad = api.http.get(f"/sessions/{sid}/mesh", params={"format": "stl"}, headers=api.auth(token))
    assert bad.status_code == 422 and bad.json()["field"] == "format"
    # which frame each export is in: the sidecar object, and a GLB that is the PLY turned Y-up by it
    frames = {fmt: api.http.get(f"/sessions/{sid}/mesh/frame", params={"format": fmt}, headers=api.auth(token))
              for fmt in ("ply", "glb")}
    assert all(r.status_code == 200 for r in frames.values())
    assert frames["ply"].json()["T_world_file"] == np.eye(4).tolist()
    T_world_glb = np.asarray(frames["glb"].json()["T_world_file"])
    assert frames["glb"].json()["file_axes"] == "gltf_y_up" and not np.allclose(T_world_glb, np.eye(4))
    assert frames["glb"].json()["world"] in ("reference", "device", "first_camera")
    glb = trimesh.load(io.BytesIO(api.http.get(f"/sessions/{sid}/mesh", params={"format": "glb"},
                                               headers=api.auth(token)).content), file_type="glb", force="mesh")
    back = glb.vertices @ T_world_glb[:3, :3].T + T_world_glb[:3, 3]
    np.testing.assert_allclose(np.sort(back, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-4)


def test_voxels_download(streamed):
    _, api, _, sid, token, _, _ = streamed
    st = api.status(sid, token)
    r = api.http.get(f"/sessions/{sid}/voxels", headers=api.auth(token))
    assert r.status_code == 200 and r.headers["content-disposition"].endswith('.npz"')
    npz = np.load(io.BytesIO(r.content))
    assert npz["morton_codes"].shape[0] == st["voxels"] and npz["embeddings"].ndim == 2
    assert any(k.startswith("decoder/") for k in npz.files)
    ply = api.http.get(f"/sessions/{sid}/voxels", params={"format": "ply"}, headers=api.auth(token))
    assert len(trimesh.load(io.BytesIO(ply.content), file_type="ply").vertices) == st["voxels"]


def test_docs_metrics_and_health(streamed):
    _, api, _, sid, _, _, _ = streamed
    assert api.http.get("/docs").status_code == 200
    paths = api.http.get("/openapi.json").json()["paths"]
    for p in ("/sessions", "/sessions/{session_id}/frames", "/sessions/{session_id}/render",
              "/sessions/{session_id}/mesh", "/sessions/{session_id}/poses", "/healthz", "/metrics"):
        assert p in paths
    health = api.http.get("/healthz").json()
    assert health["status"] == "ok" and health["sessions_open"] == 1 and health["device"] == "cpu"
    metrics = api.http.get("/metrics")
    assert metrics.headers["content-type"].startswith("text/plain; version=0.0.4")
    values = {line.rsplit(" ", 1)[0]: float(line.rsplit(" ", 1)[1]) for line in metrics.text.splitlines()
              if line and not line.startswith("#")}
    assert values["voxfusion_frames_accepted_total"] == N_FRAMES
    assert values["voxfusion_frames_duplicate_total"] == 1
    assert values[f'voxfusion_session_frames_tracked_total{{session="{sid}"}}'] == N_FRAMES
    assert values['voxfusion_http_requests_total{method="POST",route="/sessions/{session_id}/frames",status="202"}'] \
        == N_FRAMES + 1


def test_finish_then_outputs_come_from_disk(streamed):
    srv, api, scene, sid, token, _, ws_messages = streamed
    r = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token))
    assert r.status_code == 200, r.text
    st = r.json()
    assert st["state"] == "finished" and st["frames_tracked"] == N_FRAMES
    folder = srv.settings.sessions_dir / sid
    for name in ("checkpoint.pt", "mesh.ply", "poses.json", "trajectory.txt", "recording.vxr"):
        assert (folder / name).is_file(), name
    assert len(read_tum_trajectory(folder / "trajectory.txt")) == N_FRAMES
    # outputs are served from the checkpoint / files now
    mesh = api.http.get(f"/sessions/{sid}/mesh", headers=api.auth(token))
    assert mesh.status_code == 200 and mesh.content == (folder / "mesh.ply").read_bytes()
    sidecar = json.loads((folder / "mesh.ply.frame.json").read_text())
    stored = api.http.get(f"/sessions/{sid}/mesh/frame", params={"format": "glb"}, headers=api.auth(token)).json()
    assert stored["world"] == sidecar["world"] and stored["up"] == sidecar["up"]
    poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
    assert len(poses) == N_FRAMES
    frame = scene.capture[4]
    _render(api, sid, token, np.asarray(poses[4]["T_world_cam"]), frame.K, 48, 36)
    # finishing is idempotent; frames are refused now; the WebSocket ended
    assert api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token)).json()["state"] == "finished"
    late = api.post_frame(sid, token, scene.messages[0])
    assert late.status_code == 409 and "finished" in late.json()["detail"]
    wait_until(lambda: ws_messages and ws_messages[-1].get("event") == "end", 30, "the WebSocket end message")
    assert ws_messages[-1]["state"] == "finished"


def test_realtime_session_finished_at_once_still_tracks_and_maps_its_frames(server_factory):
    """``finish`` right after the frames (before the tracker has taken the first) drains the engine's queue:
    the session ends with a map, not ``finished`` with 0 frames tracked and no mesh."""
    from srvutil import TINY

    srv = server_factory()
    scene = make_scene(3, seed=4)
    sid, token = srv.api.create(config=TINY, mode="realtime")
    for m in scene.messages:
        assert srv.api.post_frame(sid, token, m).status_code == 202
    r = srv.api.http.post(f"/sessions/{sid}/finish", headers=srv.api.auth(token))
    assert r.status_code == 200, r.text
    st = r.json()
    assert st["state"] == "finished" and st["frames_tracked"] >= 1, st
    assert st["frames_tracked"] + st["frames_dropped"] == 3, st
    assert srv.api.http.get(f"/sessions/{sid}/mesh", headers=srv.api.auth(token)).status_code == 200
