"""The mesh of a neural voxel map: the field's zero level set where observations support it.

One function for every caller (a live session's snapshot, an offline mapper, a stored checkpoint), so
their meshes agree: :func:`extract_map_mesh`.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from ..map import VoxelMap
from ..map.field import SDFDecoder, query
from .colors import ColorView, image_vertex_colors, vertex_normals
from .extract import extract_mesh
from .support import SurfaceSupport

__all__ = ["extract_map_mesh"]


def extract_map_mesh(voxel_map: VoxelMap, decoder: SDFDecoder, mesh_res: int, support: bool = True,
                     support_dilate: int = 1, color_views: list[ColorView] | None = None) -> trimesh.Trimesh:
    """Triangle mesh of the field inside the map's active voxels, with colour-head vertex colours.

    Args:
        voxel_map: the map (read only; a snapshot for a live session).
        decoder: its decoder.
        mesh_res: marching-cubes samples per voxel edge (20 at 0.2 m voxels = a 1 cm lattice).
        support: keep only faces near observed depth (:class:`.support.SurfaceSupport`); ignored for a map
            without observed-surface evidence (an old checkpoint).
        support_dilate: the support's radius in surface cells (1: a face within about 1-2 cells of an
            observed point is kept).
        color_views: posed keyframe images: vertices they see take their colours (:mod:`.colors`), the
            others keep the colour head's; None: colour head only.

    Returns the mesh in the map's world frame (metres); see :func:`.extract.extract_mesh`.
    """
    def field_query(points: torch.Tensor, with_color: bool = True) -> tuple[torch.Tensor, torch.Tensor | None,
                                                                           torch.Tensor]:
        with torch.no_grad():
            return query(voxel_map, decoder, points.to(voxel_map.device), with_color=with_color)

    keep = SurfaceSupport.from_map(voxel_map, support_dilate) if support else None
    mesh = extract_mesh(voxel_map.active_voxel_coords, voxel_map.voxel_size_m, field_query,
                        mesh_res=mesh_res, device=voxel_map.device, keep_fn=keep,
                        lattice_query_fn=lambda p: field_query(p, with_color=False))
    if color_views and len(mesh.faces):
        vertices = torch.from_numpy(np.asarray(mesh.vertices)).to(voxel_map.device)
        faces = torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64)).to(voxel_map.device)
        rgb, seen = image_vertex_colors(vertices, vertex_normals(vertices, faces), color_views)
        colors = np.asarray(mesh.visual.vertex_colors).copy()
        seen_np = seen.cpu().numpy()
        colors[seen_np, :3] = (rgb[seen].cpu().numpy() * 255.0).round().astype(np.uint8)
        mesh.visual.vertex_colors = colors
    return mesh
