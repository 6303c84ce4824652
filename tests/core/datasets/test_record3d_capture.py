"""Record3D ``.r3d`` reader on archives written with zipfile + lzfse + cv2 in the app's layout."""

from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

import cv2
import lzfse
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import Record3DCapture
from voxfusion.core.errors import CaptureError, CaptureFormatError

W, H, DW, DH = 64, 48, 32, 24
K_COLOR = np.array([[60.0, 0.0, 31.5], [0.0, 61.0, 23.5], [0.0, 0.0, 1.0]])


def _gl_poses(n: int) -> list[list[float]]:
    """``[qx, qy, qz, qw, px, py, pz]`` per frame (OpenGL camera axes)."""
    out = []
    for i in range(n):
        q = Rotation.from_euler("y", 20 * i, degrees=True).as_quat()
        out.append([*q, 0.1 * i, 1.5, -0.2 * i])
    return out


def _depth(i: int) -> np.ndarray:
    d = np.full((DH, DW), 0.5 + 0.25 * i, np.float32)
    d[0, 0] = np.nan
    d[0, 1] = -1.0
    return d


def _write_r3d(path: Path, n: int = 3, meta_changes: dict | None = None, conf: bool = True,
               entries: dict[str, bytes] | None = None) -> Path:
    meta = {"w": W, "h": H, "dw": DW, "dh": DH, "K": K_COLOR.T.reshape(-1).tolist(), "fps": 60,
            "poses": _gl_poses(n), "cameraType": 1, "initPose": [0, 0, 0, 1, 0, 0, 0]}
    meta.update(meta_changes or {})
    meta = {k: v for k, v in meta.items() if v is not None}  # None = leave the key out
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("metadata", json.dumps(meta))
        for i in range(n):
            ok, jpg = cv2.imencode(".jpg", np.full((H, W, 3), (10, 20 * i, 250), np.uint8))
            zf.writestr(f"rgbd/{i}.jpg", jpg.tobytes())
            zf.writestr(f"rgbd/{i}.depth", lzfse.compress(_depth(i).tobytes()))
            if conf:
                zf.writestr(f"rgbd/{i}.conf", lzfse.compress(np.full((DH, DW), i % 3, np.uint8).tobytes()))
        for name, data in (entries or {}).items():
            zf.writestr(name, data)
    return path


def test_frames_depth_confidence_colour_and_scaled_intrinsics(tmp_path: Path):
    with Record3DCapture(_write_r3d(tmp_path / "scan.r3d")) as cap:
        assert len(cap) == 3 and cap.name == "scan"
        np.testing.assert_allclose(cap.K, [[30.0, 0.0, 15.75], [0.0, 30.5, 11.75], [0.0, 0.0, 1.0]])
        f = cap[2]
        expected = _depth(2)
        expected[0, :2] = 0.0  # NaN and negative depth are invalid
        np.testing.assert_array_equal(f.depth_m, expected)
        np.testing.assert_array_equal(f.confidence, np.full((DH, DW), 2, np.uint8))
        assert f.color.shape == (DH, DW, 3)
        assert np.abs(f.color[5, 5].astype(int) - [250, 40, 10]).max() <= 3  # RGB order
        assert f.timestamp_s == pytest.approx(2 / 60)


