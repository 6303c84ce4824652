"""Mesh outputs: sparse marching cubes over allocated voxels (kept where observations support the surface),
mesh files (PLY, GLB, OBJ), and shaded pictures of meshes (ray-cast views for checking by eye)."""

from .export import MESH_FORMATS, MeshFormat, export_mesh, mesh_bytes
from .extract import GREY_RGB, KeepFn, QueryFn, coarse_res_for, extract_mesh
from .map_mesh import extract_map_mesh
from .support import SurfaceSupport
from .view import (
    LIGHT_GREY_RGB,
    ViewImage,
    intrinsics_from_fov,
    look_at,
    overview_pose,
    render_mesh,
    save_png,
    side_by_side,
    write_mesh_pictures,
    write_scene_views,
)

__all__ = ["extract_mesh", "extract_map_mesh", "coarse_res_for", "SurfaceSupport", "QueryFn", "KeepFn",
           "GREY_RGB", "export_mesh", "mesh_bytes", "MESH_FORMATS", "MeshFormat", "ViewImage", "LIGHT_GREY_RGB",
           "intrinsics_from_fov", "look_at", "overview_pose", "render_mesh", "side_by_side", "save_png",
           "write_mesh_pictures", "write_scene_views"]
