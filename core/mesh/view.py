"""Shaded pictures of meshes for checking by eye: ray-cast rendering with correct depth ordering.

One ray per pixel centre, first hit through trimesh's embree intersector (``embreex``; trimesh's plain
intersector, much slower, when embree is missing). The colour of a hit is the mesh's vertex colours
interpolated with the hit's barycentric coordinates (face colours, or texture colours sampled at the
vertices, when that is what the mesh has), times a headlight Lambert term
``0.35 + 0.65 * |cos(face normal, ray)|`` so that the geometry reads clearly. Meshes without colours (or
with one grey colour everywhere, like an uncoloured reconstruction) are drawn light grey.

Camera convention: OpenCV axes (x right, y down, z forward), pose ``T_world_cam`` camera-to-world, metres;
pixel ``(u, v)`` integer coordinates are pixel centres, as everywhere in voxfusion.

Example::

    mesh = trimesh.load("out/desk/mesh.ply", force="mesh")
    K = intrinsics_from_fov(640, 480, fov_deg=70)
    view = render_mesh(mesh, K, overview_pose(mesh, K, 640, 480), 640, 480)
    save_png("mesh.png", view.rgb)
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image, ImageDraw, ImageFont

from ..errors import ShapeError, ValidationError
from ..geometry import check_intrinsics, check_rigid, make_intrinsics

__all__ = [
    "ViewImage",
    "LIGHT_GREY_RGB",
    "intrinsics_from_fov",
    "look_at",
    "overview_pose",
    "render_mesh",
    "side_by_side",
    "save_png",
    "write_mesh_pictures",
    "write_scene_views",
]

LIGHT_GREY_RGB = (215, 215, 215)
"""Albedo (uint8 RGB) of meshes without colours, before shading."""

_AMBIENT = 0.35  # shade = _AMBIENT + (1 - _AMBIENT) * |cos(normal, ray)|
_RAYS_PER_CHUNK = 1 << 18  # rays cast at once (rows of the image), bounds temporary memory
_MAX_LAYERS = 32  # with cull_back_faces: back faces a ray may pass through before it gives up


@dataclass(frozen=True, eq=False)
class ViewImage:
    """A rendered view.

    Attributes:
        rgb: ``[H, W, 3]`` uint8 shaded colour; the background colour where no surface was hit.
        depth_m: ``[H, W]`` float32 z-depth in metres along the camera's optical axis (as in a depth
            map), 0 = background.
        face_index: ``[H, W]`` int64 index into ``mesh.faces`` of the surface seen, -1 = background.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    face_index: np.ndarray


