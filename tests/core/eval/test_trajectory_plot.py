"""The trajectory plot: which world axes it draws, the picture itself (written, its size, not blank, the
reference drawn only when it aligns), bad input named, and ``run_capture`` writing ``trajectory.png``."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import TransformedCapture
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.eval import TrajectoryEvalConfig, plot_axes, plot_trajectory
from voxfusion.core.trajectory import Trajectory

BLUE = np.array([180, 119, 31])  # matplotlib's tab:blue (0x1f77b4) as OpenCV BGR
ORANGE = np.array([14, 127, 255])  # the reference's tab:orange (0xff7f0e) as BGR
PURPLE = np.array([189, 103, 148])  # the limited frames' tab:purple (0x9467bd) as BGR


@pytest.mark.parametrize(("up", "horizontal", "vertical", "sign", "label"), [
    ((0.0, 0.0, 1.0), (0, 1), 2, 1.0, "height (+z) [m]"),       # motion capture / TUM: z up
    ((0.0, -1.0, 0.0), (0, 2), 1, -1.0, "height (-y) [m]"),     # first camera (OpenCV y down)
    ((0.05, 0.99, 0.1), (2, 0), 1, 1.0, "height (+y) [m]"),     # ARKit: y up, a tilted estimate of it
    ((-2.0, 0.3, 0.0), (2, 1), 0, -1.0, "height (-x) [m]"),
])
def test_axes_follow_the_world_axis_nearest_up_seen_from_above(up, horizontal, vertical, sign, label):
    axes = plot_axes(up)
    assert (axes.horizontal, axes.vertical, axes.sign, axes.height_label) == (horizontal, vertical, sign, label)
    e = np.eye(3)
    a, b = axes.horizontal
    assert np.cross(e[a], e[b]) @ (sign * e[vertical]) == 1.0  # right-handed looking down: never mirrored


def test_bad_up_is_named():
    with pytest.raises(ValidationError) as err:
        plot_axes((0.0, 0.0, 0.0))
    assert err.value.field == "up_m"
    with pytest.raises(ShapeError):
        plot_axes((0.0, 1.0))


def _loop(n: int = 60) -> Trajectory:
    """A camera walking an ellipse at 1.5 m height (z up), bobbing by 5 cm, 30 poses per second."""
    t = np.arange(n) / 30.0
    ang = np.linspace(0, 2 * np.pi, n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.stack([2.0 * np.cos(ang), np.sin(ang), 1.5 + 0.05 * np.sin(5 * ang)], axis=1)
    T[:, :3, :3] = Rotation.from_euler("z", ang[:, None]).as_matrix()
    return Trajectory(t, T)


def _moved(traj: Trajectory, noise_m: float = 0.01) -> Trajectory:
    """``traj`` in another world frame (rotated and shifted), with ``noise_m`` of noise: an estimate."""
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("xyz", [10, -20, 75], degrees=True).as_matrix()
    G[:3, 3] = [3.0, -1.0, 0.5]
    T = G @ traj.T_world_cam
    T[:, :3, 3] += np.random.default_rng(0).normal(0, noise_m, (len(traj), 3))
    return Trajectory(traj.timestamps_s, T)


def _pixels_near(img: np.ndarray, bgr: np.ndarray, tol: int = 30) -> int:
    return int((np.abs(img.astype(int) - bgr).max(axis=2) < tol).sum())


def test_estimate_beside_the_aligned_reference(tmp_path):
    ref = _loop()
    path = plot_trajectory(tmp_path / "plots" / "trajectory.png", _moved(ref), (0.0, 0.0, 1.0), ref,
                           TrajectoryEvalConfig(align="se3", max_diff_s=1e-3), title="loop")
    img = cv2.imread(str(path))
    assert img is not None and img.shape == (460, 1100, 3)
    assert 20_000 < path.stat().st_size < 1_000_000
    assert _pixels_near(img, BLUE) > 500 and _pixels_near(img, ORANGE) > 300  # both curves drawn
    assert (img < 250).any(axis=2).mean() > 0.03  # not a blank page


def test_alignment_puts_the_estimate_on_the_reference(tmp_path):
    """An exact estimate in another world frame is drawn exactly where the reference itself would be: below
    the title (which states the ATE) the two pictures are the same."""
    ref = _loop()
    moved = cv2.imread(str(plot_trajectory(tmp_path / "a.png", _moved(ref, noise_m=0.0), (0, 0, 1), ref)))
    itself = cv2.imread(str(plot_trajectory(tmp_path / "r.png", ref, (0, 0, 1), ref)))
    differ = np.abs(moved.astype(int) - itself.astype(int)).max(axis=2) > 40
    assert differ[60:].mean() < 1e-3, differ[60:].sum()


def test_estimate_only(tmp_path):
    est = _moved(_loop(20))
    lost = np.zeros(20, dtype=bool)
    lost[[5, 6]] = True
    limited = np.zeros(20, dtype=bool)
    limited[[10, 11]] = True
    path = plot_trajectory(tmp_path / "alone.png", est, (0.0, 1.0, 0.0), lost=lost, limited=limited)
    img = cv2.imread(str(path))
    assert img.shape == (460, 1100, 3) and path.stat().st_size > 20_000
    assert _pixels_near(img, BLUE) > 300 and _pixels_near(img, ORANGE) == 0  # no reference curve
    assert _pixels_near(img, np.array([40, 39, 214])) > 20  # tab:red crosses at the lost frames
    assert _pixels_near(img, PURPLE) > 20  # tab:purple triangles at the limited ones
    plain = cv2.imread(str(plot_trajectory(tmp_path / "plain.png", est, (0.0, 1.0, 0.0), lost=lost)))
    assert _pixels_near(plain, PURPLE) == 0


def test_reference_that_does_not_associate_is_left_out(tmp_path):
    ref = _loop(20)
    late = Trajectory(ref.timestamps_s + 100.0, ref.T_world_cam)  # another clock: nothing pairs
    img = cv2.imread(str(plot_trajectory(tmp_path / "x.png", late, (0, 0, 1), ref)))
    assert _pixels_near(img, BLUE) > 300 and _pixels_near(img, ORANGE) == 0


def test_bad_input_is_named(tmp_path):
    with pytest.raises(ValidationError) as err:
        plot_trajectory(tmp_path / "e.png", Trajectory(np.zeros(0), np.zeros((0, 4, 4))), (0, 0, 1))
    assert err.value.field == "estimate"
    with pytest.raises(ShapeError) as err:
        plot_trajectory(tmp_path / "e.png", _loop(5), (0, 0, 1), lost=np.zeros(4, dtype=bool))
    assert err.value.field == "lost"
    with pytest.raises(ShapeError) as err:
        plot_trajectory(tmp_path / "e.png", _loop(5), (0, 0, 1), limited=np.zeros(6, dtype=bool))
    assert err.value.field == "limited"
    assert not (tmp_path / "e.png").exists()


TINY = ["mapping.first_frame_iters=3", "mapping.iters=1", "mapping.rays_per_frame=64", "tracking.iters=2",
        "tracking.rays=64", "mesh_res=2", "field.sdf_hidden=16", "field.color_hidden=16"]


@pytest.mark.parametrize("with_reference", [True, False])
def test_run_writes_trajectory_png(tmp_path, with_reference):
    from voxfusion.core.run import run_capture
    from voxfusion.core.slam.presets import load_preset

    cap = SyntheticCapture(SyntheticConfig(n_frames=4, width=32, height=24))
    if not with_reference:  # the same frames without their reference poses
        cap = TransformedCapture(cap, lambda f: dataclasses.replace(f, T_world_cam=None))
    cfg = load_preset("cpu", TINY, profile=cap.profile)
    result = run_capture(cap, cfg, tmp_path / "run", progress=False, evaluate=False)
    path = tmp_path / "run" / "trajectory.png"
    img = cv2.imread(str(path))
    assert img is not None and img.shape == (460, 1100, 3)
    assert _pixels_near(img, BLUE) > 100
    assert (_pixels_near(img, ORANGE) > 100) == with_reference
    assert (result.reference is not None) == with_reference
