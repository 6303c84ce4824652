"""SE(3) exponential and logarithm maps in torch (exp differentiable), the one place poses are perturbed.

Tangent vectors are ``xi = [rho (3), phi (3)]``: ``rho`` the translational part (metres), ``phi`` the
rotation vector (radians). Perturbations are applied on the **right** (in the camera frame):
``T_world_cam' = T_world_cam @ exp(xi)``, so ``phi`` rotates about the camera's own axes and ``rho``
moves along them (x right, y down, z forward), and ``xi = 0`` is the identity.
"""

from __future__ import annotations

import numpy as np
import torch

from .errors import ShapeError

__all__ = ["skew", "so3_exp", "se3_exp", "se3_log", "perturb_right", "se3_exp_np", "se3_log_np"]


def skew(v: torch.Tensor) -> torch.Tensor:
    """``[..., 3] -> [..., 3, 3]`` cross-product matrices."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([
        torch.stack([z, -w, y], -1),
        torch.stack([w, z, -x], -1),
        torch.stack([-y, x, z], -1),
    ], -2)


def _coefficients(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3`` with Taylor series near 0."""
    small = theta2 < 1e-8
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    A = torch.where(small, 1 - theta2 / 6, torch.sin(t) / t)
    B = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(t)) / t2)
    C = torch.where(small, 1.0 / 6 - theta2 / 120, (t - torch.sin(t)) / (t2 * t))
    return A, B, C


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rotation vectors ``[..., 3]`` -> rotation matrices ``[..., 3, 3]`` (Rodrigues)."""
    theta2 = (phi * phi).sum(-1)
    A, B, _ = _coefficients(theta2)
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + A[..., None, None] * K + B[..., None, None] * (K @ K)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Tangent vectors ``[..., 6]`` (rho, phi) -> rigid transforms ``[..., 4, 4]``."""
    if xi.shape[-1] != 6:
        raise ShapeError("xi", tuple(xi.shape), "[..., 6]")
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = (phi * phi).sum(-1)
    A, B, C = _coefficients(theta2)
    K = skew(phi)
    KK = K @ K
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(K.shape)
    R = eye + A[..., None, None] * K + B[..., None, None] * KK
    V = eye + B[..., None, None] * K + C[..., None, None] * KK
    t = (V @ rho[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], -1)
    # [0, 0, 0, 1] from fills (a scalar written by indexing is a host-to-device copy, which graph capture refuses)
    bottom = torch.cat([torch.zeros(xi.shape[:-1] + (1, 3), dtype=xi.dtype, device=xi.device),
                        torch.ones(xi.shape[:-1] + (1, 1), dtype=xi.dtype, device=xi.device)], -1)
    return torch.cat([top, bottom], -2)


