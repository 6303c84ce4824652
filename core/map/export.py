"""Voxel map export: NPZ (everything needed to rebuild the field) and a PLY of voxel centres for viewing."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
import trimesh

from ..errors import ValidationError
from .voxel_map import VoxelMap

__all__ = ["VOXEL_FORMATS", "voxels_npz_bytes", "voxels_ply_bytes", "export_voxels"]

VOXEL_FORMATS = ("npz", "ply")


def voxels_npz_bytes(voxel_map: VoxelMap, decoder: torch.nn.Module | None = None) -> bytes:
    """NPZ with ``morton_codes [M]`` int64, ``voxel_coords [M, 3]`` int64, ``centres_m [M, 3]`` float32,
    ``voxel_size_m`` (scalar), ``vertex_codes [V]``, ``voxel_vertex_ids [M, 8]``, ``embeddings [V, D]``
    float32, the observation evidence ``voxel_hits [M]``, ``voxel_free [M]`` float32 and ``voxel_active [M]``
    bool (inactive voxels read as empty, see :mod:`.evidence`) and, with a decoder, one ``decoder/<name>``
    array per parameter."""
    arrays: dict[str, np.ndarray] = {
        "morton_codes": voxel_map.voxel_codes.cpu().numpy(),
        "voxel_coords": voxel_map.voxel_coords.cpu().numpy(),
        "centres_m": voxel_map.voxel_centres_m.detach().cpu().numpy().astype(np.float32),
        "voxel_size_m": np.float64(voxel_map.voxel_size_m),
        "vertex_codes": voxel_map.vertex_codes.cpu().numpy(),
        "voxel_vertex_ids": voxel_map.voxel_vertex_ids.cpu().numpy(),
        "embeddings": voxel_map.embeddings.detach().cpu().numpy(),
        "voxel_hits": voxel_map.voxel_hits.cpu().numpy(),
        "voxel_free": voxel_map.voxel_free.cpu().numpy(),
        "voxel_active": voxel_map.voxel_active.cpu().numpy(),
    }
    if decoder is not None:
        for k, v in decoder.state_dict().items():
            arrays[f"decoder/{k}"] = v.detach().cpu().numpy()
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def voxels_ply_bytes(voxel_map: VoxelMap) -> bytes:
    """Binary PLY point cloud of voxel centres (metres, world frame)."""
    centres = voxel_map.voxel_centres_m.detach().cpu().numpy().astype(np.float64)
    cloud = trimesh.PointCloud(centres if len(centres) else np.zeros((0, 3)))
    return cloud.export(file_type="ply", encoding="binary")


def export_voxels(voxel_map: VoxelMap, path: str | Path, decoder: torch.nn.Module | None = None) -> Path:
    """Write the voxel map to ``path``; the format follows the suffix (``.npz`` or ``.ply``)."""
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower()
    if fmt not in VOXEL_FORMATS:
        raise ValidationError("format", f"unknown voxel format {fmt!r}; use one of {list(VOXEL_FORMATS)}")
    data = voxels_npz_bytes(voxel_map, decoder) if fmt == "npz" else voxels_ply_bytes(voxel_map)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path
