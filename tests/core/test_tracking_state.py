"""A frame's tracking state (``normal`` / ``limited`` / ``lost``) and its cost ratio, from the engine to the wire."""

import numpy as np
import pytest

from voxfusion.clients.stream import format_pose
from voxfusion.core.datasets import open_capture
from voxfusion.core.errors import ConfigError
from voxfusion.core.slam import SlamSystem
from voxfusion.core.slam.presets import preset_for
from voxfusion.core.slam.system import FrameRecord, cost_ratio
from voxfusion.core.slam.tracking import COST_RATIO_MIN_HISTORY, TrackingConfig
from voxfusion.proto.schemas import PoseOut
from voxfusion.server.outputs import pose_out


def test_cost_ratio_needs_a_history_and_a_positive_median():
    assert COST_RATIO_MIN_HISTORY == 3
    assert cost_ratio(5.0, []) is None and cost_ratio(5.0, [1.0, 2.0]) is None
    assert cost_ratio(6.0, [1.0, 2.0, 3.0]) == pytest.approx(3.0)
    assert cost_ratio(6.0, [2.0, 2.0, 100.0, 2.0]) == pytest.approx(3.0)  # the median, not the mean
    assert cost_ratio(1.0, [0.0, 0.0, 0.0]) is None and cost_ratio(float("nan"), [1.0, 1.0, 1.0]) is None


def test_tracking_state_of_a_record_and_on_the_wire():
    eye = np.eye(4)
    assert FrameRecord(0, 0.0, eye).tracking_state == "normal"
    assert FrameRecord(1, 0.1, eye, limited=True, cost_ratio=4.2).tracking_state == "limited"
    assert FrameRecord(2, 0.2, eye, lost=True).tracking_state == "lost"
    out = pose_out(FrameRecord(1, 0.1, eye, limited=True, cost_ratio=4.2))
    assert out.tracking_state == "limited" and out.cost_ratio == pytest.approx(4.2) and not out.lost
    assert pose_out(FrameRecord(3, 0.3, eye, cost_ratio=float("inf"))).cost_ratio is None
    with pytest.raises(ValueError, match="tracking_state"):
        PoseOut(seq=0, timestamp_s=0.0, T_world_cam=eye.tolist(), tracking_state="degraded")
    with pytest.raises(ValueError, match="contradicts"):
        PoseOut(seq=0, timestamp_s=0.0, T_world_cam=eye.tolist(), lost=True, tracking_state="limited")
    with pytest.raises(ValueError, match="cost_ratio"):
        PoseOut(seq=0, timestamp_s=0.0, T_world_cam=eye.tolist(), cost_ratio=-1.0)
    # a pose saved before the state existed (a finished session's poses.json) has only `lost`: the state follows it
    old = {"seq": 5, "timestamp_s": 0.5, "T_world_cam": eye.tolist(), "tracking_loss": None, "lost": True,
           "is_keyframe": False}
    assert PoseOut.model_validate(old).tracking_state == "lost"
    assert PoseOut.model_validate({**old, "lost": False}).tracking_state == "normal"
    assert format_pose(out).endswith(" LIMITED") and format_pose(PoseOut.model_validate(old)).endswith(" LOST")
    assert not format_pose(pose_out(FrameRecord(0, 0.0, eye))).endswith(("LOST", "LIMITED"))
    with pytest.raises(ConfigError, match="limited_cost_factor"):
        TrackingConfig(limited_cost_factor=-1.0)
    with pytest.raises(ConfigError, match="retry_window"):
        TrackingConfig(retry_window=2)
    TrackingConfig(retry_window=2, limited_cost_factor=0.0)  # no ratio needed


def _run(shared_data, stride: int, frames: int, *overrides: str) -> SlamSystem:
    cap = open_capture(shared_data / "sevenscenes_redkitchen", stride=stride, limit=frames)
    slam = SlamSystem(preset_for(cap, overrides=["device=cpu", *overrides]).config)
    for f in cap.frames():
        slam.process(f)
    return slam


def test_frames_beyond_the_trackers_reach_are_limited_on_real_7scenes(shared_data):
    """7-Scenes redkitchen at every 16th frame (1.9 Hz): frame 4 (capture frame 64) starts 8.7 cm / 3.4 deg from
    the true pose and the solver settles 14 cm off without the frame being lost; its cost jumps to ~4.8 times the
    frames before it (measured: 4.76, seed 0), where no frame of any dev capture at its own rate went over 2.22
    (the synthetic room, fast rotation, TUM fr1 / fr3, 7-Scenes 0-499, both iPhone scans). So frame 4 is
    ``limited``; kept at its own rate, none of the same frames is."""
    slow = _run(shared_data, 16, 6)
    states = [r.tracking_state for r in slow.records]
    assert states[4] == "limited" and states[:4] == ["normal"] * 4, states
    assert slow.records[4].cost_ratio > 3.5 and slow.stats().frames_limited >= 1
    # frame 0 is placed, not tracked; frame 4 is the first with three tracked frames before it
    assert [r.cost_ratio is None for r in slow.records[:4]] == [True] * 4
    dt = np.linalg.norm(slow.records[4].T_tracked[:3, 3] - open_capture(
        shared_data / "sevenscenes_redkitchen")[64].T_world_cam[:3, 3])
    assert dt > 0.05, dt  # it is the wrong pose the state flags (the test is moot if tracking got it right)
    steady = _run(shared_data, 1, 12)
    assert all(r.tracking_state == "normal" for r in steady.records), [r.cost_ratio for r in steady.records]
    assert max(r.cost_ratio for r in steady.records[4:]) < 2.5 and steady.stats().frames_limited == 0
    off = _run(shared_data, 16, 6, "tracking.limited_cost_factor=0")
    assert off.stats().frames_limited == 0 and off.records[4].cost_ratio == pytest.approx(slow.records[4].cost_ratio)
