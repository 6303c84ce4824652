"""Photometric check of a coloured mesh: its vertex colours against the input images that made it.

For a few frames, the mesh is ray cast at the frame's pose (:func:`~voxfusion.core.mesh.render_mesh`); at
every pixel that sees the mesh within ``depth_tol_m`` of the frame's own depth, the mesh's albedo (vertex
colours interpolated with barycentric coordinates, no shading) is compared with the input pixel. Reported:

* ``mae``: mean absolute error per channel, 0-255;
* ``chroma_ratio``: mean chroma (``max(rgb) - min(rgb)``) of the mesh's colours over the input's at the same
  pixels: below 1 = washed out (desaturated), 1 = as saturated as the input;
* ``contrast_ratio``: standard deviation of the mesh's luma over the input's: below 1 = blurred / flattened
  texture, the usual look of a colour field too coarse for the texture;
* ``mean_luma_shift``: mean luma of the mesh minus the input's (brightness bias), 0-255.

Example::

    >>> import trimesh
    >>> m = trimesh.creation.box()
    >>> photometric_check(m, []).n_pixels
    0
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import trimesh

from ..mesh.view import render_mesh

__all__ = ["PhotometricResult", "photometric_check"]

_LUMA = np.array([0.299, 0.587, 0.114])


@dataclass(frozen=True)
class PhotometricResult:
    mae: float
    chroma_ratio: float
    contrast_ratio: float
    mean_luma_shift: float
    n_pixels: int
    n_frames: int


def photometric_check(mesh: trimesh.Trimesh, frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                    np.ndarray]],
                      depth_tol_m: float = 0.05) -> PhotometricResult:
    """Compare ``mesh``'s vertex colours with input images.

    Args:
        mesh: coloured mesh (uint8 RGBA vertex colours), world metres.
        frames: ``(color [H, W, 3] uint8, depth_m [H, W] float (0 = invalid), K [3, 3], T_world_cam [4, 4])``
            per frame, poses in the mesh's world.
        depth_tol_m: pixels where the mesh's depth and the frame's differ more are skipped (occlusion,
            holes, pose error).
    """
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.float64) if len(mesh.faces) else None
    mesh_px, input_px, n_frames = [], [], 0
    for color, depth, K, T in frames:
        n_frames += 1
        if colors is None:
            continue
        h, w = depth.shape
        view = render_mesh(mesh, K, T, w, h)
        ok = (view.face_index >= 0) & (depth > 0) & (np.abs(view.depth_m - depth) < depth_tol_m)
        if not ok.any():
            continue
        v, u = np.nonzero(ok)
        z = view.depth_m[v, u].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        world = cam @ T[:3, :3].T + T[:3, 3]
        faces = mesh.faces[view.face_index[v, u]]
        bary = trimesh.triangles.points_to_barycentric(mesh.vertices[faces], world)
        bary = np.clip(np.nan_to_num(bary, nan=1 / 3), 0, 1)
        bary /= bary.sum(1, keepdims=True)
        mesh_px.append((colors[faces] * bary[:, :, None]).sum(1))
        input_px.append(color[v, u].astype(np.float64))
    if not mesh_px:
        return PhotometricResult(float("nan"), float("nan"), float("nan"), float("nan"), 0, n_frames)
    a, b = np.concatenate(mesh_px), np.concatenate(input_px)
    chroma = lambda x: x.max(1) - x.min(1)  # noqa: E731
    la, lb = a @ _LUMA, b @ _LUMA
    return PhotometricResult(
        mae=float(np.abs(a - b).mean()),
        chroma_ratio=float(chroma(a).mean() / max(chroma(b).mean(), 1e-9)),
        contrast_ratio=float(la.std() / max(lb.std(), 1e-9)),
        mean_luma_shift=float(la.mean() - lb.mean()),
        n_pixels=int(len(a)), n_frames=n_frames)
