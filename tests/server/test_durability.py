"""Durability: ``kill -9`` the server mid-stream, restart it on the same data folder, and check that every
acknowledged frame is in the recording, that finished sessions serve their outputs from disk, and that the
unfinished session resumes (replays its recording) and finishes."""

from __future__ import annotations

import io
import threading

import httpx
import numpy as np
import trimesh
from srvutil import FAST, TINY, ServerProcess, make_scene, wait_until

from voxfusion.proto.recording import RecordingCapture


def test_kill_9_mid_stream_then_restart_resumes(tmp_path):
    data_dir = tmp_path / "data"
    scene = make_scene(12, seed=4)
    srv = ServerProcess(data_dir)
    api = srv.api
    # a session that finishes before the crash
    done_sid, done_token = api.create("done", config=TINY, mode="offline")
    for m in scene.messages[:5]:
        assert api.post_frame(done_sid, done_token, m).status_code == 202
    finished = api.http.post(f"/sessions/{done_sid}/finish", headers=api.auth(done_token)).json()
    assert finished["state"] == "finished" and finished["frames_tracked"] == 5
    done_poses = api.http.get(f"/sessions/{done_sid}/poses", headers=api.auth(done_token)).json()["poses"]
    done_mesh = api.http.get(f"/sessions/{done_sid}/mesh", headers=api.auth(done_token)).content

    # a session streaming from another thread when the server is killed
    sid, token = api.create("live", config=FAST)
    acked: list[int] = []
    six_acked = threading.Event()
    stop = threading.Event()

    def stream() -> None:
        with httpx.Client(base_url=srv.url, timeout=30) as client:
            for i, m in enumerate(scene.messages[:10]):
                if stop.is_set():
                    return
                try:
                    r = client.post(f"/sessions/{sid}/frames", content=m,
                                    headers={**api.auth(token), "Content-Type": "application/octet-stream"})
                except httpx.TransportError:
                    return
                if r.status_code == 202:
                    acked.append(r.json()["seq"])
                if i == 5:
                    six_acked.set()

    sender = threading.Thread(target=stream)
    sender.start()
    assert six_acked.wait(120)
    srv.kill()  # SIGKILL: no shutdown handler runs
    stop.set()
    sender.join(timeout=60)
    assert len(acked) >= 6

    # a torn final write (as if the kill had landed inside an append) is cut on restart
    rec_path = data_dir / "sessions" / sid / "recording.vxr"
    n_recorded = len(RecordingCapture(rec_path))
    with open(rec_path, "ab") as f:
        f.write(b"\x10\x27\x00\x00partial")

    srv = ServerProcess(data_dir)
    api = srv.api
    try:
        listed = {s["id"]: s for s in api.http.get("/sessions").json()["sessions"]}
        assert set(listed) == {done_sid, sid}
        assert listed[done_sid]["state"] == "finished" and not listed[done_sid]["resume_required"]
        assert listed[sid]["state"] == "running" and listed[sid]["resume_required"]
        assert listed[sid]["frames_received"] == n_recorded
        # every acknowledged frame is in the recording (a frame may be recorded but not yet acknowledged)
        seqs = RecordingCapture(data_dir / "sessions" / sid).seqs()
        assert set(acked) <= set(seqs) and len(seqs) == len(set(seqs)) == n_recorded

        # the finished session serves poses, mesh, voxels and renders from its checkpoint
        auth = api.auth(done_token)
        assert api.http.get(f"/sessions/{done_sid}/poses", headers=auth).json()["poses"] == done_poses
        mesh = api.http.get(f"/sessions/{done_sid}/mesh", headers=auth)
        assert mesh.status_code == 200 and mesh.content == done_mesh
        assert len(trimesh.load(io.BytesIO(mesh.content), file_type="ply").vertices) > 0
        assert api.http.get(f"/sessions/{done_sid}/voxels", headers=auth).status_code == 200
        K = scene.capture[0].K
        body = {"T_world_cam": done_poses[2]["T_world_cam"], "width": 96, "height": 72,
                "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}}
        render = api.http.post(f"/sessions/{done_sid}/render", json=body, headers=auth)
        assert render.status_code == 200 and float(render.headers["X-Valid-Fraction"]) > 0.5

        # the next frame resumes the unfinished session: its recording is replayed, then the new frame
        r = api.post_frame(sid, token, scene.messages[11])
        assert r.status_code == 202, r.text
        st = api.status(sid, token)
        assert st["state"] == "running" and not st["resume_required"]
        final = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token)).json()
        assert final["state"] == "finished", final
        assert final["frames_received"] == n_recorded + 1
        assert final["frames_tracked"] + final["frames_dropped"] == n_recorded + 1
        poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
        assert [p["seq"] for p in poses][: n_recorded] == seqs  # the replay tracked every recorded frame
        assert all(np.isfinite(np.asarray(p["T_world_cam"])).all() for p in poses)
        assert api.http.get(f"/sessions/{sid}/mesh", headers=api.auth(token)).status_code == 200
    finally:
        srv.stop()
    log = srv.read_log()
    assert "torn" in log, log


def test_graceful_restart_keeps_a_checkpoint_and_resumes_on_request(server_factory):
    scene = make_scene(4, seed=5)
    srv = server_factory()
    sid, token = srv.api.create("resume-me", config=FAST, mode="offline")
    # no pose yet, and the answer says that no frame came either (not that frames were lost)
    assert srv.api.http.get(f"/sessions/{sid}/poses", headers=srv.api.auth(token)).json() == {
        "session": sid, "poses": [], "frames_received": 0}
    for m in scene.messages:
        assert srv.api.post_frame(sid, token, m).status_code == 202
    early = srv.api.http.get(f"/sessions/{sid}/poses", headers=srv.api.auth(token)).json()
    assert early["frames_received"] == 4 and len(early["poses"]) <= 4  # the rest are queued, not lost
    wait_until(lambda: srv.api.status(sid, token)["frames_tracked"] == 4, 120, "tracking")
    srv.stop()  # graceful: open sessions are checkpointed
    folder = srv.settings.sessions_dir / sid
    assert (folder / "checkpoint.pt").is_file() and (folder / "poses.json").is_file()

    srv = server_factory()
    api = srv.api
    st = api.status(sid, token)
    assert st["resume_required"] and st["frames_received"] == 4
    # until it resumes, the session's outputs come from its last checkpoint
    stored = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()
    assert len(stored["poses"]) == 4 and stored["frames_received"] == 4
    assert api.http.get(f"/sessions/{sid}/mesh", headers=api.auth(token)).status_code == 200
    r = api.http.post(f"/sessions/{sid}/resume", headers=api.auth(token))
    assert r.status_code == 202 and r.json()["state"] == "running" and not r.json()["resume_required"]
    wait_until(lambda: api.status(sid, token)["frames_tracked"] == 4, 120, "the replay")
    assert api.status(sid, token)["replay_pending"] == 0
    assert api.http.post(f"/sessions/{sid}/resume", headers=api.auth(token)).status_code == 202  # no-op
    assert api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token)).json()["state"] == "finished"
    r = api.http.post(f"/sessions/{sid}/resume", headers=api.auth(token))
    assert r.status_code == 409 and "finished" in r.json()["detail"]
