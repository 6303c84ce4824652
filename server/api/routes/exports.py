"""Map downloads: the mesh (PLY / GLB / OBJ, cached per map version) and the voxel map (NPZ / PLY)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from voxfusion.proto.schemas import ErrorOut

from ...outputs import MESH_MEDIA_TYPES, VOXEL_MEDIA_TYPES, MeshDetail
from ..deps import ManagerDep, SessionIdDep

__all__ = ["router"]

router = APIRouter(tags=["map"], responses={401: {"model": ErrorOut}, 403: {"model": ErrorOut},
                                            404: {"model": ErrorOut}, 409: {"model": ErrorOut}})


def _file_response(request: Request, data: bytes, version: int, media_type: str, filename: str,
                   variant: str = "") -> Response:
    etag = f'"v{version}{variant}-{len(data)}"'
    headers = {"ETag": etag, "X-Map-Version": str(version), "Cache-Control": "no-cache",
               "Content-Disposition": f'attachment; filename="{filename}"'}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    return Response(data, media_type=media_type, headers=headers)


@router.get("/sessions/{session_id}/mesh", response_class=Response,
            responses={200: {"content": {t: {} for t in sorted(set(MESH_MEDIA_TYPES.values()))}}})
def get_mesh(session_id: SessionIdDep, manager: ManagerDep, request: Request,
             format: Annotated[Literal["ply", "glb", "obj"], Query(description="ply, glb or obj")] = "ply",
             detail: Annotated[MeshDetail, Query(description="full (the configured resolution) or preview (a "
                                                             "~2.5 cm lattice, several times cheaper: for live "
                                                             "views)")] = "full") -> Response:
    """The mesh of the newest map with vertex colours (PLY binary, GLB, or OBJ); ``ETag`` per map version
    and detail; ``X-Map-Version`` names the map version it was extracted from."""
    data, version = manager.mesh_bytes(session_id, format, detail)
    suffix = "" if detail == "full" else f"-{detail}"
    response = _file_response(request, data, version, MESH_MEDIA_TYPES[format],
                              f"voxfusion-{session_id[:8]}-v{version}{suffix}.{format}", suffix)
    frame = manager.mesh_frame(session_id, format)
    response.headers["X-Mesh-World"] = frame["world"]
    response.headers["Link"] = f'</sessions/{session_id}/mesh/frame?format={format}>; rel="describedby"'
    return response


@router.get("/sessions/{session_id}/mesh/frame")
def get_mesh_frame(session_id: SessionIdDep, manager: ManagerDep,
                   format: Annotated[Literal["ply", "glb", "obj"],
                                     Query(description="ply, glb or obj")] = "ply") -> dict:
    """Which frame ``/mesh?format=...`` is in (the same object as a file export's ``.frame.json``):
    ``T_world_file`` (file coordinates -> the session's world; a GLB is Y-up), ``world`` (``reference``,
    ``device`` or ``first_camera``) and ``T_first_camera_world`` (world -> the first camera's frame)."""
    return manager.mesh_frame(session_id, format)


@router.get("/sessions/{session_id}/voxels", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}})
def get_voxels(session_id: SessionIdDep, manager: ManagerDep, request: Request,
               format: Annotated[Literal["npz", "ply"], Query(description="npz or ply")] = "npz") -> Response:
    """The sparse voxel map: NPZ (codes, embeddings, decoder weights: everything to rebuild the field) or
    a PLY point cloud of voxel centres."""
    data, version = manager.voxels_bytes(session_id, format)
    return _file_response(request, data, version, VOXEL_MEDIA_TYPES[format],
                          f"voxfusion-{session_id[:8]}-voxels-v{version}.{format}")