def intrinsics_from_fov(width: int, height: int, fov_deg: float = 70.0) -> np.ndarray:
    """Pinhole ``K`` ``[3, 3]`` float64 with horizontal field of view ``fov_deg``, square pixels and the
    principal point at the image centre ``((W - 1) / 2, (H - 1) / 2)``.

    Example:
        >>> K = intrinsics_from_fov(640, 480, 90.0)
        >>> float(K[0, 0])  # 320 px / tan(45 deg)
        320.0
    """
    width, height = _check_size(width, height)
    if not (isinstance(fov_deg, int | float) and 1.0 <= fov_deg <= 170.0):
        raise ValidationError("fov_deg", f"must be a horizontal field of view in [1, 170] degrees, got {fov_deg!r}")
    f = (width / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    return make_intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose ``[4, 4]`` float64 of an OpenCV camera at ``eye`` looking at ``target``.

    Args:
        eye: ``[3]`` camera centre, world metres.
        target: ``[3]`` world point that lands on the optical axis (image centre for a centred ``K``).
        up: ``[3]`` world direction that points up in the image (camera -y); need not be unit or exactly
            perpendicular to the view, only not parallel to it.

    Raises ``ValidationError`` when ``eye == target`` or ``up`` is parallel to the viewing direction.

    Example:
        >>> T = look_at([0, -3, 1], [0, 0, 1])  # looking along +y, z up
        >>> T[:3, 2].round(6).tolist(), T[:3, 0].round(6).tolist()  # forward, right
        ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    """
    eye_w, target_w, up_w = (_vec3(v, name) for v, name in ((eye, "eye"), (target, "target"), (up, "up")))
    forward = target_w - eye_w
    dist = np.linalg.norm(forward)
    if dist < 1e-9:
        raise ValidationError("eye/target", f"eye and target are the same point {eye_w.tolist()}")
    z = forward / dist
    if np.linalg.norm(up_w) < 1e-12:
        raise ValidationError("up", "must be a non-zero vector")
    x = np.cross(z, up_w / np.linalg.norm(up_w))
    if np.linalg.norm(x) < 1e-6:
        raise ValidationError("up", f"{up_w.tolist()} is parallel to the viewing direction {z.round(6).tolist()}")
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye_w
    return T


def overview_pose(meshes: trimesh.Trimesh | Sequence[trimesh.Trimesh], K: np.ndarray, width: int, height: int,
                  up: Sequence[float] = (0.0, 0.0, 1.0), elevation_deg: float = 35.0,
                  azimuth_deg: float = -60.0, margin: float = 0.92) -> np.ndarray:
    """A camera that frames every vertex of ``meshes`` from an oblique viewpoint above (outside a room).

    The camera looks towards the centre of the meshes' joint bounding box, down from ``elevation_deg`` above
    the horizontal plane (the plane normal to ``up``), from ``azimuth_deg`` around ``up`` (0 = from the
    world axis least aligned with ``up``, e.g. +x for z up; -60 deg is matplotlib's default view); it is
    moved sideways so that the vertices are centred in the image and backed off just far enough that every
    vertex projects within ``margin`` of the image half-size.

    Args:
        meshes: one mesh or several (framed together, so all share one camera).
        K: ``[3, 3]`` intrinsics for ``width`` x ``height`` pixels.
        up: ``[3]`` world up (z for TUM, the synthetic room and most datasets; y for ARKit worlds).

    Returns:
        ``T_world_cam`` ``[4, 4]`` float64. With no vertices at all: a camera at ``(0, 0, 0) - 3 m``
        along the view direction looking at the origin.
    """
    K = check_intrinsics(K, *_check_size(width, height), "K")
    if not 0.0 < margin <= 1.0:
        raise ValidationError("margin", f"must be in (0, 1], got {margin}")
    mesh_list = [meshes] if isinstance(meshes, trimesh.Trimesh) else list(meshes)
    pts = [np.asarray(m.vertices, dtype=np.float64) for m in mesh_list if len(m.vertices)]
    pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    up_w = _vec3(up, "up")
    if np.linalg.norm(up_w) < 1e-12:
        raise ValidationError("up", "must be a non-zero vector")
    up_w = up_w / np.linalg.norm(up_w)
    ref = np.eye(3)[np.argmin(np.abs(up_w))]
    e1 = ref - (ref @ up_w) * up_w
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up_w, e1)
    if not -89.0 <= elevation_deg <= 89.0:
        raise ValidationError("elevation_deg", f"must be in [-89, 89] degrees, got {elevation_deg}")
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    back = np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up_w  # target -> eye, unit
    centre = (pts.min(0) + pts.max(0)) / 2.0 if len(pts) else np.zeros(3)
    T = look_at(centre + back, centre, up_w)  # the orientation; the distance is fitted below
    if len(pts) == 0:
        return look_at(centre + 3.0 * back, centre, up_w)
    p_cam = (pts - centre) @ T[:3, :3]  # camera-aligned offsets from the centre, [N, 3]
    near = max(1e-3 * float(np.linalg.norm(pts.max(0) - pts.min(0))), 1e-3)
    shift = np.zeros(3)  # camera offset along its own x and y, so that the meshes are centred in the image
    for _ in range(3):
        dist = _fit_distance(p_cam - shift, K, width, height, margin, near)
        q = p_cam - shift + [0.0, 0.0, dist]
        u, v = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]  # normalised image coordinates
        mid = np.array([(u.max() + u.min()) / 2.0 - ((width - 1) / 2.0 - K[0, 2]) / K[0, 0],
                        (v.max() + v.min()) / 2.0 - ((height - 1) / 2.0 - K[1, 2]) / K[1, 1]])
        shift[:2] += mid * dist
    dist = _fit_distance(p_cam - shift, K, width, height, margin, near)
    eye = centre + T[:3, :3] @ (shift - [0.0, 0.0, dist])
    return look_at(eye, eye + T[:3, 2], up_w)


def render_mesh(mesh: trimesh.Trimesh, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
                background: Sequence[int] = (255, 255, 255), cull_back_faces: bool = False) -> ViewImage:
    """Ray-cast a shaded picture and a depth map of ``mesh`` seen by a pinhole camera.

    Args:
        mesh: triangle mesh, world metres; vertex colours (or face / texture colours) are used when present.
        K: ``[3, 3]`` intrinsics for ``width`` x ``height`` pixels.
        T_world_cam: ``[4, 4]`` camera-to-world, OpenCV axes, metres.
        width, height: image size in pixels.
        background: uint8 RGB where no surface is hit.
        cull_back_faces: rays pass through faces whose front (the side their winding's normal points to;
            voxfusion meshes point it at free space) looks away from the camera, so a closed room seen
            from outside shows its inside, like a dollhouse.

    Returns:
        :class:`ViewImage`: ``rgb`` ``[H, W, 3]`` uint8, ``depth_m`` ``[H, W]`` float32 (0 = background),
        ``face_index`` ``[H, W]`` int64 (-1 = background). An empty mesh gives an all-background view.
    """
    width, height = _check_size(width, height)
    K = check_intrinsics(K, width, height, "K")
    T = check_rigid(T_world_cam, "T_world_cam")
    bg = np.asarray(background)
    if bg.shape != (3,) or not np.all((bg >= 0) & (bg <= 255)):
        raise ValidationError("background", f"must be three values in [0, 255], got {background!r}")
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValidationError("mesh", f"must be a trimesh.Trimesh, got {type(mesh).__name__}")
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    rgb[:] = bg.astype(np.uint8)
    depth = np.zeros((height, width), dtype=np.float32)
    face_index = np.full((height, width), -1, dtype=np.int64)
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        return ViewImage(rgb, depth, face_index)

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    vertex_rgb, face_rgb = _albedo(mesh)
    intersector = _intersector(mesh)
    R, centre = T[:3, :3], T[:3, 3]
    offset = 1e-6 * max(float(np.ptp(vertices, axis=0).max()), 1e-3)  # steps rays past a culled face
    rows = max(1, _RAYS_PER_CHUNK // width)
    u = np.arange(width, dtype=np.float64)
    for v0 in range(0, height, rows):
        v = np.arange(v0, min(v0 + rows, height), dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        d_cam = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1).reshape(-1, 3)
        dirs = d_cam @ R.T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        hit_tri, hit_point = _first_hits(intersector, vertices, faces, centre, dirs, cull_back_faces, offset)
        ok = hit_tri >= 0
        tri, p = hit_tri[ok], hit_point[ok]
        a, b, c = (vertices[faces[tri, k]] for k in range(3))
        normal = np.cross(b - a, c - a)
        cos = np.abs(np.einsum("ij,ij->i", normal, dirs[ok])) / np.maximum(np.linalg.norm(normal, axis=1), 1e-30)
        if vertex_rgb is not None:
            bary = trimesh.triangles.points_to_barycentric(np.stack([a, b, c], 1), p)
            bary = np.clip(np.nan_to_num(bary, nan=1.0 / 3.0), 0.0, 1.0)
            bary /= np.maximum(bary.sum(1, keepdims=True), 1e-12)
            albedo = np.einsum("ik,ikc->ic", bary, vertex_rgb[faces[tri]])
        else:
            albedo = face_rgb[tri]
        shaded = albedo * (_AMBIENT + (1.0 - _AMBIENT) * cos)[:, None]
        n = len(v)
        chunk_rgb = rgb[v0:v0 + n].reshape(-1, 3)
        chunk_rgb[ok] = np.clip(np.rint(shaded), 0, 255).astype(np.uint8)
        depth[v0:v0 + n].reshape(-1)[ok] = ((p - centre) @ R[:, 2]).astype(np.float32)
        face_index[v0:v0 + n].reshape(-1)[ok] = tri
    return ViewImage(rgb, depth, face_index)


def side_by_side(images: Sequence[np.ndarray], labels: Sequence[str] | None = None,
                 gap_px: int = 4, gap_rgb: Sequence[int] = (64, 64, 64)) -> np.ndarray:
    """Compose ``[H_i, W_i, 3]`` uint8 panels left to right, each with its label in its top-left corner.

    Panels shorter than the tallest are padded at the bottom with ``gap_rgb``; panels are separated by
    ``gap_px`` columns of ``gap_rgb``. Returns ``[max H_i, sum W_i + gaps, 3]`` uint8.
    """
    if not images:
        raise ValidationError("images", "need at least one panel")
    labels = list(labels) if labels is not None else [""] * len(images)
    if len(labels) != len(images):
        raise ValidationError("labels", f"got {len(labels)} labels for {len(images)} panels")
    for i, im in enumerate(images):
        if not (isinstance(im, np.ndarray) and im.ndim == 3 and im.shape[2] == 3 and im.dtype == np.uint8):
            raise ShapeError(f"images[{i}]", getattr(im, "shape", ()), "[H, W, 3] uint8")
    height = max(im.shape[0] for im in images)
    width = sum(im.shape[1] for im in images) + gap_px * (len(images) - 1)
    canvas = Image.new("RGB", (width, height), tuple(int(c) for c in gap_rgb))
    draw = ImageDraw.Draw(canvas)
    font = _font(max(12, height // 32))
    x = 0
    for im, label in zip(images, labels, strict=True):
        canvas.paste(Image.fromarray(im), (x, 0))
        if label:
            left, top, right, bottom = draw.textbbox((x + 6, 4), label, font=font)
            draw.rectangle((left - 4, top - 3, right + 4, bottom + 3), fill=(0, 0, 0))
            draw.text((x + 6, 4), label, fill=(255, 255, 255), font=font)
        x += im.shape[1] + gap_px
    return np.asarray(canvas)


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write ``[H, W, 3]`` uint8 RGB to ``path`` as PNG (parent folders are created); returns the path."""
    if not (isinstance(rgb, np.ndarray) and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.uint8):
        raise ShapeError("rgb", getattr(rgb, "shape", ()), "[H, W, 3] uint8")
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValidationError("path", f"must end in .png, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path)
    return path


def write_mesh_pictures(out_dir: str | Path, panels: Mapping[str, trimesh.Trimesh], K: np.ndarray,
                        T_world_cam: np.ndarray, width: int, height: int, input_rgb: np.ndarray | None = None,
                        name: str = "view.png", cull_back_faces: bool = False) -> Path:
    """Render every mesh of ``panels`` (label -> mesh) at one camera and write them side by side as one PNG.

    Args:
        out_dir: folder of the picture (created).
        panels: label -> mesh, drawn left to right in this order.
        K: ``[3, 3]`` intrinsics for ``width`` x ``height``; ``T_world_cam``: ``[4, 4]`` camera-to-world.
        input_rgb: ``[h, w, 3]`` uint8 colour image of the input frame seen from this camera; drawn first,
            labelled ``input`` (resized to ``width`` x ``height`` if its size differs).
        name: file name of the picture inside ``out_dir`` (``.png``).

    Returns:
        The path of the PNG.
    """
    images: list[np.ndarray] = []
    labels: list[str] = []
    if input_rgb is not None:
        if not (isinstance(input_rgb, np.ndarray) and input_rgb.ndim == 3 and input_rgb.shape[2] == 3
                and input_rgb.dtype == np.uint8):
            raise ShapeError("input_rgb", getattr(input_rgb, "shape", ()), "[H, W, 3] uint8")
        if input_rgb.shape[:2] != (height, width):
            input_rgb = np.asarray(Image.fromarray(input_rgb).resize((width, height), Image.Resampling.BILINEAR))
        images.append(input_rgb)
        labels.append("input")
    if not panels:
        raise ValidationError("panels", "need at least one mesh to render")
    for label, mesh in panels.items():
        images.append(render_mesh(mesh, K, T_world_cam, width, height, cull_back_faces=cull_back_faces).rgb)
        labels.append(label)
    return save_png(Path(out_dir) / name, side_by_side(images, labels))


def write_scene_views(out_dir: str | Path, panels: Mapping[str, trimesh.Trimesh], K: np.ndarray,
                      T_world_cam: np.ndarray, width: int, height: int, input_rgb: np.ndarray | None,
                      up: Sequence[float], prefix: str = "view") -> list[Path]:
    """The two pictures written next to meshes by ``voxfusion run`` / ``map`` and ``bench/run.py``.

    ``<prefix>_frame.png``: the input frame beside every mesh rendered at that frame's camera (``K``,
    ``T_world_cam``, ``width`` x ``height``); ``<prefix>_overview.png``: every mesh from one oblique camera
    above, framed on
    the first mesh (:func:`overview_pose` with ``up``), back faces hidden so a room shows its inside. Empty meshes are
    skipped; returns the paths written (none when no mesh has a face).
    """
    panels = {k: m for k, m in panels.items() if m is not None and len(m.faces)}
    if not panels:
        return []
    frame = write_mesh_pictures(out_dir, panels, K, T_world_cam, width, height, input_rgb,
                                name=f"{prefix}_frame.png")
    Ko = intrinsics_from_fov(640, 480, 60.0)
    To = overview_pose(next(iter(panels.values())), Ko, 640, 480, up=up)  # framed on the first mesh
    overview = write_mesh_pictures(out_dir, panels, Ko, To, 640, 480, name=f"{prefix}_overview.png",
                                   cull_back_faces=True)
    return [frame, overview]


# --- internals -----------------------------------------------------------------------------------------


def _check_size(width: int, height: int) -> tuple[int, int]:
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 1 <= value <= 16384:
            raise ValidationError(name, f"must be an integer pixel count in [1, 16384], got {value!r}")
    return int(width), int(height)


def _fit_distance(p_cam: np.ndarray, K: np.ndarray, width: int, height: int, margin: float, near: float) -> float:
    """Smallest distance ``d`` to back a camera off along its -z so that every point ``p_cam`` ``[N, 3]``
    (camera axes, relative to the camera at ``d = 0``) projects within ``margin`` of the image half-size."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # f * |x| / (z + d) <= half-extent on the side the point lies  <=>  d >= f * |x| / half - z
    half_x = margin * np.where(p_cam[:, 0] >= 0, width - 1 - cx, cx).clip(min=1.0)
    half_y = margin * np.where(p_cam[:, 1] >= 0, height - 1 - cy, cy).clip(min=1.0)
    need = np.maximum(fx * np.abs(p_cam[:, 0]) / half_x, fy * np.abs(p_cam[:, 1]) / half_y) - p_cam[:, 2]
    return max(float(need.max()), float(-p_cam[:, 2].min()) + near)  # and every point in front


def _vec3(value: Sequence[float], name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (3,):
        raise ShapeError(name, a.shape, "(3,)")
    if not np.all(np.isfinite(a)):
        raise ValidationError(name, f"must be finite, got {a.tolist()}")
    return a


def _albedo(mesh: trimesh.Trimesh) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(vertex_rgb [V, 3], None)`` or ``(None, face_rgb [F, 3])``, float64 in [0, 255]."""
    visual = mesh.visual
    grey = np.tile(np.asarray(LIGHT_GREY_RGB, dtype=np.float64), (len(mesh.vertices), 1))
    kind = getattr(visual, "kind", None)
    if kind == "texture":
        try:
            visual = visual.to_color()
            kind = "vertex"
        except Exception:  # noqa: BLE001 - textures without UVs / images: draw the shape in grey
            return grey, None
    if kind == "vertex":
        colours = np.asarray(visual.vertex_colors)[:, :3].astype(np.float64)
    elif kind == "face":
        colours = np.asarray(visual.face_colors)[:, :3].astype(np.float64)
    else:
        return grey, None
    if len(colours) and np.all(colours == colours[0]) and colours[0, 0] == colours[0, 1] == colours[0, 2]:
        return grey, None  # one grey everywhere: an uncoloured mesh
    return (colours, None) if kind == "vertex" else (None, colours)


def _intersector(mesh: trimesh.Trimesh) -> object:
    """The mesh's own ray intersector (``mesh.ray``: embree when ``embreex`` is installed, cached on the mesh so
    that further views of the same mesh skip building the BVH)."""
    if not trimesh.ray.has_embree:
        warnings.warn("embree is not available (pip install embreex): rendering with trimesh's plain ray "
                      "intersector, which is much slower on large meshes", RuntimeWarning, stacklevel=3)
    return mesh.ray


def _first_hits(intersector: object, vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray, dirs: np.ndarray,
                cull_back_faces: bool, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """First surface along each ray from ``centre``: ``(face [N] int64, -1 = none; point [N, 3] float64)``.

    The hit point is recomputed in float64 from the hit triangle's plane (embree works in float32).
    """
    n = len(dirs)
    hit_tri = np.full(n, -1, dtype=np.int64)
    hit_point = np.zeros((n, 3))
    live = np.arange(n)
    origins = np.broadcast_to(centre, (n, 3)).copy()
    for _ in range(_MAX_LAYERS if cull_back_faces else 1):
        tri, ray = intersector.intersects_id(origins[live], dirs[live], multiple_hits=False)
        if len(tri) == 0:
            break
        tri, ray = np.asarray(tri, dtype=np.int64), live[np.asarray(ray, dtype=np.int64)]
        a, b, c = (vertices[faces[tri, k]] for k in range(3))
        normal = np.cross(b - a, c - a)
        d = dirs[ray]
        denom = np.einsum("ij,ij->i", normal, d)
        t = np.einsum("ij,ij->i", normal, a - origins[ray]) / np.where(np.abs(denom) > 1e-300, denom, 1e-300)
        t = np.where(np.isfinite(t) & (t >= 0), t, 0.0)
        point = origins[ray] + t[:, None] * d
        keep = denom <= 0 if cull_back_faces else np.ones(len(tri), dtype=bool)
        hit_tri[ray[keep]] = tri[keep]
        hit_point[ray[keep]] = point[keep]
        behind = ray[~keep]
        origins[behind] = point[~keep] + offset * dirs[behind]
        live = behind
        if len(live) == 0:
            break
    return hit_tri, hit_point


def _font(size_px: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size_px)
    except (TypeError, OSError):  # Pillow < 10.1 or no FreeType: the fixed bitmap font
        return ImageFont.load_default()
