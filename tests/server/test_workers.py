"""Session workers in their own processes: a killed worker restarts by itself and loses nothing acknowledged,
the other sessions never notice, restarts are bounded, and no worker outlives its server."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
from srvutil import FAST, TINY, ServerProcess, make_scene, wait_until

from voxfusion.core.eval import TrajectoryEvalConfig, compute_ate
from voxfusion.core.trajectory import Trajectory
from voxfusion.proto.recording import RecordingCapture


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped) is not alive
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_each_session_has_its_own_worker_process(server_factory):
    srv = server_factory()
    api = srv.api
    (a, ta), (b, tb) = api.create("a", config=FAST), api.create("b", config=FAST)
    pa, pb = api.status(a, ta)["worker_pid"], api.status(b, tb)["worker_pid"]
    assert pa and pb and len({pa, pb, os.getpid()}) == 3 and _alive(pa) and _alive(pb)
    assert api.http.delete(f"/sessions/{a}", headers=api.auth(ta)).status_code == 204
    wait_until(lambda: not _alive(pa), 30, "the deleted session's worker to exit")
    assert _alive(pb)


def test_killed_worker_restarts_and_loses_nothing(server_factory):
    n = 8
    srv = server_factory()
    api = srv.api
    scenes = [make_scene(n, seed=21), make_scene(n, seed=22)]
    (vic, vt), (other, ot) = (api.create(name, config=TINY, mode="offline") for name in ("victim", "other"))
    for k in range(n // 2):
        assert api.post_frame(vic, vt, scenes[0].messages[k]).status_code == 202
        assert api.post_frame(other, ot, scenes[1].messages[k]).status_code == 202
    wait_until(lambda: api.status(vic, vt)["frames_tracked"] >= 2, 120, "the victim to track frames")
    pid = api.status(vic, vt)["worker_pid"]
    other_pid = api.status(other, ot)["worker_pid"]
    os.kill(pid, signal.SIGKILL)
    # frames keep being acknowledged while the worker is dead and restarting
    for k in range(n // 2, n):
        assert api.post_frame(vic, vt, scenes[0].messages[k]).status_code == 202
        assert api.post_frame(other, ot, scenes[1].messages[k]).status_code == 202
    st = wait_until(lambda: (s := api.status(vic, vt))["worker_restarts"] == 1 and s["frames_tracked"] == n and s,
                    180, "the victim's new worker to replay and track every frame")
    assert st["state"] == "running" and st["worker_pid"] not in (pid, None) and st["frames_received"] == n
    assert not _alive(pid)
    o = wait_until(lambda: (s := api.status(other, ot))["frames_tracked"] == n and s, 180, "the other session")
    assert o["worker_restarts"] == 0 and o["worker_pid"] == other_pid and o["state"] == "running"
    for k, (sid, token) in enumerate(((vic, vt), (other, ot))):
        assert len(RecordingCapture(srv.settings.sessions_dir / sid)) == n  # every acknowledged frame
        done = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token))
        assert done.status_code == 200 and done.json()["state"] == "finished", done.text
        poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
        est = Trajectory(np.array([p["timestamp_s"] for p in poses]), np.array([p["T_world_cam"] for p in poses]))
        ate = compute_ate(est, scenes[k].gt, TrajectoryEvalConfig(align="se3", max_diff_s=1e-3))
        assert ate.n == n and ate.rmse_m < 0.05, (sid, ate.rmse_m)  # one trajectory per frame, each right


def test_worker_restarts_are_bounded(server_factory):
    srv = server_factory(worker_restarts=1)
    api = srv.api
    scene = make_scene(2, seed=23)
    sid, token = api.create("crashy", config=FAST)
    assert api.post_frame(sid, token, scene.messages[0]).status_code == 202
    pid = api.status(sid, token)["worker_pid"]
    os.kill(pid, signal.SIGKILL)
    st = wait_until(lambda: (s := api.status(sid, token))["worker_pid"] not in (None, pid) and s, 60, "a new worker")
    assert st["worker_restarts"] == 1 and st["state"] == "running"
    os.kill(st["worker_pid"], signal.SIGKILL)
    st = wait_until(lambda: (s := api.status(sid, token))["state"] == "failed" and s, 60, "the session to fail")
    assert "died 2 times" in st["last_error"] and "--worker-restarts" in st["last_error"]
    r = api.post_frame(sid, token, scene.messages[1])
    assert r.status_code == 409 and "resume" in r.json()["detail"]
    # resume starts a fresh worker with a fresh allowance
    assert api.http.post(f"/sessions/{sid}/resume", headers=api.auth(token)).status_code == 202
    st = wait_until(lambda: (s := api.status(sid, token))["frames_tracked"] == 1 and s, 60, "the resumed session")
    assert st["state"] == "running" and st["worker_restarts"] == 0 and _alive(st["worker_pid"])


def test_no_worker_outlives_a_killed_server(tmp_path):
    scene = make_scene(2, seed=24)
    srv = ServerProcess(tmp_path / "data")
    try:
        from srvutil import Api

        api = Api(srv.url)
        sid, token = api.create("orphan?", config=FAST)
        assert api.post_frame(sid, token, scene.messages[0]).status_code == 202
        pid = api.status(sid, token)["worker_pid"]
        assert pid and _alive(pid)
        api.close()
    finally:
        srv.kill()  # SIGKILL: the server cannot tell its workers anything
    deadline = time.monotonic() + 30
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(pid), "the worker of a killed server kept running"