def test_opengl_poses_become_opencv(tmp_path: Path):
    cap = Record3DCapture(_write_r3d(tmp_path / "scan.r3d"))
    gl = _gl_poses(3)[1]
    f = cap[1]
    R_gl = Rotation.from_quat(gl[:4]).as_matrix()
    np.testing.assert_allclose(f.T_world_cam[:3, 3], gl[4:])
    np.testing.assert_allclose(f.T_world_cam[:3, :3], R_gl @ np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_array_equal(f.T_world_cam, f.T_world_cam_device)
    # Physical check: the GL camera looks along its -z; the OpenCV camera looks along +z, same ray.
    forward_gl = R_gl @ np.array([0.0, 0.0, -1.0])
    forward_cv = f.T_world_cam[:3, :3] @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(forward_cv, forward_gl, atol=1e-12)
    up_gl = R_gl @ np.array([0.0, 1.0, 0.0])  # GL y is up, OpenCV y is down
    np.testing.assert_allclose(f.T_world_cam[:3, :3] @ np.array([0.0, -1.0, 0.0]), up_gl, atol=1e-12)


def test_frame_timestamps_without_poses_or_confidence(tmp_path: Path):
    path = _write_r3d(tmp_path / "a.r3d", n=2, conf=False,
                      meta_changes={"poses": [], "frameTimestamps": [10.0, 10.5], "fps": None})
    f = Record3DCapture(path)[1]
    assert f.timestamp_s == 10.5 and f.T_world_cam is None and f.confidence is None


def test_pickle_and_reopen_after_close(tmp_path: Path):
    cap = Record3DCapture(_write_r3d(tmp_path / "scan.r3d"))
    first = cap[0].depth_m
    cap.close()
    np.testing.assert_array_equal(cap[0].depth_m, first)  # reopens lazily
    clone = pickle.loads(pickle.dumps(cap))
    np.testing.assert_array_equal(clone[0].depth_m, first)


def test_bad_archives(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        Record3DCapture(tmp_path / "missing.r3d")
    (tmp_path / "plain.r3d").write_bytes(b"not a zip")
    with pytest.raises(CaptureFormatError, match="zip"):
        Record3DCapture(tmp_path / "plain.r3d")
    with zipfile.ZipFile(tmp_path / "nometa.r3d", "w") as zf:
        zf.writestr("rgbd/0.depth", b"")
    with pytest.raises(CaptureFormatError, match="metadata"):
        Record3DCapture(tmp_path / "nometa.r3d")
    with pytest.raises(CaptureFormatError, match="'dw'"):
        Record3DCapture(_write_r3d(tmp_path / "nodw.r3d", meta_changes={"dw": None}))
    with pytest.raises(CaptureFormatError, match="poses"):
        Record3DCapture(_write_r3d(tmp_path / "shortposes.r3d", meta_changes={"poses": _gl_poses(1)}))
    with pytest.raises(CaptureFormatError, match="principal point"):
        Record3DCapture(_write_r3d(tmp_path / "k.r3d", meta_changes={"w": 16, "h": 12}))
    wrong_w = Record3DCapture(_write_r3d(tmp_path / "w.r3d", meta_changes={"w": 62}))
    with pytest.raises(CaptureFormatError, match="metadata says 62x48"):
        wrong_w[0]


def test_bad_entries_are_named(tmp_path: Path):
    path = _write_r3d(tmp_path / "scan.r3d", n=2)
    # Replace frame 1's depth by one of the wrong size and frame 0's colour by garbage.
    with zipfile.ZipFile(path) as zf:
        items = {n: zf.read(n) for n in zf.namelist()}
    items["rgbd/1.depth"] = lzfse.compress(np.zeros((DH, DW + 1), np.float32).tobytes())
    items["rgbd/0.jpg"] = b"garbage"
    with zipfile.ZipFile(path, "w") as zf:
        for n, data in items.items():
            zf.writestr(n, data)
    cap = Record3DCapture(path)
    with pytest.raises(CaptureFormatError, match="32x24 float32") as e:
        cap[1]
    assert str(e.value.path).endswith("scan.r3d/rgbd/1.depth")
    with pytest.raises(CaptureError, match="corrupt") as e:
        cap[0]
    assert str(e.value.path).endswith("rgbd/0.jpg")
    items["rgbd/1.depth"] = b"not lzfse at all"
    with zipfile.ZipFile(path, "w") as zf:
        for n, data in items.items():
            zf.writestr(n, data)
    with pytest.raises(CaptureError, match="LZFSE"):
        Record3DCapture(path)[1]


@pytest.mark.parametrize("conf", [True, False])
def test_profile_lidar_confidence_when_the_archive_has_it(tmp_path: Path, conf: bool):
    p = Record3DCapture(_write_r3d(tmp_path / "scan.r3d", n=1, conf=conf)).profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.has_color) == ("iphone", 5.0, conf, True)