def perturb_right(T_world_cam: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """``T_world_cam @ exp(xi)``: ``[..., 4, 4]`` and ``[..., 6]`` -> ``[..., 4, 4]`` (differentiable in xi)."""
    return T_world_cam.to(xi.dtype) @ se3_exp(xi)


def _coefficients_np(theta2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_coefficients` in numpy (for :func:`se3_exp_np` and :func:`se3_log_np`)."""
    small = theta2 < 1e-8
    t2 = np.where(small, 1.0, theta2).astype(theta2.dtype, copy=False)
    t = np.sqrt(t2)
    A = np.where(small, 1 - theta2 / 6, np.sin(t) / t)
    B = np.where(small, 0.5 - theta2 / 24, (1 - np.cos(t)) / t2)
    C = np.where(small, 1.0 / 6 - theta2 / 120, (t - np.sin(t)) / (t2 * t))
    return A, B, C


def se3_exp_np(xi: np.ndarray) -> np.ndarray:
    """:func:`se3_exp` of a numpy array ``[..., 6]`` -> ``[..., 4, 4]`` of the same float dtype: for host-side
    pose arithmetic (:func:`~.geometry.scale_motion`, the motion prior of every frame), where torch's ~40 operators
    on one pose took ~0.35 ms a call and these ~25 numpy operations ~0.1 ms (2-core AMD EPYC). Equal to
    :func:`se3_exp` to float64 rounding (tested); the torch version is the one tensors on any device use."""
    xi = np.asarray(xi)
    if xi.shape[-1] != 6:
        raise ShapeError("xi", tuple(xi.shape), "[..., 6]")
    rho, phi = xi[..., :3], xi[..., 3:]
    A, B, C = (c[..., None, None] for c in _coefficients_np((phi * phi).sum(-1)))
    K = np.zeros(xi.shape[:-1] + (3, 3), dtype=xi.dtype)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -phi[..., 2], phi[..., 1], -phi[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = phi[..., 2], -phi[..., 1], phi[..., 0]
    KK = K @ K
    eye = np.eye(3, dtype=xi.dtype)
    out = np.zeros(xi.shape[:-1] + (4, 4), dtype=xi.dtype)
    out[..., :3, :3] = eye + A * K + B * KK
    out[..., :3, 3] = ((eye + B * K + C * KK) @ rho[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Rigid transform ``[4, 4]`` -> tangent vector ``[6]`` (rho, phi) with ``se3_exp(se3_log(T)) == T``.

    Closed form (the inverse of :func:`se3_exp`): ``theta = arccos((tr R - 1) / 2)``,
    ``phi = theta / (2 sin theta) * vee(R - R^T)``, ``rho = V^-1 t``. Rotations must be below 180 degrees
    (within about 0.06 degrees of 180 the rotation axis is ill-conditioned from ``R - R^T`` alone);
    :class:`ValueError` beyond that. Not differentiated anywhere; float64 recommended.
    """
    if T.shape != (4, 4):
        raise ShapeError("T", tuple(T.shape), "[4, 4]")
    R, t = T[:3, :3], T[:3, 3]
    cos = ((R.diagonal().sum() - 1) / 2).clamp(-1.0, 1.0)
    theta = torch.arccos(cos)
    if float(theta) > torch.pi - 1e-3:
        raise ValueError(f"se3_log needs a rotation below 180 degrees, got {float(theta) * 180 / torch.pi:.3f}")
    w = torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    theta2 = theta * theta
    small = theta2 < 1e-8
    scale = torch.where(small, 0.5 + theta2 / 12, theta / (2 * torch.sin(torch.where(small, torch.ones_like(theta),
                                                                                      theta))))
    phi = scale * w
    _, B, C = _coefficients((phi * phi).sum())
    K = skew(phi)
    V = torch.eye(3, dtype=T.dtype, device=T.device) + B * K + C * (K @ K)
    rho = torch.linalg.solve(V, t)
    return torch.cat([rho, phi])


def se3_log_np(T: np.ndarray) -> np.ndarray:
    """:func:`se3_log` of a numpy ``[4, 4]`` -> ``[6]`` (the same closed form and the same :class:`ValueError`)."""
    T = np.asarray(T)
    if T.shape != (4, 4):
        raise ShapeError("T", tuple(T.shape), "[4, 4]")
    R, t = T[:3, :3], T[:3, 3]
    theta = np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    if theta > np.pi - 1e-3:
        raise ValueError(f"se3_log needs a rotation below 180 degrees, got {float(theta) * 180 / np.pi:.3f}")
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]], dtype=T.dtype)
    theta2 = theta * theta
    small = theta2 < 1e-8
    phi = (0.5 + theta2 / 12 if small else theta / (2 * np.sin(theta))) * w
    _, B, C = _coefficients_np(np.asarray((phi * phi).sum()))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]], dtype=T.dtype)
    V = np.eye(3, dtype=T.dtype) + B * K + C * (K @ K)
    return np.concatenate([np.linalg.solve(V, t), phi]).astype(T.dtype, copy=False)
