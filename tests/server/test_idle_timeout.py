"""Idle sessions (``session_idle_timeout_s``): a session that receives no frame for that long (also one that
never got any) is closed as a server shutdown closes it: map checkpointed, recording kept, state unchanged,
listed with ``resume_required`` and a ``last_error`` saying why; its slot is free, and it resumes on its next
frame or ``POST /resume`` (its recording replayed), or can be deleted. ``0`` disables it."""

from __future__ import annotations

import threading
import time

import pytest
from srvutil import FAST, make_scene, wait_until

from voxfusion.core.errors import ConfigError
from voxfusion.server import ServerSettings
from voxfusion.server.stored import CHECKPOINT_FILE, POSES_FILE


@pytest.fixture(scope="module")
def scene():
    return make_scene(4, seed=9)


def test_idle_sessions_are_closed_kept_on_disk_and_resume(server_factory, scene):
    srv = server_factory(session_idle_timeout_s=3.0, max_sessions=2, checkpoint_interval_s=600)
    api = srv.api
    idle_sid, idle_token = api.create("never-sent", config=FAST)
    sid, token = api.create("stopped-sending", config=FAST)
    for m in scene.messages[:2]:
        assert api.post_frame(sid, token, m).status_code == 202
    # frames keep a session open: resending (a duplicate) until its first frame is mapped, well past the timeout
    deadline = time.monotonic() + 120
    while api.status(sid, token)["frames_mapped"] < 1:
        assert time.monotonic() < deadline, "the first frame was never mapped"
        r = api.post_frame(sid, token, scene.messages[1])
        assert r.status_code == 202 and r.json()["duplicate"], r.text
        threading.Event().wait(0.3)
    assert api.status(sid, token)["resume_required"] is False

    # then both are closed: slots free, listed, state kept, the reason in last_error
    wait_until(lambda: api.http.get("/healthz").json()["sessions_open"] == 0, 30, "both sessions to be closed")
    listed = {s["id"]: s for s in api.http.get("/sessions").json()["sessions"]}
    for s_id, state in ((idle_sid, "created"), (sid, "running")):
        st = listed[s_id]
        assert st["state"] == state and st["resume_required"], st
        assert "without a frame" in st["last_error"] and "resume" in st["last_error"], st
    assert listed[sid]["frames_received"] == 2 and listed[idle_sid]["frames_received"] == 0
    folder = srv.settings.sessions_dir / sid
    # the map, as at shutdown: a session leaves the open set before its worker has written it (the close
    # checkpoints outside the manager's lock; resume and delete wait for it), so wait for the files
    wait_until(lambda: (folder / CHECKPOINT_FILE).is_file() and (folder / POSES_FILE).is_file(), 60,
               "the closed session's checkpoint and poses")
    poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
    assert len(poses) >= 1  # served from the checkpoint, like a session left open by a restart
    assert "sessions_idle_closed_total 2.0" in api.http.get("/metrics").text

    # the slots are really free: max_sessions=2 new sessions fit
    extra = [api.create(f"extra-{i}", config=FAST) for i in range(2)]
    assert api.http.post("/sessions", json={"config": FAST}).status_code == 503
    for e_sid, e_token in extra:
        assert api.http.delete(f"/sessions/{e_sid}", headers=api.auth(e_token)).status_code == 204

    # the next frame resumes the session (its recording replayed) and clears the reason
    r = api.post_frame(sid, token, scene.messages[2])
    assert r.status_code == 202 and not r.json()["duplicate"], r.text
    st = api.status(sid, token)
    assert st["state"] == "running" and not st["resume_required"] and st["last_error"] is None
    assert st["frames_received"] == 3
    wait_until(lambda: api.status(sid, token)["frames_tracked"] == 3, 120, "the replay and the new frame")
    # POST /resume reopens the created one; a created session never sent a frame is resumable too
    r = api.http.post(f"/sessions/{idle_sid}/resume", headers=api.auth(idle_token))
    assert r.status_code == 202 and r.json()["state"] == "created" and r.json()["last_error"] is None, r.text
    assert api.post_frame(idle_sid, idle_token, scene.messages[0]).status_code == 202
    assert api.status(idle_sid, idle_token)["state"] == "running"
    # finishing works after a resume
    done = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token))
    assert done.status_code == 200 and done.json()["state"] == "finished", done.text


def test_idle_created_session_can_be_deleted(server_factory):
    srv = server_factory(session_idle_timeout_s=0.5)
    api = srv.api
    sid, token = api.create("abandoned", config=FAST)
    wait_until(lambda: api.status(sid, token)["resume_required"], 30, "the created session to be closed")
    st = api.status(sid, token)
    assert st["state"] == "created" and "without a frame" in st["last_error"]
    assert api.http.get("/healthz").json()["sessions_open"] == 0
    assert api.http.delete(f"/sessions/{sid}", headers=api.auth(token)).status_code == 204
    assert not (srv.settings.sessions_dir / sid).exists()
    assert api.http.get(f"/sessions/{sid}", headers=api.auth(token)).status_code == 404


def test_busy_or_disabled_sessions_are_not_closed(server_factory, scene):
    """Driven through the server's own manager with a clock far in the future (no waiting)."""
    srv = server_factory(session_idle_timeout_s=600)
    api = srv.api
    manager = srv.manager
    sid, token = api.create("busy", config=FAST)
    late = time.monotonic() + 3600
    # a frame being ingested (or a finish in progress) pins the session
    pinned = manager._pin(sid)
    assert pinned is not None
    try:
        assert manager.close_idle_sessions(now=late) == []
    finally:
        manager._unpin(sid)
    assert api.status(sid, token)["resume_required"] is False
    assert manager.close_idle_sessions(now=late) == [sid]
    assert api.status(sid, token)["resume_required"] is True
    assert manager.close_idle_sessions(now=late) == []  # nothing left to close

    off = server_factory(session_idle_timeout_s=0, data_dir=srv.settings.data_dir.parent / "off")
    off_sid, off_token = off.api.create("kept", config=FAST)
    assert off.manager.close_idle_sessions(now=late) == []
    assert off.api.status(off_sid, off_token)["resume_required"] is False


def test_idle_timeout_setting_is_checked():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError) as info:
            ServerSettings(session_idle_timeout_s=bad)
        assert info.value.field == "session_idle_timeout_s"
    with pytest.raises(ConfigError):
        ServerSettings(max_sessions_per_client=-1)
    assert ServerSettings().session_idle_timeout_s == 600.0 and ServerSettings().max_sessions_per_client == 2
