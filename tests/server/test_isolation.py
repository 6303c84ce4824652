"""Sessions do not interfere: two concurrent sessions on different scenes each match their own ground
truth, and an engine failure in one session fails only that session."""

from __future__ import annotations

import threading

import numpy as np
from srvutil import FAST, TINY, make_scene, wait_until

from voxfusion.core.eval import TrajectoryEvalConfig, compute_ate
from voxfusion.core.slam import SlamSystem
from voxfusion.core.trajectory import Trajectory
from voxfusion.proto.recording import RecordingCapture

N_FRAMES = 8


def _trajectory(api, sid, token) -> Trajectory:
    poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
    return Trajectory(np.array([p["timestamp_s"] for p in poses]), np.array([p["T_world_cam"] for p in poses]))


def test_two_concurrent_sessions_track_their_own_scenes(server_factory):
    srv = server_factory()
    api = srv.api
    scenes = [make_scene(N_FRAMES, seed=11), make_scene(N_FRAMES, seed=12)]
    sessions = [api.create(f"scene-{i}", mode="offline", config=TINY) for i in range(2)]
    codes: list[list[int]] = [[], []]

    def stream(k: int) -> None:
        sid, token = sessions[k]
        for m in scenes[k].messages:
            codes[k].append(api.post_frame(sid, token, m).status_code)

    threads = [threading.Thread(target=stream, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert codes == [[202] * N_FRAMES] * 2
    for sid, token in sessions:
        wait_until(lambda sid=sid, token=token: api.status(sid, token)["frames_tracked"] == N_FRAMES, 300,
                   "both sessions to track every frame")
    for k, (sid, token) in enumerate(sessions):
        cap = RecordingCapture(srv.settings.sessions_dir / sid)
        assert [cap.message(i) for i in range(len(cap))] == scenes[k].messages  # its own frames, in order
        est = _trajectory(api, sid, token)
        ate = compute_ate(est, scenes[k].gt, TrajectoryEvalConfig(align="se3", max_diff_s=1e-3))
        assert ate.n == N_FRAMES and ate.rmse_m < 0.05, (k, ate.rmse_m)
        # its map holds its own room: depth rendered at its last pose matches its own input frame
        frame = scenes[k].capture[N_FRAMES - 1]
        K = frame.K
        body = {"T_world_cam": est.T_world_cam[-1].tolist(), "width": 96, "height": 72,
                "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}}
        r = api.http.post(f"/sessions/{sid}/render", json=body, headers=api.auth(token))
        depth = np.frombuffer(r.content[: 96 * 72 * 2], dtype="<f2").reshape(72, 96).astype(np.float32)
        both = (depth > 0) & (frame.depth_m > 0)
        assert both.mean() > 0.8 and np.median(np.abs(depth[both] - frame.depth_m[both])) < 0.05


def test_engine_failure_fails_only_its_session(server_factory, monkeypatch):
    # the failure is injected by patching the engine, which reaches only engines on this process's threads
    srv = server_factory(session_workers="thread")
    api = srv.api
    original = SlamSystem._track

    def track(self, frame, received_at):
        if self.config.seed == 4242:  # only the poisoned session's engine
            raise RuntimeError("injected tracking failure")
        return original(self, frame, received_at)

    monkeypatch.setattr(SlamSystem, "_track", track)
    scene = make_scene(6, seed=13)
    good_sid, good_token = api.create("good", config=FAST, mode="offline")
    bad_sid, bad_token = api.create("bad", config={**FAST, "seed": 4242}, mode="offline")
    assert api.post_frame(bad_sid, bad_token, scene.messages[0]).status_code == 202  # recorded before the failure
    for m in scene.messages[:3]:
        assert api.post_frame(good_sid, good_token, m).status_code == 202
    bad = wait_until(lambda: (s := api.status(bad_sid, bad_token))["state"] == "failed" and s, 60,
                     "the poisoned session to fail")
    assert "injected tracking failure" in bad["last_error"]
    assert "recorded frame 0" in bad["last_error"] and "without it" in bad["last_error"]
    # the other session, the server and new sessions keep working
    for m in scene.messages[3:]:
        assert api.post_frame(good_sid, good_token, m).status_code == 202
    wait_until(lambda: api.status(good_sid, good_token)["frames_tracked"] == 6, 120, "the good session")
    assert api.status(good_sid, good_token)["state"] == "running"
    assert api.http.get("/healthz").json()["status"] == "ok"
    api.create("another", config=FAST)
    # the failed session refuses frames with a clear 409 ...
    r = api.post_frame(bad_sid, bad_token, scene.messages[1])
    assert r.status_code == 409 and "failed" in r.json()["detail"] and "resume" in r.json()["detail"]
    r = api.http.post(f"/sessions/{bad_sid}/finish", headers=api.auth(bad_token))
    assert r.status_code == 409
    listed = {s["id"]: s["state"] for s in api.http.get("/sessions").json()["sessions"]}
    assert listed[bad_sid] == "failed" and listed[good_sid] == "running"
    # ... and resumes from its recording without the frame the engine failed on (here the cause stays: every
    # later frame of this engine would fail too, so the patch is removed before new frames come)
    r = api.http.post(f"/sessions/{bad_sid}/resume", headers=api.auth(bad_token))
    assert r.status_code == 202 and r.json()["last_error"] is None
    wait_until(lambda: api.status(bad_sid, bad_token)["replay_pending"] == 0, 60, "the replay")
    status = api.status(bad_sid, bad_token)
    assert status["state"] == "running" and status["frames_tracked"] == 0 and status["frames_received"] == 1
    monkeypatch.setattr(SlamSystem, "_track", original)
    assert api.post_frame(bad_sid, bad_token, scene.messages[1]).status_code == 202
    wait_until(lambda: api.status(bad_sid, bad_token)["frames_tracked"] == 1, 60, "the resumed session")
    assert api.http.post(f"/sessions/{good_sid}/finish", headers=api.auth(good_token)).json()["state"] == "finished"
