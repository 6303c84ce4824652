"""A session's outputs read back from its folder: finished sessions, and open ones after a restart.

Files in ``<data_dir>/sessions/<id>/``:

=================  ========================================================================
``recording.vxr``  every acknowledged frame (:mod:`voxfusion.proto.recording`)
``checkpoint.pt``  the map (voxels, decoder, keyframes, trajectory, config); periodic + final
``poses.json``     every tracked pose (``PoseOut`` list), written with each checkpoint
``mesh.ply``       the final mesh (at finish)
``trajectory.txt`` the final trajectory, TUM format (at finish)
=================  ========================================================================

Checkpoints are loaded lazily and at most :data:`MAX_LOADED` at a time stay in memory.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from pathlib import Path

import torch
import trimesh

from voxfusion.core.checkpoint import LoadedCheckpoint, load_checkpoint
from voxfusion.core.mesh import mesh_bytes
from voxfusion.core.mesh.mesh_frame import WorldAxes, read_mesh_frame
from voxfusion.core.render.volume import RenderedImage
from voxfusion.core.slam import MapSnapshot
from voxfusion.proto.schemas import PoseOut, RenderRequest

from .errors import NotReadyError
from .outputs import MeshDetail

__all__ = ["CHECKPOINT_FILE", "POSES_FILE", "MESH_FILE", "TRAJECTORY_FILE", "MAX_LOADED", "StoredMap"]

CHECKPOINT_FILE = "checkpoint.pt"
POSES_FILE = "poses.json"
MESH_FILE = "mesh.ply"
TRAJECTORY_FILE = "trajectory.txt"
MAX_LOADED = 4
"""Checkpoints kept loaded across all stored sessions (least recently used are released)."""

_loaded: OrderedDict[tuple[str, int], LoadedCheckpoint] = OrderedDict()
_loaded_lock = threading.Lock()


def _load(path: Path, device: torch.device) -> LoadedCheckpoint:
    key = (str(path), path.stat().st_mtime_ns)
    with _loaded_lock:
        if key in _loaded:
            _loaded.move_to_end(key)
            return _loaded[key]
    ckpt = load_checkpoint(path, device)
    with _loaded_lock:
        for k in [k for k in _loaded if k[0] == key[0]]:
            del _loaded[k]
        _loaded[key] = ckpt
        while len(_loaded) > MAX_LOADED:
            _loaded.popitem(last=False)
    return ckpt


class StoredMap:
    """Poses, mesh, voxels and renders of one session from its folder (see the module docstring)."""

    def __init__(self, folder: Path, device: torch.device) -> None:
        self.folder = Path(folder)
        self.device = device
        self._lock = threading.Lock()
        self._mesh_cache: dict[tuple[int, str, str], bytes] = {}

    @property
    def checkpoint_path(self) -> Path:
        return self.folder / CHECKPOINT_FILE

    def has_map(self) -> bool:
        return self.checkpoint_path.is_file()

    def _checkpoint(self) -> LoadedCheckpoint:
        if not self.has_map():
            raise NotReadyError("this session has no saved map yet (no checkpoint was written)")
        return _load(self.checkpoint_path, self.device)

    def poses(self) -> list[PoseOut]:
        path = self.folder / POSES_FILE
        if not path.is_file():
            return []
        return [PoseOut.model_validate(p) for p in json.loads(path.read_text())]

    def mesh_bytes(self, fmt: str, detail: MeshDetail = "full") -> tuple[bytes, int]:
        """The mesh as ``fmt`` and the map version it belongs to: the final ``mesh.ply`` when it is as new as
        the checkpoint, whatever ``detail`` (it is already made, and coloured from the keyframe images, which
        checkpoints do not keep); else extracted from the checkpoint at ``detail`` (``full``: ``mesh_res``,
        ``preview``: the preview lattice) with the colour head's colours."""
        ckpt = self._checkpoint()
        version = int(ckpt.mapper.version)
        with self._lock:
            cached = self._mesh_cache.get((version, fmt, detail))
            if cached is not None:
                return cached, version
            mesh_file = self.folder / MESH_FILE
            fresh = mesh_file.is_file() and mesh_file.stat().st_mtime_ns >= self.checkpoint_path.stat().st_mtime_ns
            if fresh and fmt == "ply":
                data = mesh_file.read_bytes()
            else:
                res = ckpt.config.preview_mesh_res() if detail == "preview" else ckpt.config.mesh_res
                mesh = (trimesh.load(mesh_file, file_type="ply", process=False) if fresh
                        else MapSnapshot.of(ckpt.mapper).mesh(res, ckpt.config.mesh_support, ckpt.config.mesh_colors))
                data = mesh_bytes(mesh, fmt, self.world_axes())
            self._mesh_cache = {k: v for k, v in self._mesh_cache.items() if k[0] == version}
            self._mesh_cache[(version, fmt, detail)] = data
        return data, version

    def world_axes(self) -> WorldAxes:
        """The session's world axes, from the mesh sidecar written when it finished (a first-camera world
        held upright when there is none)."""
        frame = read_mesh_frame(self.folder / MESH_FILE)
        return WorldAxes.from_sidecar(frame.raw)

    def mesh_frame(self, fmt: str) -> dict:
        """The ``.frame.json`` sidecar of the mesh as ``fmt``."""
        return self.world_axes().sidecar(f"mesh.{fmt}", fmt)

    def voxels_bytes(self, fmt: str) -> tuple[bytes, int]:
        snap = MapSnapshot.of(self._checkpoint().mapper)
        return snap.export(fmt), snap.version

    def render(self, req: RenderRequest) -> tuple[RenderedImage, int]:
        ckpt = self._checkpoint()
        snap = MapSnapshot.of(ckpt.mapper)
        return snap.render(req.K(), req.T_world_cam_cv(), req.width, req.height, ckpt.config.render,
                           with_color=req.with_color), snap.version
