"""Replica (NICE-SLAM release layout) reader on small fixtures written with the real encoders."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import ReplicaCapture
from voxfusion.core.errors import CaptureError, CaptureFormatError
from voxfusion.core.geometry import make_intrinsics


def _poses(n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = Rotation.from_euler("xyz", [10 * i, -5 * i, 3 * i], degrees=True).as_matrix()
        T[i, :3, 3] = [0.5 * i, -0.25 * i, 1.0]
    return T


def _write_replica(root: Path, n: int = 3, size: tuple[int, int] = (40, 30)) -> tuple[Path, np.ndarray]:
    """Scene folder with ``n`` frames; depth of frame i = (i + 1) metres (raw (i + 1) * 6553.5)."""
    (root / "results").mkdir(parents=True)
    w, h = size
    for i in range(n):
        raw = np.full((h, w), round((i + 1) * 6553.5), np.uint16)
        raw[2, 3] = 0
        cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), raw)
        cv2.imwrite(str(root / "results" / f"frame{i:06d}.jpg"), np.full((h, w, 3), (30, 60, 90), np.uint8))
    T = _poses(n)
    np.savetxt(root / "traj.txt", T.reshape(n, 16))
    return root, T


def test_default_release_intrinsics_depth_scale_and_poses(tmp_path: Path):
    root, T = _write_replica(tmp_path / "room0", n=2, size=(1200, 680))
    cap = ReplicaCapture(root)
    assert len(cap) == 2 and cap.intrinsics_source == "default"
    np.testing.assert_allclose(cap.K, make_intrinsics(600, 600, 599.5, 339.5))
    f = cap[1]
    assert f.depth_m.shape == (680, 1200) and f.depth_m[2, 3] == 0.0
    assert f.depth_m[100, 100] == pytest.approx(2.0, abs=1e-4)
    np.testing.assert_allclose(f.T_world_cam, T[1], atol=1e-9)  # row-major 4x4 per line
    assert np.abs(f.color.astype(int) - [90, 60, 30]).max() <= 2  # JPEG, RGB order
    assert f.timestamp_s == pytest.approx(1 / 30) and cap.gt_mesh_path is None


def test_cam_params_json_in_parent_sets_intrinsics_and_scale(tmp_path: Path):
    root, _ = _write_replica(tmp_path / "Replica" / "office0")
    cam = {"camera": {"w": 40, "h": 30, "fx": 20.0, "fy": 21.0, "cx": 19.5, "cy": 14.5, "scale": 6553.5 * 2}}
    (tmp_path / "Replica" / "cam_params.json").write_text(json.dumps(cam))
    (tmp_path / "Replica" / "office0_mesh.ply").write_text("ply\n")
    cap = ReplicaCapture(root)
    np.testing.assert_allclose(cap.K, make_intrinsics(20, 21, 19.5, 14.5))
    assert cap[0].depth_m[5, 5] == pytest.approx(0.5, abs=1e-4)  # scale from the json
    assert ReplicaCapture(root, depth_scale=6553.5)[0].depth_m[5, 5] == pytest.approx(1.0, abs=1e-4)
    assert cap.gt_mesh_path == tmp_path / "Replica" / "office0_mesh.ply"
    cam["camera"]["w"] = 1200
    (tmp_path / "Replica" / "cam_params.json").write_text(json.dumps(cam))
    with pytest.raises(CaptureFormatError, match="1200x30") as e:
        ReplicaCapture(root)
    assert e.value.path.name == "cam_params.json"
    (tmp_path / "Replica" / "cam_params.json").write_text('{"cam": {}}')
    with pytest.raises(CaptureFormatError, match="camera"):
        ReplicaCapture(root)


def test_intrinsics_argument_and_file(tmp_path: Path):
    root, _ = _write_replica(tmp_path / "room1")
    np.testing.assert_allclose(ReplicaCapture(root, K=(20, 20, 20, 15)).K, make_intrinsics(20, 20, 20, 15))
    K = make_intrinsics(18, 19, 19.5, 14.5)
    np.testing.assert_allclose(ReplicaCapture(root, K)[2].K, K)
    (root / "intrinsics.txt").write_text("25 25 20 15\n")
    np.testing.assert_allclose(ReplicaCapture(root).K, make_intrinsics(25, 25, 20, 15))
    (root / "intrinsics.txt").unlink()
    with pytest.raises(CaptureFormatError, match="principal point"):
        ReplicaCapture(root)  # release intrinsics (cx 599.5) cannot describe 40x30 images


def test_bad_layouts(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        ReplicaCapture(tmp_path / "missing")
    (tmp_path / "noresults").mkdir()
    with pytest.raises(CaptureFormatError, match="results"):
        ReplicaCapture(tmp_path / "noresults")
    root, T = _write_replica(tmp_path / "short", n=3)
    np.savetxt(root / "traj.txt", T[:2].reshape(2, 16))
    with pytest.raises(CaptureFormatError, match="2 poses") as e:
        ReplicaCapture(root, K=(20, 20, 20, 15))
    assert e.value.path.name == "traj.txt"
    np.savetxt(root / "traj.txt", T.reshape(3, 16)[:, :12])
    with pytest.raises(CaptureFormatError, match="16 numbers"):
        ReplicaCapture(root, K=(20, 20, 20, 15))
    bad = T.copy()
    bad[1, :3, :3] *= 2.0
    np.savetxt(root / "traj.txt", bad.reshape(3, 16))
    cap = ReplicaCapture(root, K=(20, 20, 20, 15))
    with pytest.raises(CaptureFormatError, match="frame 1"):
        cap[1]
    (root / "results" / "frame000002.jpg").unlink()
    with pytest.raises(CaptureError, match="frame000002.jpg"):
        cap[2]
    cv2.imwrite(str(root / "results" / "depth000000.png"), np.zeros((30, 40), np.uint8))
    with pytest.raises(CaptureFormatError, match="16-bit"):
        cap[0]


def test_profile_replica_and_our_synthetic_layout(tmp_path: Path):
    root, _ = _write_replica(tmp_path / "room0", n=1, size=(1200, 680))
    p = ReplicaCapture(root).profile
    assert (p.kind, p.max_depth_m, p.color_registered) == ("replica", 10.0, True)
    (root / "gt_mesh.ply").write_text("ply\n")  # what `voxfusion synth --layout replica` leaves beside it
    assert ReplicaCapture(root).profile.kind == "synthetic"
