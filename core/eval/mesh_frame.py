"""Which frame a mesh file's coordinates are in: the ``<mesh file>.frame.json`` sidecar, and moving a mesh
into another frame before it is evaluated.

A session may write its mesh in a frame other than the reference (ground-truth) frame: the device's world
(ARKit), the first camera's frame, or with axes changed for a viewer (a Y-up GLB). The sidecar beside the
mesh (``mesh.ply`` -> ``mesh.ply.frame.json``) says so::

    {"T_world_file": [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]],  # file -> session world
     "world": "first_camera"}                                                     # what that world is

``T_world_file`` ([4, 4], row-major) maps the file's coordinates to the session's world frame; ``world`` is
one of ``"reference"`` (the capture's reference / ground-truth frame), ``"device"`` (the capture device's
own world, e.g. ARKit's) or ``"first_camera"`` (the first camera's frame). Other keys are kept in ``raw``
and ignored. The reader is tolerant: no sidecar means identity and ``world="unknown"``; a missing
``T_world_file`` means identity; a missing or unrecognised ``world`` means ``"unknown"``. A sidecar that
is not JSON, or whose ``T_world_file`` is not a finite 4x4 with last row ``[0, 0, 0, 1]``, is an error
(applying half of it would give wrong numbers silently).

Example::

    >>> from pathlib import Path
    >>> read_mesh_frame(Path("/nonexistent/mesh.ply")).world
    'unknown'
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from ..errors import CaptureError, ValidationError

__all__ = ["MeshWorld", "MeshFrame", "sidecar_path", "read_mesh_frame", "transform_mesh", "AlignmentLever",
           "alignment_lever"]

MeshWorld = Literal["reference", "device", "first_camera", "unknown"]
_WORLDS = ("reference", "device", "first_camera")


@dataclass(frozen=True, eq=False)
class MeshFrame:
    """What a mesh file's sidecar says about its coordinates.

    Attributes:
        T_world_file: ``[4, 4]`` float64, file coordinates -> the session's world frame (identity without
            a sidecar).
        world: ``"reference"``, ``"device"``, ``"first_camera"`` or ``"unknown"`` (no sidecar, or it does
            not say).
        path: the sidecar read, or ``None`` when there was none.
        raw: the sidecar's JSON object (``{}`` without one).
    """

    T_world_file: np.ndarray = field(default_factory=lambda: np.eye(4))
    world: MeshWorld = "unknown"
    path: Path | None = None
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def is_identity(self) -> bool:
        return bool(np.allclose(self.T_world_file, np.eye(4), atol=1e-12))

    def summary(self) -> dict:
        """JSON-friendly: sidecar path, world and ``T_world_file``."""
        return {"sidecar": None if self.path is None else str(self.path), "world": self.world,
                "T_world_file": self.T_world_file.tolist()}


def sidecar_path(mesh_path: str | Path) -> Path:
    """``mesh.ply`` -> ``mesh.ply.frame.json`` (beside the mesh)."""
    mesh_path = Path(mesh_path)
    return mesh_path.with_name(mesh_path.name + ".frame.json")


def read_mesh_frame(mesh_path: str | Path) -> MeshFrame:
    """Read ``<mesh_path>.frame.json`` if it exists (module docstring); identity / ``"unknown"`` otherwise.

    Raises:
        CaptureError: the sidecar exists but is not a JSON object, or its ``T_world_file`` is not a finite
            ``[4, 4]`` affine matrix (names the file).
    """
    path = sidecar_path(mesh_path)
    if not path.is_file():
        return MeshFrame()
    try:
        raw = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CaptureError(path, f"cannot read the mesh frame sidecar: {e}") from e
    if not isinstance(raw, dict):
        raise CaptureError(path, "the mesh frame sidecar must hold a JSON object")
    T = np.eye(4)
    if raw.get("T_world_file") is not None:
        try:
            T = np.asarray(raw["T_world_file"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise CaptureError(path, f"T_world_file is not a 4x4 matrix of numbers: {e}") from e
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise CaptureError(path, f"T_world_file must be a finite 4x4 matrix, got shape {T.shape}")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9) or abs(np.linalg.det(T[:3, :3])) < 1e-12:
            raise CaptureError(path, "T_world_file must be an invertible affine transform (last row 0 0 0 1)")
    world = raw.get("world")
    return MeshFrame(T, world if world in _WORLDS else "unknown", path, raw)


def transform_mesh(mesh: trimesh.Trimesh, T: np.ndarray, scale: float = 1.0) -> trimesh.Trimesh:
    """A copy of ``mesh`` with every vertex ``v`` moved to ``R (scale * v) + t`` (``T = [R t; 0 1]``).

    This is the convention of :class:`~.trajectory.ATEResult` (``T_align``, ``scale``), so the estimate's
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
