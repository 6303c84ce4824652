import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.geometry import (
    backproject_depth,
    check_intrinsics,
    check_rigid,
    invert_pose,
    make_intrinsics,
    opencv_to_opengl,
    opengl_to_opencv,
    pose_from_tum,
    pose_to_tum,
    scale_intrinsics,
)
from voxfusion.core.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return T


def test_tum_quaternion_round_trip():
    T = random_poses(20)
    t, q = pose_to_tum(T)
    np.testing.assert_allclose(pose_from_tum(t, q), T, atol=1e-12)


def test_gl_cv_conversion_is_involution_and_flips_viewing_axis():
    T = random_poses(5)
    np.testing.assert_allclose(opencv_to_opengl(opengl_to_opencv(T)), T, atol=1e-12)
    # An OpenGL camera looks along its -z; after conversion the OpenCV camera looks along +z: same ray.
    T_gl = T[0]
    forward_gl = T_gl[:3, :3] @ np.array([0, 0, -1.0])
    forward_cv = opengl_to_opencv(T_gl)[:3, :3] @ np.array([0, 0, 1.0])
    np.testing.assert_allclose(forward_gl, forward_cv, atol=1e-12)


def test_invert_pose():
    T = random_poses(4)
    np.testing.assert_allclose(invert_pose(T) @ T, np.tile(np.eye(4), (4, 1, 1)), atol=1e-12)


def test_check_rigid_rejects_bad_poses():
    check_rigid(np.eye(4))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValidationError, match="rigid"):
        check_rigid(bad, "pose")
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(ValidationError, match="non-finite"):
        check_rigid(nan)
    with pytest.raises(ShapeError):
        check_rigid(np.eye(3))


def test_intrinsics_checks_and_scaling():
    K = make_intrinsics(1000.0, 1000.0, 960.0, 720.0)
    with pytest.raises(ValidationError, match="another resolution"):
        check_intrinsics(K, 256, 192)
    K_d = scale_intrinsics(K, (1920, 1440), (256, 192))
    check_intrinsics(K_d, 256, 192)
    np.testing.assert_allclose(np.diag(K_d)[:2], [1000 * 256 / 1920] * 2)
    with pytest.raises(ValidationError, match="focal"):
        check_intrinsics(make_intrinsics(0.0, 1.0, 1.0, 1.0), 4, 4)


def test_backproject_round_trip():
    K = make_intrinsics(50.0, 50.0, 16.0, 12.0)
    depth = np.full((24, 32), 2.0, np.float32)
    depth[0, 0] = 0
    pts = backproject_depth(depth, K)
    assert pts.shape == (24 * 32 - 1, 3)
    uv = pts[:, :2] / pts[:, 2:] * 50.0 + [16.0, 12.0]
    assert np.all((uv >= 0) & (uv < [32, 24]))
    T = random_poses(1)[0]
    np.testing.assert_allclose(backproject_depth(depth, K, T), pts @ T[:3, :3].T + T[:3, 3])


def test_tum_trajectory_file_round_trip(tmp_path):
    traj = Trajectory(np.arange(5) * 0.1 + 1e9, random_poses(5))
    back = read_tum_trajectory(write_tum_trajectory(tmp_path / "t.txt", traj))
    np.testing.assert_allclose(back.T_world_cam, traj.T_world_cam, atol=1e-8)
    np.testing.assert_allclose(back.timestamps_s, traj.timestamps_s, atol=1e-6)


def test_tum_trajectory_errors_name_file_and_line(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("# c\n1 2 3\n")
    with pytest.raises(Exception, match=r"bad.txt.*line 2"):
        read_tum_trajectory(p)
    with pytest.raises(Exception, match="not found"):
        read_tum_trajectory(tmp_path / "nope.txt")


def test_scale_motion_is_constant_velocity_on_se3():
    """Twice a motion is the motion applied twice; half of it, applied twice, is the motion."""
    import torch

    from voxfusion.core.geometry import scale_motion
    from voxfusion.core.lie import se3_exp

    T = se3_exp(torch.tensor([0.05, -0.02, 0.03, 0.1, -0.2, 0.05], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(scale_motion(T, 2.0), T @ T, atol=1e-10)
    half = scale_motion(T, 0.5)
    np.testing.assert_allclose(half @ half, T, atol=1e-10)
    assert scale_motion(T, 1.0) is not None and np.allclose(scale_motion(T, 1.0), T)


def test_scale_motion_of_a_half_turn_is_left_unscaled_not_an_error():
    """~180 degrees has no usable log; the motion prior must not raise inside a tracking worker."""
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[:3, 3] = (0.1, 0.0, 0.0)
    from voxfusion.core.geometry import scale_motion

    np.testing.assert_allclose(scale_motion(T, 1.5), T)
