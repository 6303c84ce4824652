"""ScanNet ``.sens`` export reader on a small fixture in the exact SensReader layout."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from voxfusion.core.datasets import ScanNetCapture
from voxfusion.core.errors import CaptureError, CaptureFormatError
from voxfusion.core.geometry import make_intrinsics

DEPTH_WH = (40, 30)
COLOR_WH = (80, 60)
IDS = (0, 2, 10)  # numeric order, not lexicographic ("10" < "2")


def _write_scannet(root: Path) -> Path:
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k, fid in enumerate(IDS):
        color = rng.integers(0, 255, (COLOR_WH[1], COLOR_WH[0], 3), dtype=np.uint8)
        cv2.imwrite(str(root / "color" / f"{fid}.jpg"), color, [cv2.IMWRITE_JPEG_QUALITY, 100])
        cv2.imwrite(str(root / "depth" / f"{fid}.png"), np.full(DEPTH_WH[::-1], 1000 * (k + 1), np.uint16))
        T = np.eye(4)
        T[:3, 3] = [k, 0.0, 0.0]
        np.savetxt(root / "pose" / f"{fid}.txt", T)
    np.savetxt(root / "pose" / "10.txt", np.full((4, 4), -np.inf))  # tracking failure, as in ScanNet
    K4 = np.eye(4)
    K4[:3, :3] = make_intrinsics(35.0, 36.0, 19.5, 14.5)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K4)
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", K4 * 2)
    return root


def test_frames_in_numeric_order_with_resized_colour_and_poses(tmp_path: Path):
    root = _write_scannet(tmp_path / "scene0000_00")
    (root / "scene0000_00_vh_clean_2.ply").write_text("ply\n")
    cap = ScanNetCapture(root)
    assert len(cap) == 3 and cap.name == "scene0000_00"
    assert [f.meta["frame_id"] for f in cap.frames()] == list(IDS)
    np.testing.assert_allclose(cap.K, make_intrinsics(35.0, 36.0, 19.5, 14.5))  # top-left 3x3 of the 4x4
    f = cap[1]
    assert f.depth_m.shape == (30, 40) and f.depth_m[0, 0] == pytest.approx(2.0)
    decoded = cv2.imread(str(root / "color" / "2.jpg"))[..., ::-1]
    np.testing.assert_array_equal(f.color, cv2.resize(decoded, DEPTH_WH, interpolation=cv2.INTER_AREA))
    np.testing.assert_allclose(f.T_world_cam[:3, 3], [1.0, 0.0, 0.0])
    assert f.timestamp_s == pytest.approx(2 / 30)
    assert cap[2].T_world_cam is None  # -inf pose
    assert cap.gt_mesh_path == root / "scene0000_00_vh_clean_2.ply"


def test_bad_exports(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        ScanNetCapture(tmp_path / "missing")
    root = _write_scannet(tmp_path / "scene")
    (root / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(CaptureFormatError, match="intrinsic_depth.txt"):
        ScanNetCapture(root)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", np.eye(4) * 500)
    with pytest.raises(CaptureFormatError, match="pinhole"):
        ScanNetCapture(root)  # last row of the 3x3 is not [0, 0, 1]
    K4 = np.eye(4)
    K4[:3, :3] = make_intrinsics(577.6, 578.7, 318.9, 242.7)  # for 640x480, not 40x30
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K4)
    with pytest.raises(CaptureFormatError, match="principal point"):
        ScanNetCapture(root)
    K4[:3, :3] = make_intrinsics(35.0, 36.0, 19.5, 14.5)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K4)
    cap = ScanNetCapture(root)
    (root / "color" / "0.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(CaptureError, match="corrupt") as e:
        cap[0]
    assert e.value.path == root / "color" / "0.jpg"
    cv2.imwrite(str(root / "depth" / "2.png"), np.zeros((15, 20), np.uint16))
    with pytest.raises(CaptureFormatError, match="20x15") as e:
        cap[1]
    assert e.value.path == root / "depth" / "2.png"
    (root / "pose" / "10.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(CaptureFormatError, match="4x4"):
        cap[2]
    for p in (root / "depth").iterdir():
        p.unlink()
    with pytest.raises(CaptureFormatError, match="no <id>.png"):
        ScanNetCapture(root)


def test_profile_depth_range_and_approximate_registration(tmp_path: Path):
    p = ScanNetCapture(_write_scannet(tmp_path / "scene0000_00")).profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.color_registered) == ("scannet", 5.0, False, False)
