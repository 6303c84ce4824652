"""Frames the engine cannot use never fail a session: implausible values are refused at the door (422),
frames without usable depth are tracked as lost and skipped, and the map starts with the first good frame
(also after a restart, when the recording is replayed)."""

from __future__ import annotations

import numpy as np
import pytest
from srvutil import TINY, make_scene, wait_until

from voxfusion.proto import encode_frame
from voxfusion.proto.container import pack_message, unpack_message


def _with_header(message: bytes, **changes) -> bytes:
    header, payloads = unpack_message(message)
    for key, value in changes.items():
        if isinstance(value, dict):
            header[key] = {**header.get(key, {}), **value}
        else:
            header[key] = value
    return pack_message(header, payloads)


@pytest.fixture(scope="module")
def scene():
    return make_scene(5, seed=21)


@pytest.mark.parametrize("mode", ["offline", "realtime"])
def test_bad_first_frames_never_fail_the_session(server_factory, scene, mode):
    srv = server_factory(checkpoint_interval_s=1.0)
    sid, token = srv.api.create(config=TINY, mode=mode)
    first = scene.capture[0]
    far = np.eye(4)
    far[:3, 3] = 1e12

    # Checked at the door: 422 naming the field, nothing recorded.
    refused = {
        "intrinsics": _with_header(scene.messages[0], intrinsics={"fx": 1e-6, "fy": 1e-6}),
        "device_pose": encode_frame(first.with_(T_world_cam_device=far), seq=0, depth_encoding="png16_mm",
                                    color_encoding="jpeg"),
    }
    for field, message in refused.items():
        r = srv.api.post_frame(sid, token, message)
        assert r.status_code == 422 and r.json()["field"] == field, r.text

    # Accepted (202) but unusable: tracked as lost and skipped.
    unusable = [first.with_(depth_m=np.zeros_like(first.depth_m)),       # pointed at the sky
                first.with_(depth_m=np.full_like(first.depth_m, 65.0)),  # all beyond range
                first.with_(depth_m=np.full_like(first.depth_m, 0.001))]  # all 1 mm
    seq = 0
    for frame in unusable:
        message = encode_frame(frame, seq=seq, depth_encoding="png16_mm", color_encoding="jpeg")
        assert srv.api.post_frame(sid, token, message).status_code == 202
        seq += 1
        wait_until(lambda s=seq: srv.api.status(sid, token)["frames_tracked"] + srv.api.status(sid, token)[
            "frames_dropped"] >= s, 120, "the unusable frame to be handled")
    for i in range(1, len(scene.messages)):
        message = _with_header(scene.messages[i], seq=seq)
        assert srv.api.post_frame(sid, token, message).status_code == 202
        seq += 1
        wait_until(lambda s=seq: srv.api.status(sid, token)["frames_tracked"] + srv.api.status(sid, token)[
            "frames_dropped"] >= s, 120, "the good frame to be tracked")
    st = srv.api.status(sid, token)
    assert st["state"] == "running" and st["last_error"] is None, st
    assert st["frames_lost"] >= len(unusable) - st["frames_dropped"]
    poses = srv.api.http.get(f"/sessions/{sid}/poses", headers=srv.api.auth(token)).json()["poses"]
    good = [p for p in poses if p["seq"] >= len(unusable)]
    assert good and not any(p["lost"] for p in good)
    assert srv.api.http.get(f"/sessions/{sid}/mesh", headers=srv.api.auth(token)).status_code == 200

    # A restart replays the recording (bad frames included) through a new engine: the session resumes.
    srv.stop()
    srv2 = server_factory(data_dir=srv.settings.data_dir)
    r = srv2.api.http.post(f"/sessions/{sid}/resume", headers=srv2.api.auth(token))
    assert r.status_code == 202, r.text
    wait_until(lambda: srv2.api.status(sid, token)["replay_pending"] == 0, 180, "the replay")
    st = srv2.api.status(sid, token)
    assert st["state"] == "running" and st["last_error"] is None, st
    r = srv2.api.http.post(f"/sessions/{sid}/finish", headers=srv2.api.auth(token))
    assert r.status_code == 200 and r.json()["state"] == "finished", r.text


@pytest.mark.parametrize("mode", ["offline", "realtime"])
def test_a_session_of_only_unusable_frames_finishes_cleanly(server_factory, scene, mode):
    srv = server_factory()
    sid, token = srv.api.create(config=TINY, mode=mode)
    empty = scene.capture[0].with_(depth_m=np.zeros_like(scene.capture[0].depth_m))
    for seq in range(3):
        message = encode_frame(empty, seq=seq, depth_encoding="png16_mm", color_encoding="jpeg")
        assert srv.api.post_frame(sid, token, message).status_code == 202
    r = srv.api.http.post(f"/sessions/{sid}/finish", headers=srv.api.auth(token))
    assert r.status_code == 200 and r.json()["state"] == "finished", r.text
    assert srv.api.http.get(f"/sessions/{sid}/mesh", headers=srv.api.auth(token)).status_code == 409
