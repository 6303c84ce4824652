"""Pose and camera conventions, written once.

Conventions (see ../shared/GUIDE.md):

* A pose ``T_world_cam`` is a 4x4 float64 camera-to-world matrix, OpenCV camera axes
  (x right, y down, z forward), metres.
* ARKit / OpenGL poses (y up, camera looks along -z) convert with
  ``T_cv = T_gl @ diag(1, -1, -1, 1)`` (the same matrix converts back).
* Quaternions in files and APIs are ``qx qy qz qw`` (TUM order, scalar last).
* Intrinsics ``K`` (3x3) always refer to a stated image resolution; scale them on resize.
"""

from __future__ import annotations

import numpy as np

from .errors import ShapeError, ValidationError

__all__ = [
    "scale_motion",
    "GL_TO_CV",
    "opengl_to_opencv",
    "opencv_to_opengl",
    "pose_from_tum",
    "pose_to_tum",
    "check_rigid",
    "make_intrinsics",
    "scale_intrinsics",
    "check_intrinsics",
    "backproject_depth",
    "invert_pose",
    "nearest_rigid",
]

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiply an OpenGL/ARKit camera-to-world pose by this to get OpenCV axes (and back)."""


def opengl_to_opencv(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """Convert camera-to-world pose(s) ``[..., 4, 4]`` from OpenGL/ARKit to OpenCV camera axes."""
    return np.asarray(T_world_cam_gl, dtype=np.float64) @ GL_TO_CV


def opencv_to_opengl(T_world_cam_cv: np.ndarray) -> np.ndarray:
    """Convert camera-to-world pose(s) ``[..., 4, 4]`` from OpenCV to OpenGL/ARKit camera axes."""
    return np.asarray(T_world_cam_cv, dtype=np.float64) @ GL_TO_CV


def pose_from_tum(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """Build 4x4 pose(s) from translation ``[..., 3]`` and quaternion ``[..., 4]`` (qx qy qz qw)."""
    t_xyz = np.asarray(t_xyz, dtype=np.float64)
    q_xyzw = np.asarray(q_xyzw, dtype=np.float64)
    batch = t_xyz.shape[:-1]
    T = np.zeros(batch + (4, 4))
    from scipy.spatial.transform import Rotation  # here: importing scipy.spatial takes ~0.2 s

    T[..., :3, :3] = Rotation.from_quat(q_xyzw.reshape(-1, 4)).as_matrix().reshape(batch + (3, 3))
    T[..., :3, 3] = t_xyz
    T[..., 3, 3] = 1.0
    return T


def pose_to_tum(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split pose(s) ``[..., 4, 4]`` into translation ``[..., 3]`` and quaternion ``[..., 4]`` (xyzw)."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    batch = T.shape[:-2]
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_quat().reshape(batch + (4,))
    return T[..., :3, 3].copy(), q


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Invert rigid transform(s) ``[..., 4, 4]`` exactly (R^T, -R^T t)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def check_rigid(T: np.ndarray, field: str = "pose", tol: float = 1e-3) -> np.ndarray:
    """Return ``T`` as float64 [4, 4] or raise ``ValidationError`` if it is not a finite rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError(field, T.shape, "(4, 4)")
    if not np.all(np.isfinite(T)):
        raise ValidationError(field, "contains non-finite values")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        raise ValidationError(field, "rotation block is not orthonormal with det +1 (not a rigid pose)")
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > tol:
        raise ValidationError(field, "last row must be [0, 0, 0, 1]")
    return T


def make_intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole intrinsics (float64)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def scale_intrinsics(K: np.ndarray, from_wh: tuple[int, int], to_wh: tuple[int, int]) -> np.ndarray:
    """Rescale intrinsics from resolution ``from_wh`` (width, height) to ``to_wh``.

    Every entry of the first two rows is multiplied by the axis's scale (``fx, cx`` by ``sx``; ``fy, cy``
    by ``sy``), the convention ARKit, Stray Scanner and Record3D exports use for their depth maps.
    """
    sx = to_wh[0] / from_wh[0]
    sy = to_wh[1] / from_wh[1]
    K = np.asarray(K, dtype=np.float64)
    out = K.copy()
    out[0] *= sx
    out[1] *= sy
    return out


def check_intrinsics(K: np.ndarray, width: int, height: int, field: str = "intrinsics") -> np.ndarray:
    """Validate a 3x3 pinhole ``K`` for an image of ``width`` x ``height``; returns float64 K."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ShapeError(field, K.shape, "(3, 3)")
    if not np.all(np.isfinite(K)):
        raise ValidationError(field, "contains non-finite values")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValidationError(field, f"focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]}")
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        raise ValidationError(
            field,
            f"principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the {width}x{height} image; "
            "are the intrinsics for another resolution?",
        )
    return K


def backproject_depth(depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray | None = None,
                      stride: int = 1) -> np.ndarray:
    """Back-project valid depth pixels to 3D points.

    Args:
        depth_m: ``[H, W]`` float32 metres, 0 = invalid.
        K: ``[3, 3]`` intrinsics for this depth resolution.
        T_world_cam: optional ``[4, 4]`` camera-to-world; points are returned in world frame if given.
        stride: take every ``stride``-th pixel in both directions.

    Returns:
        ``[N, 3]`` float64 points (camera frame, or world frame with a pose).
    """
    d = depth_m[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    u = u * stride
    v = v * stride
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    pts = np.stack([x, y, z], axis=-1)
    if T_world_cam is not None:
        pts = pts @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return pts


def scale_motion(T_rel: np.ndarray, ratio: float) -> np.ndarray:
    """A relative motion ``[4, 4]`` stretched to ``ratio`` times its duration at constant velocity:
    ``exp(ratio * log(T_rel))`` on SE(3) (constant angular and linear velocity in the moving frame, a screw
    motion). ``ratio`` 1 returns ``T_rel``, and so does a rotation within ~0.06 degrees of 180 (no usable log).
    """
    T_rel = np.asarray(T_rel, dtype=np.float64)
    if ratio == 1.0:
        return T_rel
    from .lie import se3_exp_np, se3_log_np

    try:
        xi = se3_log_np(nearest_rigid(T_rel))  # closed forms (scipy's logm took ~7 ms per call)
    except ValueError:  # a rotation of ~180 degrees (e.g. across lost frames) has no usable log: do not scale
        return T_rel
    return nearest_rigid(se3_exp_np(ratio * xi))


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """``T`` ``[4, 4]`` with its rotation block replaced by the nearest rotation (SVD) and the last row
    set to ``0 0 0 1``: re-orthonormalises poses composed from many small updates."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1
    T[:3, :3] = U @ Vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T
