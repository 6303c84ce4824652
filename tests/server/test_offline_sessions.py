"""An ``offline`` session runs the engine's offline mode: each frame is tracked and mapped before the next, so the
same frames give the same poses every time, and the poses ``SlamSystem.process`` gives on those frames."""

from __future__ import annotations

import numpy as np
import torch
from srvutil import TINY, make_scene

from voxfusion.core.config import config_from_dict
from voxfusion.core.slam import SlamSystem
from voxfusion.core.slam.presets import VoxFusionConfig
from voxfusion.proto import decode_frame

N_FRAMES = 6


def _finished_poses(api, sid: str, token: str) -> np.ndarray:
    """``[N, 4, 4]`` poses of a finished session (with the final keyframe refinements)."""
    r = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token))
    assert r.status_code == 200 and r.json()["state"] == "finished", r.text
    poses = api.http.get(f"/sessions/{sid}/poses", headers=api.auth(token)).json()["poses"]
    return np.array([p["T_world_cam"] for p in poses])


def test_offline_sessions_are_reproducible_and_match_the_engine_offline(server_factory):
    srv = server_factory()  # worker processes, the server's default
    api = srv.api
    scene = make_scene(N_FRAMES, seed=13)
    sessions = [api.create(f"again-{k}", mode="offline", config=TINY) for k in range(2)]
    for sid, token in sessions:
        assert [api.post_frame(sid, token, m).status_code for m in scene.messages] == [202] * N_FRAMES
    first, second = (_finished_poses(api, sid, token) for sid, token in sessions)
    assert first.shape == (N_FRAMES, 4, 4)
    np.testing.assert_array_equal(first, second)  # the same recording, the same trajectory

    # the engine's offline mode in this process, on the frames as the server decoded them, with the session's
    # configuration and the worker's torch thread count (threads change the rounding of parallel reductions)
    config = config_from_dict(VoxFusionConfig, srv.manager.get(sessions[0][0]).config)
    assert config.mode == "offline"
    threads = torch.get_num_threads()
    torch.set_num_threads(srv.settings.torch_threads_per_worker())
    try:
        slam = SlamSystem(config)
        for message in scene.messages:
            slam.process(decode_frame(message).frame)
        slam.finish()
    finally:
        torch.set_num_threads(threads)
    expected = slam.trajectory().T_world_cam
    torch.testing.assert_close(torch.from_numpy(first), torch.from_numpy(expected), atol=1e-6, rtol=0)


def test_sessions_on_threads_of_one_process_leave_torchs_thread_count_alone(server_factory, monkeypatch):
    """Engines sharing the API process (``--session-workers thread``) never change torch's process-wide thread
    count (an offline tracker's ``cpu_threads``, a realtime engine's ``realtime_cpu_threads``): one session
    would otherwise reset it under another's feet."""
    srv = server_factory(session_workers="thread")
    api = srv.api
    scene = make_scene(4, seed=14)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)  # a count both engines would otherwise change
    calls: list[int] = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)
    for mode in ("offline", "realtime"):
        sid, token = api.create(mode, mode=mode, config=TINY)
        assert [api.post_frame(sid, token, m).status_code for m in scene.messages] == [202] * 4
        r = api.http.post(f"/sessions/{sid}/finish", headers=api.auth(token))
        assert r.status_code == 200 and r.json()["frames_tracked"] >= 1, r.text
    assert calls == []
