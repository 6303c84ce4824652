"""7-Scenes reader: real redkitchen frames (values, poses, reprojection) and bad-input handling."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from voxfusion.core.datasets import SevenScenesCapture
from voxfusion.core.errors import CaptureError, CaptureFormatError
from voxfusion.core.geometry import make_intrinsics


def _write_7scenes(root: Path, n: int = 2, size: tuple[int, int] = (640, 480)) -> Path:
    root.mkdir(parents=True)
    w, h = size
    for i in range(n):
        d = np.full((h, w), 1500, np.uint16)
        d[0, :4] = [0, 65535, 1000, 2000]
        cv2.imwrite(str(root / f"frame-{i:06d}.depth.png"), d)
        cv2.imwrite(str(root / f"frame-{i:06d}.color.png"), np.full((h, w, 3), (0, 100, 200), np.uint8))
        T = np.eye(4)
        T[:3, 3] = [0.1 * i, 0.0, 0.0]
        np.savetxt(root / f"frame-{i:06d}.pose.txt", T)
    return root


@pytest.fixture(scope="module")
def kitchen(shared_data) -> SevenScenesCapture:
    return SevenScenesCapture(shared_data / "sevenscenes_redkitchen")


def test_real_frame_values(kitchen: SevenScenesCapture, shared_data: Path):
    root = shared_data / "sevenscenes_redkitchen"
    assert len(kitchen) == 500
    np.testing.assert_allclose(kitchen.K, make_intrinsics(585, 585, 320, 240))
    f = kitchen[7]
    raw = cv2.imread(str(root / "frame-000007.depth.png"), cv2.IMREAD_UNCHANGED)
    expected = raw.astype(np.float32) / 1000.0
    expected[raw == 65535] = 0.0
    np.testing.assert_allclose(f.depth_m, expected)
    np.testing.assert_array_equal(f.color, cv2.imread(str(root / "frame-000007.color.jpg"))[..., ::-1])
    np.testing.assert_allclose(f.T_world_cam, np.loadtxt(root / "frame-000007.pose.txt"), atol=1e-6)
    assert f.timestamp_s == pytest.approx(7 / 30) and f.index == 7 and f.T_world_cam_device is None
    assert kitchen[-1].meta["frame_id"] == 499


def test_real_poses_reproject_depth(kitchen: SevenScenesCapture, reprojection_error):
    a, b = kitchen[0], kitchen[40]
    err = reprojection_error(a.depth_m, a.K, a.T_world_cam, b.depth_m, b.K, b.T_world_cam)
    err_identity = reprojection_error(a.depth_m, a.K, np.eye(4), b.depth_m, b.K, np.eye(4))
    assert err < 0.03  # data README: 0.7-3 cm
    assert err_identity > 2 * err and err_identity > 0.05


def test_synthetic_invalid_values_and_default_intrinsics(tmp_path: Path):
    cap = SevenScenesCapture(_write_7scenes(tmp_path / "seq-01"))
    assert cap.name == f"{tmp_path.name}-seq-01"  # scene-sequence
    f = cap[1]
    np.testing.assert_allclose(f.depth_m[0, :4], [0.0, 0.0, 1.0, 2.0])  # 0 and 65535 are invalid
    assert f.depth_m[5, 5] == pytest.approx(1.5)
    assert tuple(f.color[1, 1]) == (200, 100, 0)
    np.testing.assert_allclose(f.T_world_cam[:3, 3], [0.1, 0.0, 0.0])
    np.testing.assert_allclose(cap.K, make_intrinsics(585, 585, 320, 240))


def test_intrinsics_file_three_by_three_or_four_numbers(tmp_path: Path):
    root = _write_7scenes(tmp_path / "seq", n=1)
    (root / "camera-intrinsics.txt").write_text("500 0 321\n0 501 239\n0 0 1\n")
    np.testing.assert_allclose(SevenScenesCapture(root).K, make_intrinsics(500, 501, 321, 239))
    (root / "camera-intrinsics.txt").write_text("400 402 300 200\n")
    np.testing.assert_allclose(SevenScenesCapture(root)[0].K, make_intrinsics(400, 402, 300, 200))
    (root / "camera-intrinsics.txt").write_text("400 402 3000 200\n")
    with pytest.raises(CaptureFormatError, match="principal point") as e:
        SevenScenesCapture(root)
    assert e.value.path.name == "camera-intrinsics.txt"
    (root / "camera-intrinsics.txt").write_text("400 402 300\n")
    with pytest.raises(CaptureFormatError, match="fx fy cx cy"):
        SevenScenesCapture(root)


def test_bad_layout_and_files(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        SevenScenesCapture(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureFormatError, match="frame-XXXXXX.depth.png"):
        SevenScenesCapture(tmp_path / "empty")
    root = _write_7scenes(tmp_path / "seq", n=4)
    cap = SevenScenesCapture(root)
    (root / "frame-000000.pose.txt").unlink()
    with pytest.raises(CaptureError, match="pose not found"):
        cap[0]
    np.savetxt(root / "frame-000001.pose.txt", 2 * np.eye(4))
    with pytest.raises(CaptureFormatError, match="rigid") as e:
        cap[1]
    assert e.value.path.name == "frame-000001.pose.txt"
    cv2.imwrite(str(root / "frame-000002.color.png"), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(CaptureFormatError, match="must match") as e:
        cap[2]
    assert e.value.path.name == "frame-000002.color.png"
    (root / "frame-000003.color.png").unlink()
    with pytest.raises(CaptureError, match="colour image not found"):
        cap[3]


def test_non_finite_pose_gives_none(tmp_path: Path):
    root = _write_7scenes(tmp_path / "seq", n=1)
    np.savetxt(root / "frame-000000.pose.txt", np.full((4, 4), -np.inf))
    assert SevenScenesCapture(root)[0].T_world_cam is None


def test_profile_says_colour_is_not_registered(tmp_path: Path):
    p = SevenScenesCapture(_write_7scenes(tmp_path / "seq-01", n=1)).profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.color_registered) == ("sevenscenes", 4.0, False, False)
