"""Stray Scanner reader: the real depth-only iPhone capture, and a small fixture with an ``rgb.mp4``."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from voxfusion.core.datasets import StrayCapture
from voxfusion.core.errors import CaptureError, CaptureFormatError, ValidationError
from voxfusion.core.geometry import GL_TO_CV, pose_from_tum

# BGR colours written to the fixture video, one per frame.
VIDEO_BGR = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (0, 255, 255), (128, 128, 128)]


@pytest.fixture(scope="module")
def stray_real(shared_data) -> StrayCapture:
    return StrayCapture(shared_data / "stray_iphone_lidar")


def test_real_capture_values(stray_real: StrayCapture, shared_data: Path):
    root = shared_data / "stray_iphone_lidar"
    assert len(stray_real) == 942
    K_color = np.loadtxt(root / "camera_matrix.csv", delimiter=",")
    expected = K_color.copy()
    expected[:2] *= 256 / 1920
    np.testing.assert_allclose(stray_real.K, expected)
    f = stray_real[5]
    assert f.depth_m.shape == (192, 256) and f.color is None and f.confidence is not None
    raw = cv2.imread(str(root / "depth" / "000005.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
    conf = cv2.imread(str(root / "confidence" / "000005.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(f.confidence, conf)
    np.testing.assert_allclose(f.depth_m, np.where(conf >= 1, raw, 0.0))  # default threshold 1
    np.testing.assert_allclose(StrayCapture(root, confidence_threshold=None)[5].depth_m, raw)
    assert (StrayCapture(root, confidence_threshold=2)[5].depth_m > 0).sum() == (conf == 2).sum()
    row = np.loadtxt(root / "odometry.csv", delimiter=",", skiprows=1)[5]
    assert f.timestamp_s == pytest.approx(row[0])
    np.testing.assert_allclose(f.T_world_cam, pose_from_tum(row[2:5], row[5:9]), atol=1e-6)
    np.testing.assert_array_equal(f.T_world_cam, f.T_world_cam_device)


def test_real_poses_are_opencv_axes(stray_real: StrayCapture, reprojection_error):
    a, b = stray_real[300], stray_real[330]
    err = reprojection_error(a.depth_m, a.K, a.T_world_cam, b.depth_m, b.K, b.T_world_cam, stride=2)
    err_identity = reprojection_error(a.depth_m, a.K, np.eye(4), b.depth_m, b.K, np.eye(4), stride=2)
    err_gl = reprojection_error(
        a.depth_m, a.K, a.T_world_cam @ GL_TO_CV, b.depth_m, b.K, b.T_world_cam @ GL_TO_CV, stride=2
    )
    assert err < 0.08  # data README: 4-6 cm for this capture with poses as-is
    assert err_identity > 2 * err
    assert err_gl > 2 * err  # an extra OpenGL->OpenCV flip would be wrong


def _write_stray(root: Path, n: int = 6, video: bool = True, npy: bool = False) -> Path:
    """Depth 32x24, colour video 64x48 (K given for 64x48: fx 50, cx 32, cy 24)."""
    (root / "depth").mkdir(parents=True)
    (root / "confidence").mkdir()
    lines = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    for i in range(n):
        d = np.full((24, 32), 1000 + 100 * i, np.uint16)
        if npy:
            np.save(root / "depth" / f"{i:06d}.npy", d)
        else:
            cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), d)
        c = np.full((24, 32), 2, np.uint8)
        c[:, :8] = 0
        cv2.imwrite(str(root / "confidence" / f"{i:06d}.png"), c)
        lines.append(f"{100.0 + i / 60:.6f}, {i:06d}, {0.1 * i}, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0")
    (root / "odometry.csv").write_text("\n".join(lines) + "\n")
    (root / "camera_matrix.csv").write_text("50.0, 0.0, 32.0\n0.0, 50.0, 24.0\n0.0, 0.0, 1.0")
    if video:
        writer = cv2.VideoWriter(str(root / "rgb.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 60, (64, 48))
        assert writer.isOpened()
        for i in range(n):
            writer.write(np.full((48, 64, 3), VIDEO_BGR[i % len(VIDEO_BGR)], np.uint8))
        writer.release()
    return root


def test_video_colour_random_access_and_intrinsics_from_video_size(tmp_path: Path):
    cap = StrayCapture(_write_stray(tmp_path / "scan"))
    assert cap.color_size == (64, 48)
    np.testing.assert_allclose(cap.K, [[25, 0, 16], [0, 25, 12], [0, 0, 1]])
    for i in (0, 1, 2, 5, 3, 0, 4):  # in order, forward jump, backward seeks
        f = cap[i]
        assert f.color.shape == (24, 32, 3)
        expected_rgb = np.array(VIDEO_BGR[i][::-1])
        assert np.abs(f.color[12, 16].astype(int) - expected_rgb).max() < 12, i
    f = cap[2]
    assert f.depth_m[0, 0] == 0.0 and f.depth_m[0, 20] == pytest.approx(1.2)  # conf 0 filtered
    assert f.timestamp_s == pytest.approx(100 + 2 / 60)
    np.testing.assert_allclose(f.T_world_cam_device[:3, 3], [0.2, 0, 0])


def test_depth_only_and_npy_depth(tmp_path: Path):
    cap = StrayCapture(_write_stray(tmp_path / "scan", n=2, video=False, npy=True), confidence_threshold=None)
    f = cap[1]
    assert f.color is None and f.depth_m.dtype == np.float32
    assert f.depth_m[0, 0] == pytest.approx(1.1)
    np.testing.assert_allclose(cap.K[0, 0], 50 * 32 / 1920)  # colour size defaults to 1920x1440


def test_video_shorter_than_odometry(tmp_path: Path):
    root = _write_stray(tmp_path / "scan", n=3)
    lines = (root / "odometry.csv").read_text().splitlines()
    lines.append("101.0, 000003, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0")
    (root / "odometry.csv").write_text("\n".join(lines) + "\n")
    cv2.imwrite(str(root / "depth" / "000003.png"), np.full((24, 32), 1000, np.uint16))
    cap = StrayCapture(root)
    assert cap[2].color is not None
    with pytest.raises(CaptureError, match="frame 3") as e:
        cap[3]
    assert e.value.path.name == "rgb.mp4"


def test_bad_captures(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        StrayCapture(tmp_path / "missing")
    root = _write_stray(tmp_path / "scan", n=2, video=False)
    with pytest.raises(ValidationError, match="confidence_threshold"):
        StrayCapture(root, confidence_threshold=5)
    (root / "camera_matrix.csv").write_text("50.0, 0.0, 3200.0\n0.0, 50.0, 24.0\n0.0, 0.0, 1.0")
    with pytest.raises(CaptureFormatError, match="principal point") as e:
        StrayCapture(root)
    assert e.value.path.name == "camera_matrix.csv"
    (root / "camera_matrix.csv").write_text("50.0, 0.0, 32.0\n0.0, 50.0, 24.0\n0.0, 0.0, 1.0")
    cap = StrayCapture(root)
    cv2.imwrite(str(root / "confidence" / "000001.png"), np.full((24, 32), 255, np.uint8))
    with pytest.raises(CaptureFormatError, match="0/1/2"):
        cap[1]
    (root / "depth" / "000000.png").unlink()
    with pytest.raises(CaptureError, match="depth image not found"):
        cap[0]
    (root / "odometry.csv").write_text("timestamp, frame, x, y, z\n1.0, 0, 0, 0, 0\n")
    with pytest.raises(CaptureFormatError, match="qx"):
        StrayCapture(root)
    (root / "odometry.csv").unlink()
    with pytest.raises(CaptureFormatError, match="odometry.csv"):
        StrayCapture(root)


def test_capture_with_video_pickles(tmp_path: Path):
    cap = StrayCapture(_write_stray(tmp_path / "scan", n=3))
    first = cap[1].color
    clone = pickle.loads(pickle.dumps(cap))
    np.testing.assert_array_equal(clone[1].color, first)
    np.testing.assert_array_equal(clone[0].depth_m, cap[0].depth_m)


@pytest.mark.parametrize("video", [True, False])
def test_profile_lidar_with_confidence_and_colour_only_with_the_video(tmp_path: Path, video: bool):
    p = StrayCapture(_write_stray(tmp_path / "scan", n=2, video=video)).profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.has_color) == ("iphone", 5.0, True, video)
