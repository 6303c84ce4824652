"""3D Scanner App reader: exports written at test time in the app's exact layout from the synthetic room
(known poses, exact depth), wrong layouts, and the real corridor export."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import RGBDFrame, Scanner3DCapture, SlicedCapture, detect_format, open_capture
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import CaptureError, CaptureFormatError, ValidationError
from voxfusion.core.geometry import GL_TO_CV
from voxfusion.core.slam.presets import preset_for

COLOR_W, COLOR_H = 1920, 1440  # the app's colour JPEGs; the JSON intrinsics refer to them
DEPTH_W, DEPTH_H = 256, 192
SCALE = COLOR_W / DEPTH_W  # 7.5
N = 6
T0_S = 104137.33988787502  # a device-clock time as in the real export


@pytest.fixture(scope="module")
def synthetic_frames() -> list[RGBDFrame]:
    """The synthetic room at 256x192, exact depth, poses moving ~4 cm per frame (OpenCV axes)."""
    cap = SyntheticCapture(SyntheticConfig(n_frames=N, width=DEPTH_W, height=DEPTH_H, motion_scale=4))
    return [cap[i] for i in range(N)]


def _confidence(i: int) -> np.ndarray:
    c = np.full((DEPTH_H, DEPTH_W), 2, np.uint8)
    c[:, :16] = 0
    c[:, 16:32] = 1
    return c


def _write_export(root: Path, frames: list[RGBDFrame], *, color_every: int = 3) -> Path:
    """``frames`` as a 3D Scanner App "All Data" export: per frame ``frame_%05d.json`` (ARKit / OpenGL pose,
    K for 1920x1440, time), ``depth_%05d.png`` (uint16 mm), ``conf_%05d.png``; ``frame_%05d.jpg``
    (1920x1440) for every ``color_every``-th frame; ``info.json``."""
    root.mkdir(parents=True)
    for i, f in enumerate(frames):
        K_color = f.K.copy()
        K_color[:2] *= SCALE
        T_gl = f.T_world_cam @ GL_TO_CV
        meta = {"cameraGrain": 0, "intrinsics": K_color.reshape(-1).tolist(), "latitude": 37.5, "longitude": 127.0,
                "time": T0_S + i / 6, "hasGPS": True, "cameraPoseARFrame": T_gl.reshape(-1).tolist(),
                "frame_index": i, "projectionMatrix": np.eye(4).reshape(-1).tolist(), "motionQuality": 1}
        (root / f"frame_{i:05d}.json").write_text(json.dumps(meta, indent=2))
        cv2.imwrite(str(root / f"depth_{i:05d}.png"), np.round(f.depth_m * 1000).astype(np.uint16))
        cv2.imwrite(str(root / f"conf_{i:05d}.png"), _confidence(i))
        if i % color_every == 0:
            big = cv2.resize(f.color, (COLOR_W, COLOR_H), interpolation=cv2.INTER_LINEAR)
            cv2.imwrite(str(root / f"frame_{i:05d}.jpg"), cv2.cvtColor(big, cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
    (root / "info.json").write_text(json.dumps({"numImages": len(frames), "appVersionString": "1.9.7",
                                                "title": "synthetic"}))
    return root


@pytest.fixture
def export(tmp_path: Path, synthetic_frames: list[RGBDFrame]) -> Path:
    return _write_export(tmp_path / "scan", synthetic_frames)


def test_depth_in_metres_confidence_intrinsics_and_colour(export: Path, synthetic_frames: list[RGBDFrame]):
    cap = Scanner3DCapture(export)
    assert len(cap) == N and cap.color_indices == (0, 3) and cap.color_size == (COLOR_W, COLOR_H)
    for i in (0, 1, 3):
        f, truth = cap[i], synthetic_frames[i]
        assert f.depth_m.shape == (DEPTH_H, DEPTH_W) and f.depth_m.dtype == np.float32
        np.testing.assert_allclose(f.K, truth.K, atol=1e-9)  # K for 1920x1440 scaled to 256x192
        np.testing.assert_array_equal(f.confidence, _confidence(i))  # 0/1/2 passed through
        keep = (_confidence(i) >= 1) & (truth.depth_m > 0)  # default threshold 1 zeroes low confidence
        np.testing.assert_allclose(f.depth_m[keep], truth.depth_m[keep], atol=5e-4)  # mm -> m
        assert np.all(f.depth_m[_confidence(i) == 0] == 0)
        assert f.timestamp_s == pytest.approx(T0_S + i / 6)
        assert f.meta["frame_id"] == i
    assert cap[1].color is None and cap[4].color is None  # no JPEG: a depth-only frame
    c = cap[3].color
    assert c.shape == (DEPTH_H, DEPTH_W, 3) and c.dtype == np.uint8
    assert np.abs(c.astype(int) - synthetic_frames[3].color.astype(int)).mean() < 6  # RGB order, registered
    raw = Scanner3DCapture(export, confidence_threshold=None)[2]
    np.testing.assert_allclose(raw.depth_m, synthetic_frames[2].depth_m, atol=5e-4)


def test_arkit_poses_become_opencv(export: Path, synthetic_frames: list[RGBDFrame], reprojection_error):
    cap = Scanner3DCapture(export, confidence_threshold=None)
    for i in range(N):
        f = cap[i]
        np.testing.assert_allclose(f.T_world_cam, synthetic_frames[i].T_world_cam, atol=1e-9)
        np.testing.assert_array_equal(f.T_world_cam, f.T_world_cam_device)  # ARKit pose = device prior
    a, b = cap[0], cap[5]
    err = reprojection_error(a.depth_m, a.K, a.T_world_cam, b.depth_m, b.K, b.T_world_cam)
    err_identity = reprojection_error(a.depth_m, a.K, np.eye(4), b.depth_m, b.K, np.eye(4))
    err_gl = reprojection_error(a.depth_m, a.K, a.T_world_cam @ GL_TO_CV, b.depth_m, b.K, b.T_world_cam @ GL_TO_CV)
    assert err < 0.01 and err_identity > 10 * err and err_gl > 10 * err


def test_a_known_arkit_pose(tmp_path: Path, synthetic_frames: list[RGBDFrame]):
    """A hand-written ARKit camera-to-world (turned 90 deg left about +y, 1.5 m up) in the JSON."""
    root = _write_export(tmp_path / "scan", synthetic_frames[:1])
    R_gl = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    T_gl = np.eye(4)
    T_gl[:3, :3], T_gl[:3, 3] = R_gl, (0.5, 1.5, -2.0)
    meta = json.loads((root / "frame_00000.json").read_text())
    meta["cameraPoseARFrame"] = T_gl.reshape(-1).tolist()  # row-major: translation at [3], [7], [11]
    (root / "frame_00000.json").write_text(json.dumps(meta))
    T = Scanner3DCapture(root)[0].T_world_cam
    expected = np.array([[0.0, 0.0, -1.0, 0.5], [0.0, -1.0, 0.0, 1.5], [-1.0, 0.0, 0.0, -2.0], [0, 0, 0, 1]])
    np.testing.assert_allclose(T, expected, atol=1e-12)
    # the GL camera looks along its -z = world -x; the OpenCV camera along its +z: the same ray
    np.testing.assert_allclose(T[:3, 2], R_gl @ [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 1], -(R_gl @ [0.0, 1.0, 0.0]), atol=1e-12)  # image y is down


def test_detected_and_opened_with_the_iphone_profile(export: Path):
    assert detect_format(export) == "scanner3d"
    cap = open_capture(export)
    assert isinstance(cap, Scanner3DCapture)
    p = cap.profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.has_color) == ("iphone", 5.0, True, True)
    assert preset_for(cap, "cpu").preset == "iphone+cpu"
    colour_only = open_capture(export, stride=3)
    assert isinstance(colour_only, SlicedCapture) and all(f.color is not None for f in colour_only)
    assert open_capture(export, confidence_threshold=2)[0].depth_m[:, 16:32].max() == 0


def test_depth_only_export(tmp_path: Path, synthetic_frames: list[RGBDFrame]):
    root = _write_export(tmp_path / "scan", synthetic_frames[:2], color_every=100)
    (root / "frame_00000.jpg").unlink()
    cap = Scanner3DCapture(root)
    assert cap.color_indices == () and cap[0].color is None and not cap.profile.has_color
    np.testing.assert_allclose(cap.K, synthetic_frames[0].K, atol=1e-9)  # K for the default 1920x1440


def _broken(tmp_path: Path, frames: list[RGBDFrame]) -> Path:
    return _write_export(tmp_path / "broken", frames[:4])


def test_broken_exports_name_what_is_wrong(tmp_path: Path, synthetic_frames: list[RGBDFrame]):
    with pytest.raises(CaptureError, match="not found"):
        Scanner3DCapture(tmp_path / "missing")
    root = _broken(tmp_path, synthetic_frames)
    with pytest.raises(ValidationError, match="confidence_threshold"):
        Scanner3DCapture(root, confidence_threshold=3)

    (root / "depth_00002.png").unlink()  # a frame without depth: open_capture routes it here and says so
    with pytest.raises(CaptureFormatError, match=r"1 of 4 frame_\*\.json have no depth_\*\.png \(depth_00002"):
        open_capture(root)
    shutil.copy(root / "depth_00001.png", root / "depth_00002.png")

    shutil.copy(root / "depth_00001.png", root / "depth_00009.png")  # depth without its json
    with pytest.raises(CaptureFormatError, match="frame_00009.json"):
        open_capture(root)
    (root / "depth_00009.png").unlink()

    (root / "conf_00003.png").unlink()  # confidence maps for some frames only
    with pytest.raises(CaptureFormatError, match="conf_00003.png"):
        open_capture(root)
    shutil.copy(root / "conf_00001.png", root / "conf_00003.png")

    good = (root / "frame_00001.json").read_text()
    meta = json.loads(good)
    del meta["cameraPoseARFrame"]
    (root / "frame_00001.json").write_text(json.dumps(meta))
    with pytest.raises(CaptureFormatError, match="cameraPoseARFrame") as e:
        open_capture(root)
    assert e.value.path.name == "frame_00001.json"
    for key, value, message in [("intrinsics", [1.0, 2.0, 3.0], "holds 3 values, expected 9"),
                                ("cameraPoseARFrame", (2 * np.eye(4)).reshape(-1).tolist(), "not a rigid"),
                                ("time", None, "'time'")]:
        meta = json.loads(good)
        if value is None:
            del meta[key]
        else:
            meta[key] = value
        (root / "frame_00001.json").write_text(json.dumps(meta))
        with pytest.raises(CaptureFormatError, match=message):
            Scanner3DCapture(root)
    (root / "frame_00001.json").write_text("{not json")
    with pytest.raises(CaptureFormatError, match="not valid JSON"):
        Scanner3DCapture(root)
    (root / "frame_00001.json").write_text(good)

    cap = Scanner3DCapture(root)
    cv2.imwrite(str(root / "frame_00003.jpg"), np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(CaptureFormatError, match="colour is 640x480") as e:
        cap[3]
    assert e.value.path.name == "frame_00003.jpg"
    cv2.imwrite(str(root / "depth_00001.png"), np.zeros((DEPTH_H, DEPTH_W), np.uint8))
    with pytest.raises(CaptureFormatError, match="16-bit"):
        cap[1]


# ------------------------------------------------------------------------------------------- real export


@pytest.fixture(scope="module")
def corridor(shared_data: Path) -> Path:
    root = shared_data / "scanner3d_iphone_corridor"
    if not root.is_dir():
        pytest.skip(f"the real 3D Scanner App export is not available ({root} is absent)")
    return root


def test_real_export_values(corridor: Path):
    cap = open_capture(corridor)
    assert isinstance(cap, Scanner3DCapture) and detect_format(corridor) == "scanner3d"
    assert len(cap) == 436 and len(cap.color_indices) == 146 and cap.color_indices[:3] == (0, 3, 6)
    assert cap.profile.kind == "iphone" and preset_for(cap, "cpu").preset == "iphone+cpu"
    meta = json.loads((corridor / "frame_00010.json").read_text())
    f = cap[10]
    K = np.asarray(meta["intrinsics"]).reshape(3, 3)
    K[:2] *= 256 / 1920
    np.testing.assert_allclose(f.K, K)
    T_gl = np.asarray(meta["cameraPoseARFrame"]).reshape(4, 4)
    np.testing.assert_allclose(f.T_world_cam, T_gl @ GL_TO_CV, atol=1e-6)
    assert f.timestamp_s == meta["time"] and f.color is None and cap[9].color.shape == (192, 256, 3)
    raw = cv2.imread(str(corridor / "depth_00010.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
    conf = cv2.imread(str(corridor / "conf_00010.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(f.confidence, conf)
    np.testing.assert_allclose(f.depth_m, np.where(conf >= 1, raw, 0.0))


def test_real_poses_reproject_depth(corridor: Path, reprojection_error):
    cap = Scanner3DCapture(corridor)
    for i, j in ((200, 205), (400, 405)):  # ~0.8 m walked between the two frames
        a, b = cap[i], cap[j]
        err = reprojection_error(a.depth_m, a.K, a.T_world_cam, b.depth_m, b.K, b.T_world_cam, stride=2)
        err_identity = reprojection_error(a.depth_m, a.K, np.eye(4), b.depth_m, b.K, np.eye(4), stride=2)
        err_gl = reprojection_error(
            a.depth_m, a.K, a.T_world_cam @ GL_TO_CV, b.depth_m, b.K, b.T_world_cam @ GL_TO_CV, stride=2
        )
        assert err < 0.04, (i, j, err)  # measured 1.4-2.2 cm
        assert err_identity > 5 * err and err_gl > 5 * err, (i, j, err, err_identity, err_gl)
