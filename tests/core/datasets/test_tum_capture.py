"""TUM RGB-D reader: association, depth scale, intrinsics choice, ground-truth interpolation, bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import TUMCapture
from voxfusion.core.datasets.tum import TUM_INTRINSICS, associate_timestamps
from voxfusion.core.errors import CaptureError, CaptureFormatError, ValidationError
from voxfusion.core.geometry import make_intrinsics, pose_from_tum

W, H = 32, 24


def _write_tum(root: Path, rgb_ts: list[float], depth_ts: list[float],
               gt_rows: list[list[float]] | None = None, size: tuple[int, int] = (W, H)) -> Path:
    """A small TUM-layout sequence; depth of the k-th image = 5000 + 500 k raw units, pixel (0, 0) invalid.

    Images other than 640x480 get an ``intrinsics.txt`` (fx = fy = 20, centred principal point).
    """
    (root / "rgb").mkdir(parents=True)
    if size != (640, 480):
        (root / "intrinsics.txt").write_text(f"20 20 {size[0] / 2} {size[1] / 2}\n")
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for k, t in enumerate(rgb_ts):
        img = np.zeros((size[1], size[0], 3), np.uint8)
        img[..., 2] = 200  # red in BGR order
        img[..., 0] = 10 * k  # blue channel encodes the index
        rel = f"rgb/{t:.6f}.png"
        cv2.imwrite(str(root / rel), img)
        rgb_lines.append(f"{t:.6f} {rel}")
    for k, t in enumerate(depth_ts):
        d = np.full((size[1], size[0]), 5000 + 500 * k, np.uint16)
        d[0, 0] = 0
        rel = f"depth/{t:.6f}.png"
        cv2.imwrite(str(root / rel), d)
        depth_lines.append(f"{t:.6f} {rel}")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt_rows is not None:
        lines = ["# timestamp tx ty tz qx qy qz qw"] + [" ".join(f"{v:.9f}" for v in r) for r in gt_rows]
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return root


# --- real data --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tum_real(shared_data) -> TUMCapture:
    return TUMCapture(shared_data / "tum_fr1_desk_9frames")


def test_real_sequence_association_and_values(tum_real: TUMCapture, shared_data: Path):
    root = shared_data / "tum_fr1_desk_9frames"
    assert len(tum_real) == 9  # rgb.txt lists the whole sequence; only 9 image pairs are on disk
    assert tum_real.skipped_missing > 0
    assert tum_real.intrinsics_source == "fr1"
    np.testing.assert_allclose(tum_real.K, make_intrinsics(*TUM_INTRINSICS["fr1"]))
    # The one pair in the shipped associate.txt is our first frame.
    rgb_t, _, depth_t, _ = (root / "associate.txt").read_text().splitlines()[0].split()
    f = tum_real[0]
    assert f.timestamp_s == pytest.approx(float(rgb_t))
    assert f.meta["depth_time_s"] == pytest.approx(float(depth_t))
    raw = cv2.imread(str(root / "depth" / f"{depth_t}.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(f.depth_m, raw.astype(np.float32) / 5000.0)
    bgr = cv2.imread(str(root / "rgb" / f"{rgb_t}.png"))
    np.testing.assert_array_equal(f.color, bgr[..., ::-1])
    assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (480, 640)
    times = [fr.timestamp_s for fr in tum_real.frames()]
    assert np.all(np.diff(times) > 0)
    assert all(abs(fr.timestamp_s - fr.meta["depth_time_s"]) < 0.02 for fr in tum_real.frames(step=4))


def test_real_ground_truth_interpolated_at_colour_time(tum_real: TUMCapture, shared_data: Path):
    gt = np.loadtxt(shared_data / "tum_fr1_desk_9frames" / "groundtruth.txt")
    f = tum_real[4]
    j = np.searchsorted(gt[:, 0], f.timestamp_s)
    t0, t1 = gt[j - 1, 0], gt[j, 0]
    assert t0 <= f.timestamp_s <= t1
    a = (f.timestamp_s - t0) / (t1 - t0)
    np.testing.assert_allclose(f.T_world_cam[:3, 3], (1 - a) * gt[j - 1, 1:4] + a * gt[j, 1:4], atol=1e-9)
    # Rotation lies between the two samples: angle to each is at most the angle between them.
    R = Rotation.from_matrix(f.T_world_cam[:3, :3])
    r0, r1 = Rotation.from_quat(gt[j - 1, 4:8]), Rotation.from_quat(gt[j, 4:8])
    total = (r0.inv() * r1).magnitude()
    assert (r0.inv() * R).magnitude() == pytest.approx(a * total, abs=1e-6)
    nearest = TUMCapture(shared_data / "tum_fr1_desk_9frames", gt="nearest")[4]
    assert np.abs(nearest.T_world_cam[:3, 3] - f.T_world_cam[:3, 3]).max() < 0.01
    assert TUMCapture(shared_data / "tum_fr1_desk_9frames", gt="none")[4].T_world_cam is None


def test_real_poses_reproject_depth(tum_real: TUMCapture, reprojection_error):
    a, b = tum_real[0], tum_real[8]
    err = reprojection_error(a.depth_m, a.K, a.T_world_cam, b.depth_m, b.K, b.T_world_cam)
    err_identity = reprojection_error(a.depth_m, a.K, np.eye(4), b.depth_m, b.K, np.eye(4))
    assert err < 0.03  # data README: ~2 cm
    assert err_identity > 2 * err and err_identity > 0.05


# --- synthetic layouts ---------------------------------------------------------------------------------


def test_association_is_greedy_one_to_one():
    pairs = associate_timestamps([0.0, 0.010, 0.100], [0.004, 0.011, 0.5], 0.02)
    # 0.010<->0.011 is the closest pair, so 0.0 must take 0.004; 0.100 has no partner.
    assert pairs == [(0, 0), (1, 1)]
    assert associate_timestamps([0.0], [0.03], 0.02) == []


def test_synthetic_sequence_depth_scale_colour_and_unmatched(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.00, 1.10, 1.20], [1.005, 1.112, 1.26])
    cap = TUMCapture(root)
    assert len(cap) == 2  # depth at 1.26 is 60 ms from the nearest colour image
    f0, f1 = cap[0], cap[1]
    assert f0.depth_m[5, 5] == pytest.approx(1.0) and f0.depth_m[0, 0] == 0.0
    assert f1.depth_m[5, 5] == pytest.approx(5500 / 5000)
    assert tuple(f1.color[3, 3]) == (200, 0, 10)  # RGB order; blue channel = 10 * index
    assert f0.T_world_cam is None and cap.frames_without_gt == (0, 1) and not cap.has_gt
    assert f1.timestamp_s == pytest.approx(1.10)


def test_ground_truth_interpolation_nearest_and_out_of_range(tmp_path: Path):
    q0 = [0.0, 0.0, 0.0, 1.0]
    q1 = Rotation.from_euler("z", 90, degrees=True).as_quat().tolist()
    gt = [[1.06, 0.0, 0.0, 0.0, *q0], [1.15, 0.9, 1.8, 0.0, *q1]]
    root = _write_tum(tmp_path / "seq", [1.00, 1.10, 1.20], [1.00, 1.10, 1.20], gt_rows=gt)
    cap = TUMCapture(root)
    assert cap[0].T_world_cam is None and cap[2].T_world_cam is None  # outside [1.06, 1.15]
    assert cap.frames_without_gt == (0, 2)
    T = cap[1].T_world_cam  # a = (1.10 - 1.06) / 0.09 = 4/9 of the way
    np.testing.assert_allclose(T[:3, 3], [0.4, 0.8, 0.0], atol=1e-9)
    yaw = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
    np.testing.assert_allclose(yaw, [0, 0, 40], atol=1e-6)
    near = TUMCapture(root, gt="nearest", max_time_diff_s=0.06)
    np.testing.assert_allclose(near[1].T_world_cam, pose_from_tum(np.zeros(3), np.array(q0)), atol=1e-12)
    assert near[2].T_world_cam is not None  # 1.15 is 50 ms from 1.20
    assert TUMCapture(root, gt="nearest")[1].T_world_cam is None  # 40 ms > default 20 ms


def test_ground_truth_gap_is_not_bridged(tmp_path: Path):
    q = [0.0, 0.0, 0.0, 1.0]
    gt = [[0.9, 0.0, 0.0, 0.0, *q], [1.5, 1.0, 0.0, 0.0, *q]]  # 0.6 s mocap dropout
    root = _write_tum(tmp_path / "seq", [1.0], [1.0], gt_rows=gt)
    assert TUMCapture(root)[0].T_world_cam is None


def test_intrinsics_choice(tmp_path: Path):
    size = (640, 480)
    root = _write_tum(tmp_path / "rgbd_dataset_freiburg2_xyz", [1.0], [1.0], size=size)
    cap = TUMCapture(root)
    assert cap.intrinsics_source == "fr2"
    np.testing.assert_allclose(cap.K, make_intrinsics(*TUM_INTRINSICS["fr2"]))
    np.testing.assert_allclose(TUMCapture(root, intrinsics="fr3").K, make_intrinsics(*TUM_INTRINSICS["fr3"]))
    K = make_intrinsics(500.0, 501.0, 320.0, 240.0)
    np.testing.assert_allclose(TUMCapture(root, intrinsics=K)[0].K, K)
    (root / "intrinsics.txt").write_text("400 410 319.5 239.5\n")
    cap = TUMCapture(root)
    np.testing.assert_allclose(cap[0].K, make_intrinsics(400, 410, 319.5, 239.5))
    assert cap.intrinsics_source.endswith("intrinsics.txt")
    with pytest.raises(ValidationError, match="fr9"):
        TUMCapture(root, intrinsics="fr9")


def test_sensor_detected_from_rgb_txt_header(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.0], [1.0], size=(640, 480))
    txt = root / "rgb.txt"
    txt.write_text("# file: 'rgbd_dataset_freiburg3_long_office.bag'\n" + txt.read_text())
    assert TUMCapture(root).intrinsics_source == "fr3"


def test_principal_point_outside_image_names_intrinsics_file(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.0], [1.0])  # 32x24 images
    (root / "intrinsics.txt").write_text("500 500 319.5 239.5\n")  # for 640x480
    with pytest.raises(CaptureFormatError, match="principal point") as e:
        TUMCapture(root)
    assert e.value.path.name == "intrinsics.txt"
    (root / "intrinsics.txt").unlink()
    with pytest.raises(CaptureFormatError, match="principal point"):
        TUMCapture(root)  # fr1 intrinsics do not fit 32x24 either


def test_bad_inputs(tmp_path: Path):
    with pytest.raises(CaptureError, match="not found"):
        TUMCapture(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureFormatError, match="rgb.txt"):
        TUMCapture(tmp_path / "empty")
    root = _write_tum(tmp_path / "far", [1.0], [2.0], size=(640, 480))
    with pytest.raises(CaptureFormatError, match="no colour/depth pairs"):
        TUMCapture(root)
    with pytest.raises(ValidationError, match="gt"):
        TUMCapture(root, gt="linear")


def test_missing_listed_image_skipped_or_strict(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.0, 1.1], [1.0, 1.1], size=(640, 480))
    (root / "rgb" / "1.100000.png").unlink()
    assert len(TUMCapture(root)) == 1 and TUMCapture(root).skipped_missing == 1
    with pytest.raises(CaptureError, match="1.100000.png"):
        TUMCapture(root, strict=True)


def test_eight_bit_depth_and_corrupt_images_named(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.0, 1.1, 1.2], [1.0, 1.1, 1.2], size=(640, 480))
    cv2.imwrite(str(root / "depth" / "1.100000.png"), np.full((480, 640), 7, np.uint8))
    (root / "rgb" / "1.200000.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    cap = TUMCapture(root)
    assert cap[0].depth_m.shape == (480, 640)
    with pytest.raises(CaptureFormatError, match="uint16") as e:
        cap[1]
    assert e.value.path.name == "1.100000.png"
    with pytest.raises(CaptureError, match="corrupt") as e:
        cap[2]
    assert e.value.path.name == "1.200000.png"


def test_colour_depth_size_mismatch(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.0], [1.0], size=(640, 480))
    cv2.imwrite(str(root / "rgb" / "1.000000.png"), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(CaptureFormatError, match="same size"):
        TUMCapture(root)


def test_confidence_list_and_gt_mesh_extensions(tmp_path: Path):
    root = _write_tum(tmp_path / "seq", [1.0, 1.1], [1.0, 1.1])
    (root / "confidence").mkdir()
    cv2.imwrite(str(root / "confidence" / "1.000000.png"), np.full((H, W), 2, np.uint8))
    (root / "confidence.txt").write_text("# confidence\n1.000000 confidence/1.000000.png\n")
    (root / "gt_mesh.ply").write_text("ply\n")
    cap = TUMCapture(root)
    assert cap.gt_mesh_path == root / "gt_mesh.ply"
    np.testing.assert_array_equal(cap[0].confidence, np.full((H, W), 2, np.uint8))
    assert cap[1].confidence is None  # no map listed for that depth image
    cv2.imwrite(str(root / "confidence" / "1.000000.png"), np.full((H, W), 9, np.uint8))
    with pytest.raises(CaptureFormatError, match="0/1/2"):
        cap[0]


def test_profile_kinect_depth_range_and_confidence_file(tmp_path: Path):
    cap = TUMCapture(_write_tum(tmp_path / "seq", [1.0, 1.1], [1.0, 1.1]))
    p = cap.profile
    assert (p.kind, p.max_depth_m, p.has_confidence, p.has_color, p.color_registered) == ("tum", 4.0, False,
                                                                                          True, True)
    assert "Kinect" in p.sensor
