"""Mesh files: binary PLY with vertex colours, GLB (glTF binary) and OBJ, via trimesh.

PLY and OBJ keep the session's world axes; GLB is written in glTF's Y-up convention when the caller says
where "up" is (:class:`.frame.WorldAxes`). :func:`export_mesh` writes a ``<file>.frame.json`` sidecar beside
every file saying which frame its coordinates are in (:mod:`.frame`). USDZ is not offered: the one
maintained writer on Linux is Pixar's ``usd-core`` (a ~100 MB dependency) and GLB covers the same viewers
(Apple's Quick Look converts glTF through Reality Converter).

The format always follows the file suffix (or a bare format name for in-memory bytes, as the server
sends them); anything else is a :class:`~voxfusion.core.errors.ValidationError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import trimesh
from trimesh.exchange.obj import export_obj
from trimesh.exchange.ply import export_ply

from ..errors import ValidationError
from .mesh_frame import WorldAxes, write_mesh_frame

__all__ = ["MESH_FORMATS", "MeshFormat", "mesh_bytes", "export_mesh"]

MeshFormat = Literal["ply", "glb", "obj"]
MESH_FORMATS: tuple[str, ...] = ("ply", "glb", "obj")
"""Supported formats: ``ply`` binary little-endian with uchar RGBA vertex colours, ``glb`` with a
``COLOR_0`` vertex attribute, ``obj`` with ``v x y z r g b`` vertex colours (floats in [0, 1])."""


def mesh_bytes(mesh: trimesh.Trimesh, fmt: str, axes: WorldAxes | None = None) -> bytes:
    """Encode ``mesh`` as ``fmt`` (``"ply"``, ``"glb"`` or ``"obj"``, case-insensitive, leading dot allowed).

    With ``axes``, a GLB is rotated into glTF's Y-up axes (``axes.T_file_world("glb")``); without, every
    format keeps the mesh's coordinates.

    Example:
        >>> mesh = trimesh.creation.box()
        >>> mesh_bytes(mesh, "ply")[:35]
        b'ply\\nformat binary_little_endian 1.0'
    """
    fmt = _format(fmt, "fmt")
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValidationError("mesh", f"must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if axes is not None and fmt == "glb":
        mesh = mesh.copy()
        mesh.apply_transform(axes.T_file_world(fmt))
    if fmt == "ply":
        return export_ply(mesh, encoding="binary", vertex_normal=False, include_attributes=False)
    if fmt == "obj":
        return export_obj(mesh, include_normals=False, include_color=True, include_texture=False).encode()
    if len(mesh.faces) == 0:
        raise ValidationError("mesh", "glb needs at least one face; the mesh is empty")
    return mesh.export(file_type="glb", include_normals=False)


def export_mesh(mesh: trimesh.Trimesh, path_or_format: str | Path, axes: WorldAxes | None = None) -> Path | bytes:
    """Write ``mesh`` to a file whose suffix (``.ply``, ``.glb``, ``.obj``) picks the format, or encode it.

    A bare format name (``"ply"``, ``".glb"``, ...) returns the encoded bytes (see :func:`mesh_bytes`);
    anything else is a path: the file is written (parent folders must exist) and its ``Path`` returned,
    and with ``axes`` the ``<file>.frame.json`` sidecar is written beside it.
    Raises ``ValidationError`` for an unknown format.
    """
    text = str(path_or_format)
    if not isinstance(path_or_format, Path) and text.lower().lstrip(".") in MESH_FORMATS and "/" not in text:
        return mesh_bytes(mesh, text, axes)
    path = Path(path_or_format)
    fmt = _format(path.suffix, "path")
    path.write_bytes(mesh_bytes(mesh, fmt, axes))
    if axes is not None:
        write_mesh_frame(path, axes.sidecar(path.name, fmt))
    return path


def _format(fmt: str, field: str) -> MeshFormat:
    name = str(fmt).lower().lstrip(".")
    if name not in MESH_FORMATS:
        raise ValidationError(field, f"unknown mesh format {fmt!r}; use one of {', '.join(MESH_FORMATS)}")
    return name  # type: ignore[return-value]
