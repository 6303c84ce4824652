"""``open_capture`` / ``detect_format``: layout detection, subsets, reader options, unknown layouts."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from voxfusion.core.datasets import (
    CAPTURE_FORMATS,
    Capture,
    ReplicaCapture,
    SevenScenesCapture,
    SlicedCapture,
    StrayCapture,
    TUMCapture,
    detect_format,
    open_capture,
)
from voxfusion.core.errors import CaptureError, CaptureFormatError, ValidationError


def test_real_captures_detected_and_opened(shared_data: Path):
    expected = {
        "tum_fr1_desk_9frames": ("tum", TUMCapture),
        "sevenscenes_redkitchen": ("sevenscenes", SevenScenesCapture),
        "stray_iphone_lidar": ("stray", StrayCapture),
    }
    for folder, (fmt, cls) in expected.items():
        assert detect_format(shared_data / folder) == fmt
        cap = open_capture(shared_data / folder)
        assert isinstance(cap, cls) and isinstance(cap, Capture)


def test_stride_limit_start_and_reader_options(shared_data: Path):
    root = shared_data / "tum_fr1_desk_9frames"
    full = open_capture(root)
    view = open_capture(root, start=1, stride=3, limit=2)
    assert isinstance(view, SlicedCapture) and len(view) == 2
    assert [f.timestamp_s for f in view] == [full[1].timestamp_s, full[4].timestamp_s]
    assert len(open_capture(root, limit=100)) == 9
    assert len(open_capture(root, limit=0)) == 0
    assert open_capture(root, intrinsics="fr2").K[0, 0] == pytest.approx(520.9)
    with pytest.raises(ValidationError, match="TUMCapture"):
        open_capture(root, no_such_option=1)
    with pytest.raises(ValidationError, match="stride"):
        open_capture(root, stride=0)
    with pytest.raises(ValidationError, match="format"):
        open_capture(root, format="kinect")


def test_marker_layouts_detected(tmp_path: Path):
    def mk(name: str, dirs: tuple[str, ...] = (), files: tuple[str, ...] = ()) -> Path:
        root = tmp_path / name
        root.mkdir()
        for d in dirs:
            (root / d).mkdir()
        for f in files:
            (root / f).write_text("")
        return root

    assert detect_format(mk("replica", ("results",), ("traj.txt",))) == "replica"
    assert detect_format(mk("scannet", ("color", "depth", "intrinsic", "pose"))) == "scannet"
    assert detect_format(mk("stray", ("depth",), ("odometry.csv",))) == "stray"
    assert detect_format(mk("tum", ("rgb", "depth"), ("rgb.txt", "depth.txt"))) == "tum"
    assert detect_format(mk("seven", (), ("frame-000010.pose.txt",))) == "sevenscenes"
    r3d_dir = mk("r3d", (), ("scan.r3d",))
    assert detect_format(r3d_dir / "scan.r3d") == "record3d"
    assert detect_format(r3d_dir) == "record3d"
    (r3d_dir / "other.r3d").write_text("")
    with pytest.raises(CaptureFormatError, match="Known layouts"):
        detect_format(r3d_dir)  # two .r3d files: which one?


def test_unknown_layout_lists_known_ones(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        open_capture(tmp_path / "missing")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hello")
    with pytest.raises(CaptureFormatError) as e:
        open_capture(tmp_path / "junk")
    for name in CAPTURE_FORMATS:
        assert name in str(e.value)
    (tmp_path / "file.bin").write_bytes(b"")
    with pytest.raises(CaptureFormatError, match="unrecognised"):
        detect_format(tmp_path / "file.bin")


def test_synthetic_replica_layout_opens_with_options(tmp_path: Path):
    root = tmp_path / "synthetic_room"
    (root / "results").mkdir(parents=True)
    for i in range(4):
        cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), np.full((12, 16), 6554, np.uint16))
        cv2.imwrite(str(root / "results" / f"frame{i:06d}.jpg"), np.zeros((12, 16, 3), np.uint8))
    np.savetxt(root / "traj.txt", np.tile(np.eye(4).reshape(1, 16), (4, 1)))
    cap = open_capture(root, K=(10.0, 10.0, 8.0, 6.0), stride=2)
    assert isinstance(cap.capture, ReplicaCapture) and len(cap) == 2
    assert cap[1].meta["source_index"] == 2 and cap[1].depth_m[0, 0] == pytest.approx(1.0, abs=1e-3)
    forced = open_capture(root, format="replica", K=(10.0, 10.0, 8.0, 6.0))
    assert len(forced) == 4
