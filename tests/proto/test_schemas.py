"""The JSON API models: valid bodies parse, bad ones are refused with the field named."""

from __future__ import annotations

import json
from datetime import UTC, datetime

import numpy as np
import pytest
from pydantic import ValidationError as PydanticValidationError

from voxfusion.core.geometry import opengl_to_opencv
from voxfusion.proto.schemas import (
    ErrorOut,
    FrameAccepted,
    PoseOut,
    RenderRequest,
    SessionCreate,
    SessionMode,
    SessionState,
    SessionStatus,
    Trajectory,
)

T_GL = [[0.0, -1.0, 0.0, 0.5], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 1.5], [0.0, 0.0, 0.0, 1.0]]


def _render(**changes):
    body = {"T_world_cam": T_GL, "convention": "arkit", "intrinsics": {"fx": 200.0, "fy": 200.0, "cx": 127.5,
                                                                        "cy": 95.5}, "width": 256, "height": 192}
    body.update(changes)
    return body


def _loc(body, model=RenderRequest, as_json=False):
    with pytest.raises(PydanticValidationError) as info:
        model.model_validate_json(body) if as_json else model.model_validate(body)
    return info.value.errors()[0]["loc"]


def test_render_request_converts_arkit_pose_and_builds_K():
    req = RenderRequest.model_validate(_render())
    np.testing.assert_allclose(req.T_world_cam_cv(), opengl_to_opencv(np.array(T_GL)))
    np.testing.assert_allclose(req.K(), [[200, 0, 127.5], [0, 200, 95.5], [0, 0, 1]])
    assert req.format == "f16" and req.with_color is False
    flat = RenderRequest.model_validate(_render(T_world_cam=sum(T_GL, []), convention="opencv"))
    np.testing.assert_allclose(flat.T_world_cam_cv(), T_GL)  # 16 numbers are read row-major


@pytest.mark.parametrize("changes,loc", [
    ({"T_world_cam": [[2.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 2.0, 0], [0, 0, 0, 1]]}, ("T_world_cam",)),
    ({"T_world_cam": [1.0] * 15}, ("T_world_cam",)),
    ({"T_world_cam": "eye"}, ("T_world_cam",)),
    ({"convention": "unity"}, ("convention",)),
    ({"width": 0}, ("width",)),
    ({"height": 100000}, ("height",)),
    ({"format": "exr"}, ("format",)),
    ({"intrinsics": {"fx": -1.0, "fy": 200.0, "cx": 1.0, "cy": 1.0}}, ("intrinsics", "fx")),
    ({"intrinsics": {"fx": 200.0, "fy": 200.0, "cx": 900.0, "cy": 1.0}}, ("intrinsics",)),
    ({"unexpected": 1}, ("unexpected",)),
])
def test_render_request_refusals_name_the_field(changes, loc):
    assert _loc(_render(**changes)) == loc


def test_non_finite_numbers_are_refused_with_their_field():
    body = json.dumps(_render()).replace('"fx": 200.0', '"fx": NaN')
    assert _loc(body, as_json=True) == ("intrinsics", "fx")
    body = json.dumps(_render()).replace("1.5]", "Infinity]")
    assert _loc(body, as_json=True) == ("T_world_cam",)
    pose = {"seq": 1, "timestamp_s": float("inf"), "T_world_cam": np.eye(4).tolist()}
    assert _loc(pose, PoseOut) == ("timestamp_s",)
    assert _loc({"seq": 1, "timestamp_s": 0.0, "T_world_cam": np.eye(4).tolist(), "tracking_loss": float("nan")},
                PoseOut) == ("tracking_loss",)


def test_session_create_defaults_and_preset_is_a_name_not_a_path():
    s = SessionCreate.model_validate({})
    assert s.mode is SessionMode.realtime and s.name is None and s.config is None and s.preset is None
    s = SessionCreate.model_validate({"name": "desk", "preset": "iphone", "mode": "offline",
                                      "config": {"mapping": {"iters": 5}}})
    assert s.mode is SessionMode.offline and s.config == {"mapping": {"iters": 5}}
    for bad in ("../etc/passwd", "x.yaml", "/tmp/a", "UPPER"):
        assert _loc({"preset": bad}, SessionCreate) == ("preset",)
    assert _loc({"mode": "batch"}, SessionCreate) == ("mode",)


def test_status_pose_trajectory_error_serialise_to_json():
    status = SessionStatus(id="a1", state=SessionState.running, created_at=datetime(2025, 1, 2, tzinfo=UTC),
                           frames_received=10, frames_tracked=9, latency_ms=12.5, fps=29.9)
    out = json.loads(status.model_dump_json())
    assert out["state"] == "running" and out["created_at"].startswith("2025-01-02T00:00:00")
    assert out["frames_dropped"] == 0 and out["last_error"] is None and out["map_version"] == 0
    assert _loc({"id": "a", "state": "running", "created_at": "2025-01-01T00:00:00Z", "frames_received": -1},
                SessionStatus) == ("frames_received",)
    assert _loc({"id": "a", "state": "paused", "created_at": "2025-01-01T00:00:00Z"}, SessionStatus) == ("state",)
    pose = PoseOut(seq=3, timestamp_s=0.1, T_world_cam=np.eye(4).tolist(), tracking_loss=0.02)
    traj = Trajectory(session="a1", poses=[pose])
    assert json.loads(traj.model_dump_json())["poses"][0]["convention"] == "opencv"
    assert _loc({"seq": 0, "timestamp_s": 0.0, "T_world_cam": np.diag([1.0, 1, 1, 2]).tolist()}, PoseOut) == (
        "T_world_cam",)
    assert FrameAccepted(seq=4, session="a1").model_dump() == {"seq": 4, "session": "a1", "duplicate": None,
                                                               "action": None}
    assert FrameAccepted(seq=4, session="a1", duplicate=True, action="ignored").duplicate is True
    assert _loc({"seq": 4, "session": "a", "action": "re-recorded"}, FrameAccepted) == ("action",)
    assert _loc({"seq": -1, "session": "a"}, FrameAccepted) == ("seq",)
    assert ErrorOut(detail="crc: mismatch", field="crc").model_dump() == {"detail": "crc: mismatch", "field": "crc"}
