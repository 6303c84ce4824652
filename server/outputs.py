"""What the server sends back: poses as JSON / TUM text, rendered depth bodies, mesh and voxel files.

Render answer (``POST /sessions/{id}/render``): one ``application/octet-stream`` body made of up to three
parts back to back, ``depth | mask | color``, with their byte lengths in headers:

===================  =====================================  ==========================================
header               ``format=f16``                          ``format=png16``
===================  =====================================  ==========================================
``X-Depth-Bytes``    ``H*W*2``: float16 LE metres, 0 = none  16-bit greyscale PNG, millimetres, 0 = none
``X-Mask-Bytes``     ``H*W``: uint8 1 = valid, 0 = none       8-bit greyscale PNG, 255 = valid, 0 = none
``X-Color-Bytes``    ``H*W*3`` RGB8 (0 without colour)       RGB PNG (0 without colour)
===================  =====================================  ==========================================

plus ``X-Width``, ``X-Height``, ``X-Depth-Format`` (``f16``/``png16``), ``X-Depth-Units`` (``m``/``mm``),
``X-Map-Version`` and ``X-Valid-Fraction``. Images are row-major, top row first; depth is the camera
z-depth (not the ray length) at the requested pose and intrinsics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import cv2
import numpy as np

from voxfusion.core.errors import ValidationError
from voxfusion.core.geometry import nearest_rigid
from voxfusion.core.render.volume import RenderedImage
from voxfusion.core.slam import FrameRecord
from voxfusion.core.trajectory import Trajectory, format_tum_trajectory
from voxfusion.proto.schemas import PoseOut

__all__ = [
    "MESH_MEDIA_TYPES",
    "MESH_DETAILS",
    "MeshDetail",
    "VOXEL_MEDIA_TYPES",
    "RenderBody",
    "pose_out",
    "tum_text",
    "encode_render",
]

MESH_MEDIA_TYPES = {"ply": "application/octet-stream", "glb": "model/gltf-binary", "obj": "model/obj"}
"""``Content-Type`` of each mesh format (PLY has no registered media type)."""
MeshDetail = Literal["full", "preview"]
"""``full``: the configured mesh resolution (``mesh_res``); ``preview``: a coarser lattice (about 2.5 cm,
:meth:`VoxFusionConfig.preview_mesh_res`), several times cheaper to extract (the live viewer's)."""
MESH_DETAILS: tuple[str, ...] = get_args(MeshDetail)
VOXEL_MEDIA_TYPES = {"npz": "application/octet-stream", "ply": "application/octet-stream"}


def pose_out(rec: FrameRecord, refined: bool = True) -> PoseOut:
    """A tracked frame as :class:`PoseOut` (``refined``: with the newest keyframe refinements); the pose
    is re-orthonormalised (:func:`nearest_rigid`)."""
    T = nearest_rigid(rec.current_pose() if refined else rec.T_tracked)
    loss = rec.tracking.loss if rec.tracking is not None else None
    if loss is not None and not np.isfinite(loss):
        loss = None
    ratio = rec.cost_ratio if rec.cost_ratio is not None and np.isfinite(rec.cost_ratio) else None
    return PoseOut(seq=int(rec.index), timestamp_s=float(rec.timestamp_s), T_world_cam=np.asarray(T).tolist(),
                   tracking_loss=loss, lost=bool(rec.lost), tracking_state=rec.tracking_state, cost_ratio=ratio,
                   is_keyframe=rec.keyframe is not None)


def tum_text(poses: list[PoseOut]) -> str:
    """Poses as a TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, camera-to-world, OpenCV axes),
    the same text :func:`voxfusion.core.trajectory.write_tum_trajectory` writes."""
    T = np.asarray([p.T_world_cam for p in poses], dtype=np.float64).reshape(-1, 4, 4)
    return format_tum_trajectory(Trajectory(np.array([p.timestamp_s for p in poses]), T))


@dataclass(frozen=True)
class RenderBody:
    """An encoded render answer: the body and the headers describing its parts."""

    body: bytes
    headers: dict[str, str]


def _png(img: np.ndarray, field: str) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValidationError(field, "PNG encoding failed")
    return buf.tobytes()


def encode_render(image: RenderedImage, fmt: str, map_version: int) -> RenderBody:
    """Encode a rendered depth (+ mask, + colour) image as the render answer (module docstring)."""
    depth = image.depth.detach().cpu().numpy().astype(np.float32)
    valid = image.valid.detach().cpu().numpy() & (depth > 0) & np.isfinite(depth)
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    h, w = depth.shape
    color = None
    if image.color is not None:
        color = (image.color.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
        color[~valid] = 0
    if fmt == "f16":
        depth_b = depth.astype("<f2").tobytes()
        mask_b = valid.astype(np.uint8).tobytes()
        color_b = color.tobytes() if color is not None else b""
        units = "m"
    elif fmt == "png16":
        mm = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        depth_b = _png(mm, "depth")
        mask_b = _png(valid.astype(np.uint8) * 255, "mask")
        color_b = _png(cv2.cvtColor(color, cv2.COLOR_RGB2BGR), "color") if color is not None else b""
        units = "mm"
    else:
        raise ValidationError("format", f"unknown render format {fmt!r}; use f16 or png16")
    headers = {
        "X-Width": str(w), "X-Height": str(h), "X-Depth-Format": fmt, "X-Depth-Units": units,
        "X-Depth-Bytes": str(len(depth_b)), "X-Mask-Bytes": str(len(mask_b)), "X-Color-Bytes": str(len(color_b)),
        "X-Map-Version": str(map_version), "X-Valid-Fraction": f"{float(valid.mean()) if valid.size else 0.0:.6f}",
    }
    return RenderBody(depth_b + mask_b + color_b, headers)
