"""Polycam raw-data reader: exports written at test time in Polycam's layout (keyframes/images, cameras,
depth, confidence, corrected_*) from the synthetic room (known poses, exact depth), and wrong layouts."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import PolycamCapture, RGBDFrame, detect_format, open_capture
from voxfusion.core.datasets.polycam import read_polycam_confidence
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import CaptureError, CaptureFormatError, ValidationError
from voxfusion.core.geometry import GL_TO_CV
from voxfusion.core.slam.presets import preset_for

IMAGE_W, IMAGE_H = 1024, 768  # Polycam's keyframe images; the camera JSON's fx..cy refer to them
DEPTH_W, DEPTH_H = 256, 192
N = 5
T0_US = 14329470478  # keyframe timestamps (file names) are microseconds of the device clock
ARKIT_OFFSET_M = np.array([0.05, 0.0, 0.0])  # the raw ARKit poses are off the corrected ones by this


def _stem(i: int) -> str:
    return str(T0_US + 200_000 * i)


@pytest.fixture(scope="module")
def synthetic_frames() -> list[RGBDFrame]:
    cap = SyntheticCapture(SyntheticConfig(n_frames=N, width=DEPTH_W, height=DEPTH_H, motion_scale=4))
    return [cap[i] for i in range(N)]


def _confidence_raw() -> np.ndarray:
    """Polycam's encoding: 0 / 127 / 255 = low / medium / high."""
    c = np.full((DEPTH_H, DEPTH_W), 255, np.uint8)
    c[:, :16] = 0
    c[:, 16:32] = 127
    return c


def _camera(f: RGBDFrame, i: int, T_world_cam_cv: np.ndarray) -> dict:
    K = f.K.copy()
    K[:2] *= IMAGE_W / DEPTH_W
    T_gl = T_world_cam_cv @ GL_TO_CV
    cam = {"blur_score": 100.0 + i, "cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1],
           "height": IMAGE_H, "width": IMAGE_W, "manual_keyframe": False, "neighbors": [],
           "timestamp": int(_stem(i))}
    cam.update({f"t_{r}{c}": float(T_gl[r, c]) for r in range(3) for c in range(4)})
    return cam


def _write_export(root: Path, frames: list[RGBDFrame], corrected: bool = True) -> Path:
    """A Polycam raw-data export; the corrected cameras hold the true poses, the ARKit ones are offset."""
    kf = root / "keyframes"
    folders = ["images", "cameras", "depth", "confidence"] + (["corrected_images", "corrected_cameras"]
                                                              if corrected else [])
    for d in folders:
        (kf / d).mkdir(parents=True)
    for i, f in enumerate(frames):
        stem = _stem(i)
        big = cv2.cvtColor(cv2.resize(f.color, (IMAGE_W, IMAGE_H), interpolation=cv2.INTER_LINEAR),
                           cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(kf / "images" / f"{stem}.jpg"), big, [cv2.IMWRITE_JPEG_QUALITY, 95])
        T_arkit = f.T_world_cam.copy()
        T_arkit[:3, 3] += ARKIT_OFFSET_M
        (kf / "cameras" / f"{stem}.json").write_text(json.dumps(_camera(f, i, T_arkit)))
        if corrected:
            cv2.imwrite(str(kf / "corrected_images" / f"{stem}.jpg"), big, [cv2.IMWRITE_JPEG_QUALITY, 95])
            (kf / "corrected_cameras" / f"{stem}.json").write_text(json.dumps(_camera(f, i, f.T_world_cam)))
        cv2.imwrite(str(kf / "depth" / f"{stem}.png"), np.round(f.depth_m * 1000).astype(np.uint16))
        cv2.imwrite(str(kf / "confidence" / f"{stem}.png"), _confidence_raw())
    (root / "mesh_info.json").write_text(json.dumps({"alignmentTransform": np.eye(4).reshape(-1).tolist()}))
    return root


@pytest.fixture
def export(tmp_path: Path, synthetic_frames: list[RGBDFrame]) -> Path:
    return _write_export(tmp_path / "polycam", synthetic_frames)


