"""Moving a mesh into another frame before it is evaluated: trajectory alignment applied to a mesh, and how
far that alignment's uncertainty can move it. The ``<mesh file>.frame.json`` sidecar (which frame a mesh
file's coordinates are in) is :mod:`voxfusion.core.mesh.mesh_frame`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..errors import ValidationError

__all__ = ["transform_mesh", "AlignmentLever", "alignment_lever"]

def transform_mesh(mesh: trimesh.Trimesh, T: np.ndarray, scale: float = 1.0) -> trimesh.Trimesh:
    """A copy of ``mesh`` with every vertex ``v`` moved to ``R (scale * v) + t`` (``T = [R t; 0 1]``).

    This is the convention of :class:`~.trajectory_error.ATEResult` (``T_align``, ``scale``), so the estimate's
    mesh can follow its trajectory's alignment onto the reference.

    Args:
        mesh: triangle mesh, metres.
        T: ``[4, 4]`` affine transform.
        scale: uniform scale applied before ``T`` (a Sim(3) fit's scale; 1 otherwise).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValidationError("T", f"expected a 4x4 transform, got shape {T.shape}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValidationError("scale", f"must be a finite positive number, got {scale}")
    out = mesh.copy()
    v = scale * np.asarray(mesh.vertices, dtype=np.float64)
    out.vertices = v @ T[:3, :3].T + T[:3, 3]
    return out


@dataclass(frozen=True)
class AlignmentLever:
    """How far a trajectory alignment's uncertainty can move a mesh (a rough, one-sigma-ish estimate).

    A position-only fit (ATE's Umeyama / Horn) constrains rotation about an axis only through the camera
    centres' spread across that axis; a short or straight path leaves the rotation about the path loose, and
    a mesh metres from the cameras swings with it.

    Attributes:
        spread_m: ``[3]`` standard deviations of the camera centres along their principal axes, largest first.
        rotation_deg: rotation uncertainty about the worst axis, ``rmse / (sqrt(n) * spread_perp)``, degrees.
        reach_m: RMS distance of the mesh's vertices from the cameras' centroid, metres.
        mesh_shift_m: ``radians(rotation_deg) * reach_m``: how far the mesh can move through it, metres.
    """

    spread_m: np.ndarray
    rotation_deg: float
    reach_m: float
    mesh_shift_m: float


def alignment_lever(positions_m: np.ndarray, residual_rmse_m: float, mesh: trimesh.Trimesh) -> AlignmentLever:
    """:class:`AlignmentLever` of aligning ``mesh`` with a fit of camera centres ``positions_m`` (``[N, 3]``,
    the frame the mesh is in) that left ``residual_rmse_m`` (the aligned ATE RMSE)."""
    p = np.asarray(positions_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ValidationError("positions_m", f"expected [N >= 2, 3] camera centres, got shape {p.shape}")
    centroid = p.mean(axis=0)
    spread = np.linalg.svd(p - centroid, compute_uv=False) / np.sqrt(len(p))
    perp = float(np.hypot(spread[1], spread[2]))
    rot = float(np.pi) if perp <= 1e-12 else min(float(np.pi), residual_rmse_m / (np.sqrt(len(p)) * perp))
    reach = float(np.sqrt(np.mean(np.sum((np.asarray(mesh.vertices) - centroid) ** 2, axis=1))))
    return AlignmentLever(spread, float(np.degrees(rot)), reach, rot * reach)
