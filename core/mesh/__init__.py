"""Mesh outputs: sparse marching cubes over allocated voxels, and mesh files (PLY, GLB, OBJ)."""

from .export import MESH_FORMATS, MeshFormat, export_mesh, mesh_bytes
from .extract import GREY_RGB, QueryFn, extract_mesh

__all__ = ["extract_mesh", "QueryFn", "GREY_RGB", "export_mesh", "mesh_bytes", "MESH_FORMATS", "MeshFormat"]