def test_depth_confidence_intrinsics_colour_and_time(export: Path, synthetic_frames: list[RGBDFrame]):
    cap = PolycamCapture(export)
    assert len(cap) == N and cap.corrected
    for i in (0, 4):
        f, truth = cap[i], synthetic_frames[i]
        np.testing.assert_allclose(f.K, truth.K, atol=1e-9)  # K for 1024x768 scaled to the 256x192 depth
        expected_conf = (_confidence_raw() // 127).astype(np.uint8)
        np.testing.assert_array_equal(f.confidence, expected_conf)  # 0/127/255 -> 0/1/2
        keep = (expected_conf >= 1) & (truth.depth_m > 0)
        np.testing.assert_allclose(f.depth_m[keep], truth.depth_m[keep], atol=5e-4)  # mm -> m
        assert np.all(f.depth_m[:, :16] == 0)  # low confidence dropped by the default threshold
        assert f.color.shape == (DEPTH_H, DEPTH_W, 3)
        assert np.abs(f.color.astype(int) - truth.color.astype(int)).mean() < 6  # RGB order, registered
        assert f.timestamp_s == pytest.approx(int(_stem(i)) / 1e6)
        assert f.meta["stem"] == _stem(i) and f.meta["blur_score"] == 100.0 + i
    raw = PolycamCapture(export, confidence_threshold=None)[2]
    np.testing.assert_allclose(raw.depth_m, synthetic_frames[2].depth_m, atol=5e-4)


def test_corrected_poses_preferred_arkit_as_device_prior(export: Path, synthetic_frames: list[RGBDFrame],
                                                         reprojection_error):
    cap = PolycamCapture(export, confidence_threshold=None)
    for i in range(N):
        f, truth = cap[i], synthetic_frames[i].T_world_cam
        np.testing.assert_allclose(f.T_world_cam, truth, atol=1e-9)  # corrected = the true pose
        np.testing.assert_allclose(f.T_world_cam_device[:3, 3], truth[:3, 3] + ARKIT_OFFSET_M, atol=1e-9)
        np.testing.assert_allclose(f.T_world_cam_device[:3, :3], truth[:3, :3], atol=1e-9)
    a, b = cap[0], cap[4]
    err = reprojection_error(a.depth_m, a.K, a.T_world_cam, b.depth_m, b.K, b.T_world_cam)
    err_identity = reprojection_error(a.depth_m, a.K, np.eye(4), b.depth_m, b.K, np.eye(4))
    err_gl = reprojection_error(a.depth_m, a.K, a.T_world_cam @ GL_TO_CV, b.depth_m, b.K, b.T_world_cam @ GL_TO_CV)
    assert err < 0.01 and err_identity > 10 * err and err_gl > 10 * err

    arkit = PolycamCapture(export, corrected=False)[1]
    assert not PolycamCapture(export, corrected=False).corrected
    np.testing.assert_allclose(arkit.T_world_cam[:3, 3], synthetic_frames[1].T_world_cam[:3, 3] + ARKIT_OFFSET_M)
    np.testing.assert_array_equal(arkit.T_world_cam, arkit.T_world_cam_device)


def test_a_known_arkit_pose(tmp_path: Path, synthetic_frames: list[RGBDFrame]):
    """Hand-written t_ij (camera turned 90 deg left about ARKit's +y, 1.5 m up): row i, column j."""
    root = _write_export(tmp_path / "polycam", synthetic_frames[:1], corrected=False)
    path = root / "keyframes" / "cameras" / f"{_stem(0)}.json"
    cam = json.loads(path.read_text())
    T_gl = np.eye(4)
    T_gl[:3, :3] = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    T_gl[:3, 3] = (0.5, 1.5, -2.0)
    cam.update({f"t_{r}{c}": float(T_gl[r, c]) for r in range(3) for c in range(4)})
    path.write_text(json.dumps(cam))
    T = PolycamCapture(root)[0].T_world_cam
    expected = np.array([[0.0, 0.0, -1.0, 0.5], [0.0, -1.0, 0.0, 1.5], [-1.0, 0.0, 0.0, -2.0], [0, 0, 0, 1]])
    np.testing.assert_allclose(T, expected, atol=1e-12)


def test_raw_only_export_and_partial_corrections(tmp_path: Path, synthetic_frames: list[RGBDFrame]):
    root = _write_export(tmp_path / "polycam", synthetic_frames[:2], corrected=False)
    cap = PolycamCapture(root)
    assert not cap.corrected
    with pytest.raises(CaptureFormatError, match="corrected=True"):
        PolycamCapture(root, corrected=True)
    (root / "keyframes" / "corrected_cameras").mkdir()  # corrected cameras without corrected images
    assert not PolycamCapture(root).corrected


def test_detected_and_opened_with_the_iphone_profile(export: Path):
    assert detect_format(export) == "polycam"
    cap = open_capture(export)
    assert isinstance(cap, PolycamCapture)
    p = cap.profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.has_color) == ("iphone", 5.0, True, True)
    assert "corrected poses" in p.sensor
    assert preset_for(cap, "cpu").preset == "iphone+cpu"
    assert not open_capture(export, corrected=False).corrected


