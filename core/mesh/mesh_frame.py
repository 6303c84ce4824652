"""The frame a mesh file's coordinates are in: the ``<mesh file>.frame.json`` sidecar written beside every
mesh export, and read back by evaluation.

A session's world frame is the capture's reference (ground-truth) frame when its first frame carried a
reference pose, else the device's world (ARKit) when frames carried device poses, else the first camera's
frame (OpenCV axes: x right, y down, z forward). A file may also change axes for a viewer: a GLB is Y-up
(glTF's convention), the others keep the world's axes. The sidecar says both::

    {"T_world_file": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]],  # file -> session world
     "world": "first_camera",                                                     # what that world is
     "T_first_camera_world": [...], "units": "m", "file_axes": "gltf_y_up", "mesh": "mesh.glb"}

``T_world_file`` ([4, 4], row-major) maps the file's coordinates to the session's world frame; ``world`` is
one of ``"reference"``, ``"device"`` or ``"first_camera"``; ``T_first_camera_world`` (when known) maps the
world to the first camera's frame (the inverse of the first pose). Other keys are kept in ``raw``. The
reader is tolerant: no sidecar means identity and ``world="unknown"``; a missing ``T_world_file`` means
identity; a missing or unrecognised ``world`` means ``"unknown"``. A sidecar that is not JSON, or whose
``T_world_file`` is not a finite 4x4 with last row ``[0, 0, 0, 1]``, is an error (applying half of it would
give wrong numbers silently).

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

from ..errors import CaptureError, ValidationError

__all__ = ["MeshWorld", "MeshFrame", "sidecar_path", "read_mesh_frame", "frame_sidecar", "write_mesh_frame",
           "T_GLTF_WORLD", "gltf_from_world", "camera_up_forward", "WorldAxes"]

T_GLTF_WORLD = np.diag([1.0, -1.0, -1.0, 1.0])
"""``[4, 4]`` world (OpenCV camera axes: y down, z forward) -> glTF's Y-up axes (a half turn about x: y up,
the first camera looking down -z as glTF cameras do). Its own inverse."""

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


def frame_sidecar(mesh_name: str, world: MeshWorld, T_world_file: np.ndarray | None = None,
                  T_first_camera_world: np.ndarray | None = None, file_axes: str = "world") -> dict:
    """The sidecar's JSON object for a mesh file named ``mesh_name`` (module docstring)."""
    if world not in _WORLDS:
        raise ValidationError("world", f"must be one of {', '.join(_WORLDS)}, got {world!r}")
    T = np.eye(4) if T_world_file is None else np.asarray(T_world_file, dtype=np.float64)
    out = {"mesh": mesh_name, "units": "m", "world": world, "file_axes": file_axes,
           "T_world_file": T.tolist()}
    if T_first_camera_world is not None:
        out["T_first_camera_world"] = np.asarray(T_first_camera_world, dtype=np.float64).tolist()
    return out


def write_mesh_frame(mesh_path: str | Path, sidecar: dict) -> Path:
    """Write ``sidecar`` (:func:`frame_sidecar`) to ``<mesh_path>.frame.json``; returns its path."""
    path = sidecar_path(mesh_path)
    path.write_text(json.dumps(sidecar, indent=2) + "\n")
    return path


@dataclass(frozen=True)
class WorldAxes:
    """What a session knows about its world frame, for writing mesh files and their sidecars.

    Attributes:
        world: ``"reference"``, ``"device"`` or ``"first_camera"`` (module docstring).
        up_m: ``[3]`` unit "up" direction in the world (for the Y-up GLB).
        forward_m: ``[3]`` unit viewing direction of the first camera in the world.
        T_first_camera_world: ``[4, 4]`` world -> first camera frame (inverse of the first pose), or None.
    """

    world: MeshWorld = "first_camera"
    up_m: tuple[float, float, float] = (0.0, -1.0, 0.0)
    forward_m: tuple[float, float, float] = (0.0, 0.0, 1.0)
    T_first_camera_world: np.ndarray | None = None

    def T_file_world(self, fmt: str) -> np.ndarray:
        """``[4, 4]`` world -> file coordinates for format ``fmt``: glTF's Y-up for ``glb``, else identity."""
        if str(fmt).lower().lstrip(".") != "glb":
            return np.eye(4)
        return gltf_from_world(np.asarray(self.up_m), np.asarray(self.forward_m))

    def sidecar(self, mesh_name: str, fmt: str) -> dict:
        """The ``.frame.json`` object for a ``fmt`` file named ``mesh_name`` written with these axes (plus
        ``up`` and ``forward``, so :meth:`from_sidecar` can rebuild them)."""
        glb = str(fmt).lower().lstrip(".") == "glb"
        out = frame_sidecar(mesh_name, self.world, np.linalg.inv(self.T_file_world(fmt)),
                            self.T_first_camera_world, "gltf_y_up" if glb else "world")
        return {**out, "up": list(self.up_m), "forward": list(self.forward_m)}

    @classmethod
    def from_sidecar(cls, raw: dict) -> WorldAxes:
        """Rebuild from a :meth:`sidecar` object (defaults for what it lacks)."""
        world = raw.get("world") if raw.get("world") in _WORLDS else "first_camera"
        T = raw.get("T_first_camera_world")
        return cls(world, tuple(raw.get("up", cls.up_m)), tuple(raw.get("forward", cls.forward_m)),
                   None if T is None else np.asarray(T, dtype=np.float64))


def gltf_from_world(up_world: np.ndarray, forward_world: np.ndarray) -> np.ndarray:
    """``[4, 4]`` rotation from world axes to glTF's: ``up_world`` -> +Y, ``forward_world`` (made orthogonal
    to up) -> -Z, so a viewer shows the scene upright and starts looking where the first camera looked.
    For a first-camera world held upright (up = -y, forward = +z) this is :data:`T_GLTF_WORLD`."""
    up = np.asarray(up_world, dtype=np.float64)
    up = up / np.linalg.norm(up)
    fwd = np.asarray(forward_world, dtype=np.float64)
    fwd = fwd - up * float(fwd @ up)
    if np.linalg.norm(fwd) < 1e-6:  # looking straight up or down: any horizontal direction will do
        fwd = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    z = -fwd / np.linalg.norm(fwd)
    x = np.cross(up, z)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, up, z])
    return T


def camera_up_forward(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimated world "up" (mean of the cameras' -y axes: hand-held and mounted cameras are mostly upright)
    and the first camera's viewing direction (+z), from poses ``[N, 4, 4]`` (OpenCV axes)."""
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    up = -T[:, :3, 1].sum(axis=0)
    if np.linalg.norm(up) < 1e-9:
        up = -T[0, :3, 1]
    return up / np.linalg.norm(up), T[0, :3, 2].copy()