def test_confidence_values_are_checked(tmp_path: Path):
    path = tmp_path / "c.png"
    cv2.imwrite(str(path), np.array([[0, 127, 255]], np.uint8))
    np.testing.assert_array_equal(read_polycam_confidence(path), [[0, 1, 2]])
    cv2.imwrite(str(path), np.array([[0, 2, 1]], np.uint8))  # our 0/1/2, not Polycam's encoding
    with pytest.raises(CaptureFormatError, match="0/127/255"):
        read_polycam_confidence(path)


def test_broken_exports_name_what_is_wrong(tmp_path: Path, synthetic_frames: list[RGBDFrame]):
    with pytest.raises(CaptureError, match="not found"):
        PolycamCapture(tmp_path / "missing")
    root = _write_export(tmp_path / "broken", synthetic_frames[:3])
    kf = root / "keyframes"
    with pytest.raises(ValidationError, match="confidence_threshold"):
        PolycamCapture(root, confidence_threshold=127)

    moved = tmp_path / "depth_moved"
    shutil.move(kf / "depth", moved)  # no depth at all: still detected as Polycam, and the reader says so
    with pytest.raises(CaptureFormatError, match="keyframes/depth folder not found"):
        open_capture(root)
    shutil.move(moved, kf / "depth")

    (kf / "depth" / f"{_stem(1)}.png").unlink()  # one keyframe without depth
    with pytest.raises(CaptureFormatError, match=rf"1 of 3 cameras .* no keyframes/depth/.*{_stem(1)}\.png"):
        open_capture(root)
    shutil.copy(kf / "depth" / f"{_stem(0)}.png", kf / "depth" / f"{_stem(1)}.png")

    (kf / "corrected_images" / f"{_stem(2)}.jpg").unlink()
    with pytest.raises(CaptureFormatError, match=f"corrected_images/<timestamp>.jpg .*{_stem(2)}"):
        PolycamCapture(root)
    shutil.copy(kf / "images" / f"{_stem(2)}.jpg", kf / "corrected_images" / f"{_stem(2)}.jpg")

    cam_path = kf / "corrected_cameras" / f"{_stem(1)}.json"
    good = cam_path.read_text()
    cam = json.loads(good)
    del cam["t_23"]
    cam_path.write_text(json.dumps(cam))
    with pytest.raises(CaptureFormatError, match="t_23") as e:
        PolycamCapture(root)
    assert e.value.path == cam_path
    cam = json.loads(good)
    cam["width"], cam["height"] = 1024, 1024
    cam_path.write_text(json.dumps(cam))
    with pytest.raises(CaptureFormatError, match="aspect"):
        PolycamCapture(root)
    cam = json.loads(good)
    cam["t_00"] = 3.0
    cam_path.write_text(json.dumps(cam))
    with pytest.raises(CaptureFormatError, match="not a rigid"):
        PolycamCapture(root)
    cam_path.write_text(good)

    cap = PolycamCapture(root)
    cv2.imwrite(str(kf / "corrected_images" / f"{_stem(0)}.jpg"), np.zeros((96, 128, 3), np.uint8))
    with pytest.raises(CaptureFormatError, match="image is 128x96, its camera says 1024x768"):
        cap[0]
    cv2.imwrite(str(kf / "confidence" / f"{_stem(1)}.png"), np.full((DEPTH_H, DEPTH_W), 200, np.uint8))
    with pytest.raises(CaptureFormatError, match="found 200"):
        cap[1]
    shutil.rmtree(kf / "corrected_cameras")
    shutil.rmtree(kf / "cameras")
    with pytest.raises(CaptureFormatError, match="keyframes/cameras folder not found"):
        open_capture(root)
