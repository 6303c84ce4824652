"""A procedural indoor room with exact geometry, position-based colour textures and a ray-casting renderer.

This is the scene half of the synthetic generator (:mod:`.synthetic` holds the capture, the trajectory
and the writers). Everything is deterministic given the seed.

World frame: metres, **z up**; the room is the box ``x in [-2.5, 2.5]``, ``y in [-2, 2]``,
``z in [0, 2.7]`` (``ROOM_MIN_M`` / ``ROOM_MAX_M``), an inward-facing closed box (floor, ceiling, four
walls). Furniture, placed by the seed: a table (top plus four thin cylindrical legs) near the centre with
a sphere and a small box on it; a tall cabinet, a low sideboard, a crate and a cylindrical bin on the
floor against four different walls; a thin shelf and two flat pictures hung on walls. Furniture taller
than the table stays outside ``CAMERA_ZONE_MIN_M .. CAMERA_ZONE_MAX_M`` (expanded by 0.3 m), the region
the synthetic camera moves in, so no view is ever closer than ~0.3 m to a surface. Objects that rest on
something are sunk 1 cm into it so that no visible face is coplanar with another.

Texture: each object has an albedo that is a smooth function of the 3D surface point (two sums of
sinusoids along random 3D directions, wavelengths 8 cm to 1.5 m, mixing three colours), so the pattern
varies within every face and is not aligned with the geometry's edges. Shading is Lambertian from one
point light (``LIGHT_POSITION_M``) plus ambient, no shadows, so a surface point has the same colour from
every viewpoint (what photometric tracking assumes).
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh

from ..errors import ShapeError, ValidationError
from ..geometry import check_intrinsics, check_rigid

__all__ = [
    "ROOM_MIN_M",
    "ROOM_MAX_M",
    "CAMERA_ZONE_MIN_M",
    "CAMERA_ZONE_MAX_M",
    "LIGHT_POSITION_M",
    "RoomScene",
    "RenderedView",
    "SceneRenderer",
    "make_room_scene",
]

ROOM_MIN_M = np.array([-2.5, -2.0, 0.0])
"""Room corner with the smallest coordinates (world frame, metres); the room is 5 x 4 x 2.7 m."""
ROOM_MAX_M = np.array([2.5, 2.0, 2.7])
"""Room corner with the largest coordinates (world frame, metres)."""
CAMERA_ZONE_MIN_M = np.array([-0.6, -0.5, 1.4])
"""The synthetic camera centre always stays inside ``CAMERA_ZONE_MIN_M .. CAMERA_ZONE_MAX_M``."""
CAMERA_ZONE_MAX_M = np.array([0.6, 0.5, 1.7])
LIGHT_POSITION_M = np.array([0.7, -0.5, 2.3])
"""The point light used for Lambertian shading (world frame, metres)."""

_AMBIENT = 0.4
_DIFFUSE = 0.6
_N_WAVES_A = 6  # sinusoids mixing colour 0 and colour 1
_N_WAVES_B = 3  # sinusoids adding colour 2
_SINK_M = 0.01  # objects resting on a surface are sunk this far into it


@dataclass(frozen=True, eq=False)
class RoomScene:
    """The room: triangle mesh, which object each face belongs to, and each object's texture.

    Attributes:
        mesh: the ground-truth mesh (world frame, metres; vertex colours = unshaded albedo at the
            vertices). Faces are not merged or reordered, so ``face_object_id`` lines up with ``mesh.faces``.
        face_object_id: ``[F]`` int32 object index of each face.
        object_names: name of each object (``"floor"``, ``"ceiling"``, ``"wall_x-"``, ..., ``"table_top"``).
        colors: ``[O, 3, 3]`` float64 RGB in [0, 1]: the three colours each object's texture mixes.
        waves_a / waves_b: ``[O, Ka, 3]`` / ``[O, Kb, 3]`` float64 wave vectors (radians per metre).
        phases_a / phases_b: ``[O, Ka]`` / ``[O, Kb]`` float64 phases (radians).
        seed: the seed the scene was made from.
    """

    mesh: trimesh.Trimesh
    face_object_id: np.ndarray
    object_names: tuple[str, ...]
    colors: np.ndarray
    waves_a: np.ndarray
    phases_a: np.ndarray
    waves_b: np.ndarray
    phases_b: np.ndarray
    seed: int

    @property
    def n_objects(self) -> int:
        return len(self.object_names)

    def albedo(self, points_world: np.ndarray, object_id: np.ndarray) -> np.ndarray:
        """Unshaded surface colour at ``points_world`` ``[N, 3]`` (metres) on objects ``object_id`` ``[N]``.

        Returns ``[N, 3]`` float32 RGB in [0, 1].
        """
        p = np.asarray(points_world, dtype=np.float64)
        oid = np.asarray(object_id, dtype=np.int64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ShapeError("points_world", p.shape, "[N, 3]")
        if oid.shape != (p.shape[0],):
            raise ShapeError("object_id", oid.shape, f"[{p.shape[0]}]")
        if oid.size and (oid.min() < 0 or oid.max() >= self.n_objects):
            raise ValidationError("object_id", f"values must be in [0, {self.n_objects})")
        p32 = p.astype(np.float32)  # float32 sin is ~5x faster; phase error < 1e-4 rad in the room
        rgb = np.empty((len(p), 3), dtype=np.float32)
        order = np.argsort(oid, kind="stable")
        bounds = np.searchsorted(oid[order], np.arange(self.n_objects + 1))
        for o in range(self.n_objects):
            idx = order[bounds[o]:bounds[o + 1]]
            if idx.size == 0:
                continue
            q = p32[idx]
            t = (0.5 + 0.5 * np.tanh(1.5 * _wave_sum(q, self.waves_a[o], self.phases_a[o])))[:, None]
            s = (0.6 * np.clip(_wave_sum(q, self.waves_b[o], self.phases_b[o]), 0.0, 1.0))[:, None]
            c = self.colors[o].astype(np.float32)
            rgb[idx] = (1.0 - s) * ((1.0 - t) * c[0] + t * c[1]) + s * c[2]
        return rgb


def _wave_sum(p: np.ndarray, waves: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """Unit-variance sum of sinusoids ``sum_k sin(w_k . p + phi_k) / sqrt(K / 2)`` at ``p`` ``[N, 3]``,
    for one object's ``waves`` ``[K, 3]`` and ``phases`` ``[K]``; returns ``[N]``."""
    arg = np.einsum("nc,kc->nk", p, waves.astype(p.dtype)) + phases.astype(p.dtype)
    return np.sin(arg).sum(axis=1) / np.float32(np.sqrt(waves.shape[0] / 2.0))


# ---------------------------------------------------------------------------------------------- building


class _Builder:
    """Collects mesh parts and their object ids."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.face_ids: list[np.ndarray] = []
        self.names: list[str] = []
        self._n_vertices = 0

    def add(self, name: str, part: trimesh.Trimesh, flip: bool = False) -> int:
        oid = len(self.names)
        self.names.append(name)
        faces = np.asarray(part.faces, dtype=np.int64)
        if flip:
            faces = faces[:, ::-1]
        self.vertices.append(np.asarray(part.vertices, dtype=np.float64))
        self.faces.append(faces + self._n_vertices)
        self.face_ids.append(np.full(len(faces), oid, dtype=np.int32))
        self._n_vertices += len(part.vertices)
        return oid


def _pose(yaw_rad: float, centre: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = centre
    return T


def _box(extents: tuple[float, float, float], centre: np.ndarray, yaw_rad: float = 0.0) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=_pose(yaw_rad, np.asarray(centre, float)))


def _footprint(extents: tuple[float, float, float], centre: np.ndarray, yaw_rad: float) -> np.ndarray:
    """Axis-aligned ``[xmin, ymin, xmax, ymax]`` of a yawed box's floor footprint."""
    c, s = abs(np.cos(yaw_rad)), abs(np.sin(yaw_rad))
    hx = 0.5 * (c * extents[0] + s * extents[1])
    hy = 0.5 * (s * extents[0] + c * extents[1])
    return np.array([centre[0] - hx, centre[1] - hy, centre[0] + hx, centre[1] + hy])


def _against_wall(rng: np.random.Generator, width: float, depth: float, taken: list[np.ndarray],
                  wall: int, gap_m: float = 0.03) -> tuple[np.ndarray, float]:
    """Pick a spot for a ``width x depth`` footprint with its back ``gap_m`` from wall ``wall`` (0..3:
    x-, x+, y-, y+), or from any wall if that one is full.

    Returns the footprint centre ``(x, y)`` and the yaw that turns the object's x axis along the wall.
    Rejection-samples against the footprints in ``taken`` (0.1 m clearance); deterministic given ``rng``.
    """
    for attempt in range(300):
        if attempt >= 100:
            wall = int(rng.integers(4))
        if wall < 2:  # walls x = -2.5 / x = +2.5: object runs along y
            span = ROOM_MAX_M[1] - ROOM_MIN_M[1] - width - 0.2
            along = ROOM_MIN_M[1] + 0.1 + width / 2 + rng.uniform(0, span)
            x = (ROOM_MIN_M[0] + gap_m + depth / 2) if wall == 0 else (ROOM_MAX_M[0] - gap_m - depth / 2)
            centre, yaw = np.array([x, along]), np.pi / 2
        else:  # walls y = -2 / y = +2: object runs along x
            span = ROOM_MAX_M[0] - ROOM_MIN_M[0] - width - 0.2
            along = ROOM_MIN_M[0] + 0.1 + width / 2 + rng.uniform(0, span)
            y = (ROOM_MIN_M[1] + gap_m + depth / 2) if wall == 2 else (ROOM_MAX_M[1] - gap_m - depth / 2)
            centre, yaw = np.array([along, y]), 0.0
        fp = _footprint((width, depth, 0.0), centre, yaw)
        if all(_separated(fp, other, 0.1) for other in taken) and _outside_camera_zone(fp):
            taken.append(fp)
            return centre, yaw
    raise ValidationError("seed", "could not place the furniture (no free wall space); try another seed")


def _separated(a: np.ndarray, b: np.ndarray, clearance: float) -> bool:
    return bool(a[2] + clearance <= b[0] or b[2] + clearance <= a[0]
                or a[3] + clearance <= b[1] or b[3] + clearance <= a[1])


def _outside_camera_zone(fp: np.ndarray, margin: float = 0.3) -> bool:
    zone = np.array([CAMERA_ZONE_MIN_M[0] - margin, CAMERA_ZONE_MIN_M[1] - margin,
                     CAMERA_ZONE_MAX_M[0] + margin, CAMERA_ZONE_MAX_M[1] + margin])
    return _separated(fp, zone, 0.0)


def _palette(rng: np.random.Generator, value_range: tuple[float, float]) -> np.ndarray:
    """Three RGB colours: two of one hue family with clearly different brightness, one accent."""
    h = rng.uniform()
    s = rng.uniform(0.25, 0.7)
    lo, hi = value_range
    v0 = rng.uniform(lo, lo + 0.3 * (hi - lo))
    v1 = rng.uniform(lo + 0.7 * (hi - lo), hi)
    c0 = colorsys.hsv_to_rgb(h, s, v0)
    c1 = colorsys.hsv_to_rgb((h + rng.uniform(-0.08, 0.08)) % 1.0, s * rng.uniform(0.5, 1.0), v1)
    c2 = colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.5, 0.9), rng.uniform(0.5, 0.95))
    return np.array([c0, c1, c2], dtype=np.float64)


def _waves(rng: np.random.Generator, n: int,
           wavelength_m: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = np.exp(rng.uniform(np.log(wavelength_m[0]), np.log(wavelength_m[1]), size=n))
    return d * (2.0 * np.pi / lam)[:, None], rng.uniform(0.0, 2.0 * np.pi, size=n)


def make_room_scene(seed: int = 0) -> RoomScene:
    """Build the furnished room for ``seed`` (see the module docstring); deterministic.

    Example::

        scene = make_room_scene(3)
        scene.mesh.export("room.ply")           # ground truth, vertex colours = albedo
        scene.face_object_id[:12]               # the room's 12 faces: floor, ceiling, walls
    """
    if int(seed) != seed or seed < 0:
        raise ValidationError("seed", f"must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng([int(seed), 0x5CE])
    b = _Builder()

    # Room: inward-facing box, one object per side (floor, ceiling, 4 walls).
    room = trimesh.creation.box(extents=ROOM_MAX_M - ROOM_MIN_M,
                                transform=_pose(0.0, (ROOM_MIN_M + ROOM_MAX_M) / 2))
    outward = np.asarray(room.face_normals)
    sides = {"floor": (2, -1), "ceiling": (2, 1), "wall_x-": (0, -1), "wall_x+": (0, 1),
             "wall_y-": (1, -1), "wall_y+": (1, 1)}
    for name, (axis, sign) in sides.items():
        sel = np.isclose(outward[:, axis], sign)
        b.add(name, trimesh.Trimesh(room.vertices, room.faces[sel], process=False), flip=True)

    # Table near the centre: top, four thin legs; a sphere and a small box on top.
    top = (rng.uniform(1.0, 1.4), rng.uniform(0.6, 0.9), 0.04)
    top_z = rng.uniform(0.72, 0.78)
    t_centre = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.15, 0.15), top_z - top[2] / 2])
    t_yaw = rng.uniform(-0.5, 0.5)
    T_table = _pose(t_yaw, t_centre)
    b.add("table_top", _box(top, t_centre, t_yaw))
    leg_r = rng.uniform(0.018, 0.03)
    leg_h = top_z - top[2] / 2 + _SINK_M + _SINK_M  # from 1 cm below the floor to 1 cm into the top
    for k, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        local = np.array([sx * (top[0] / 2 - 0.06), sy * (top[1] / 2 - 0.06), 0.0, 1.0])
        xy = (T_table @ local)[:2]
        leg = trimesh.creation.cylinder(radius=leg_r, height=leg_h, sections=16,
                                        transform=_pose(0.0, np.array([*xy, -_SINK_M + leg_h / 2])))
        b.add(f"table_leg_{k}", leg)
    r_sphere = rng.uniform(0.1, 0.15)
    local = np.array([rng.uniform(-0.25, 0.0) * top[0], rng.uniform(-0.2, 0.2) * top[1], 0.0, 1.0])
    xy = (T_table @ local)[:2]
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=r_sphere)
    sphere.apply_translation([*xy, top_z + r_sphere - 0.002])
    b.add("sphere", sphere)
    small = (rng.uniform(0.15, 0.3), rng.uniform(0.12, 0.25), rng.uniform(0.05, 0.2))
    local = np.array([rng.uniform(0.15, 0.3) * top[0], rng.uniform(-0.15, 0.15) * top[1], 0.0, 1.0])
    xy = (T_table @ local)[:2]
    book_yaw = t_yaw + rng.uniform(-0.6, 0.6)
    b.add("book", _box(small, np.array([*xy, top_z - _SINK_M + small[2] / 2]), book_yaw))

    # Furniture against the walls (outside the camera zone), floor pieces on four different walls so that
    # every bearing of the camera sees some.
    taken: list[np.ndarray] = []
    floor_walls = rng.permutation(4)
    hung_walls = rng.permutation(4)
    cab = (rng.uniform(0.5, 0.9), rng.uniform(0.4, 0.5), rng.uniform(1.2, 1.9))
    c, yaw = _against_wall(rng, cab[0], cab[1], taken, floor_walls[0])
    b.add("cabinet", _box(cab, np.array([*c, cab[2] / 2 - _SINK_M]), yaw))
    side = (rng.uniform(1.2, 1.8), rng.uniform(0.4, 0.55), rng.uniform(0.4, 0.6))
    c, yaw = _against_wall(rng, side[0], side[1], taken, floor_walls[1])
    b.add("sideboard", _box(side, np.array([*c, side[2] / 2 - _SINK_M]), yaw))
    crate = (rng.uniform(0.35, 0.55),) * 2 + (rng.uniform(0.3, 0.55),)
    c, _ = _against_wall(rng, crate[0] * 1.42, crate[1] * 1.42, taken, floor_walls[2], gap_m=0.15)
    b.add("crate", _box(crate, np.array([*c, crate[2] / 2 - _SINK_M]), rng.uniform(0.2, 1.2)))
    r_bin = rng.uniform(0.12, 0.22)
    h_bin = rng.uniform(0.4, 0.9)
    c, _ = _against_wall(rng, 2 * r_bin, 2 * r_bin, taken, floor_walls[3], gap_m=0.08)
    b.add("bin", trimesh.creation.cylinder(radius=r_bin, height=h_bin, sections=32,
                                           transform=_pose(0.0, np.array([*c, h_bin / 2 - _SINK_M]))))
    shelf = (rng.uniform(0.8, 1.2), 0.25, 0.03)
    c, yaw = _against_wall(rng, shelf[0], shelf[1], taken, hung_walls[0], gap_m=0.0)
    b.add("shelf", _box((shelf[0], shelf[1] + _SINK_M, shelf[2]),
                        np.array([*c, rng.uniform(1.5, 1.9)]), yaw))

    for k in range(2):  # flat pictures on the walls: small depth steps on otherwise plain walls
        pic = (rng.uniform(0.5, 1.0), rng.uniform(0.02, 0.04), rng.uniform(0.4, 0.7))
        c, yaw = _against_wall(rng, pic[0], pic[1], taken, hung_walls[1 + k], gap_m=0.0)
        b.add(f"picture_{k}", _box((pic[0], pic[1] + _SINK_M, pic[2]),
                                   np.array([*c, rng.uniform(1.3, 1.7)]), yaw))

    # Textures: one palette and wave set per object.
    n_obj = len(b.names)
    colors = np.empty((n_obj, 3, 3))
    waves_a = np.empty((n_obj, _N_WAVES_A, 3))
    phases_a = np.empty((n_obj, _N_WAVES_A))
    waves_b = np.empty((n_obj, _N_WAVES_B, 3))
    phases_b = np.empty((n_obj, _N_WAVES_B))
    for o, name in enumerate(b.names):
        bright = (0.55, 0.95) if name.startswith(("wall", "ceiling")) else (0.2, 0.85)
        colors[o] = _palette(rng, bright)
        waves_a[o], phases_a[o] = _waves(rng, _N_WAVES_A, (0.08, 0.8))
        waves_b[o], phases_b[o] = _waves(rng, _N_WAVES_B, (0.15, 1.5))

    vertices = np.concatenate(b.vertices)
    faces = np.concatenate(b.faces)
    face_ids = np.concatenate(b.face_ids)
    vertex_ids = np.concatenate([np.full(len(v), i, dtype=np.int32) for i, v in enumerate(b.vertices)])
    scene = RoomScene(
        mesh=trimesh.Trimesh(vertices, faces, process=False),
        face_object_id=face_ids, object_names=tuple(b.names), colors=colors,
        waves_a=waves_a, phases_a=phases_a, waves_b=waves_b, phases_b=phases_b, seed=int(seed),
    )
    rgb = scene.albedo(vertices, vertex_ids)
    scene.mesh.visual.vertex_colors = np.concatenate(
        [np.round(rgb * 255).astype(np.uint8), np.full((len(rgb), 1), 255, np.uint8)], axis=1
    )
    return scene


# --------------------------------------------------------------------------------------------- rendering


@dataclass(frozen=True, eq=False)
class RenderedView:
    """What one pinhole camera sees of a :class:`RoomScene` (all arrays ``[H, W, ...]``, row = image v).

    Attributes:
        depth_m: ``[H, W]`` float32 z-depth along the optical axis (not ray length), 0 where nothing is hit.
        color: ``[H, W, 3]`` uint8 RGB, shaded (ambient + Lambertian point light); black where no hit.
        normal_world: ``[H, W, 3]`` float32 unit face normal facing the camera (world frame).
        cos_incidence: ``[H, W]`` float32 ``|cos|`` of the angle between viewing ray and normal (0 = grazing).
        object_id: ``[H, W]`` int32 object index (see ``RoomScene.object_names``), -1 where no hit.
    """

    depth_m: np.ndarray
    color: np.ndarray
    normal_world: np.ndarray
    cos_incidence: np.ndarray
    object_id: np.ndarray


def _first_hit_function(mesh: trimesh.Trimesh) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``first_hit(origins [N, 3], directions [N, 3]) -> [N]`` int64 index of the first face hit, -1 for none.

    Embree (embreex, float32) when installed; else trimesh's pure-numpy intersector (slow but exact).
    Directions need not be unit length.
    """
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:  # no embreex wheel for this platform
        intersector = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
        return lambda o, d: np.asarray(intersector.intersects_first(o, d), dtype=np.int64)
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=scene, vertices=np.asarray(mesh.vertices, dtype=np.float32),
                 indices=np.asarray(mesh.faces, dtype=np.int32))
    return lambda o, d: np.asarray(
        scene.run(np.ascontiguousarray(o, dtype=np.float32), np.ascontiguousarray(d, dtype=np.float32)),
        dtype=np.int64,
    )


class SceneRenderer:
    """Ray-casts a :class:`RoomScene` into depth, colour, normals and object ids.

    One ray per pixel through the pixel centre (integer pixel coordinates, OpenCV convention), so a
    pixel ``(u, v)`` with depth ``z`` back-projects to ``z * K^-1 [u, v, 1]`` exactly on the surface.
    Embree (float32, through embreex, which trimesh uses too) picks the first triangle hit; the hit
    distance is then recomputed in float64 from that triangle's plane, so depth is exact to ~1e-6 m.
    Cost: ~50 ms of one CPU core for a 320x240 view (ray casting ~15 ms, texturing and shading the rest).

    Example::

        r = SceneRenderer(make_room_scene(0))
        view = r.render(T_world_cam, make_intrinsics(192, 192, 159.5, 119.5), 320, 240)
    """

    def __init__(self, scene: RoomScene) -> None:
        self.scene = scene
        self._first_hit = _first_hit_function(scene.mesh)
        self._ray_cache: tuple[tuple, np.ndarray] | None = None

    @cached_property
    def _planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-face unit normals ``[F, 3]`` and plane offsets ``[F]`` (``n . x = c`` on the face), float64."""
        tri = np.asarray(self.scene.mesh.triangles, dtype=np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return n, np.einsum("ij,ij->i", n, tri[:, 0])

    def _camera_rays(self, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """``[H*W, 3]`` camera-frame ray directions with z = 1 (so the ray parameter is the z-depth)."""
        key = (width, height, *np.asarray(K).ravel().tolist())
        if self._ray_cache is None or self._ray_cache[0] != key:
            u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
            d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
            self._ray_cache = (key, d.reshape(-1, 3))
        return self._ray_cache[1]

    def render(self, T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int,
               max_depth_m: float = np.inf) -> RenderedView:
        """Render the view of a camera at ``T_world_cam`` (``[4, 4]`` camera-to-world, OpenCV axes).

        Args:
            T_world_cam: ``[4, 4]`` camera-to-world pose, metres.
            K: ``[3, 3]`` intrinsics for ``width`` x ``height``.
            width, height: image size in pixels.
            max_depth_m: hits farther than this (z-depth) are dropped (depth 0, colour black, id -1).
        """
        T = check_rigid(T_world_cam, "T_world_cam")
        K = check_intrinsics(K, width, height, "K")
        d_cam = self._camera_rays(K, width, height)
        R, o = T[:3, :3], T[:3, 3]
        d_world = np.einsum("ij,nj->ni", R, d_cam)  # einsum, not BLAS: tall-skinny products are
        tri_id = self._first_hit(np.broadcast_to(o, d_world.shape), d_world)  # slow with threaded BLAS
        n_face, c_face = self._planes
        # Exact hit in float64 on the face's plane; the ray parameter is the z-depth (d_cam.z = 1).
        f = np.maximum(tri_id, 0)
        n = n_face[f]
        nd = np.einsum("ij,ij->i", n, d_world)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (c_face[f] - np.einsum("ij,j->i", n, o)) / nd
        hit = (tri_id >= 0) & np.isfinite(z) & (z > 0) & (z <= max_depth_m)
        z = np.where(hit, z, 0.0)
        n *= np.where(nd > 0, -1.0, 1.0)[:, None]  # face the camera
        p = o + d_world * z[:, None]
        oid = np.where(hit, self.scene.face_object_id[f], -1).astype(np.int32)

        to_light = LIGHT_POSITION_M - p
        to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
        shade = _AMBIENT + _DIFFUSE * np.clip(np.einsum("ij,ij->i", n, to_light), 0.0, 1.0)
        rgb = np.zeros((width * height, 3), dtype=np.float32)
        rgb[hit] = self.scene.albedo(p[hit], oid[hit]) * shade[hit, None].astype(np.float32)
        cos_inc = np.where(hit, np.abs(nd) / np.linalg.norm(d_world, axis=1), 0.0)
        n[~hit] = 0.0

        return RenderedView(
            depth_m=z.reshape(height, width).astype(np.float32),
            color=np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8).reshape(height, width, 3),
            normal_world=n.reshape(height, width, 3).astype(np.float32),
            cos_incidence=cos_inc.reshape(height, width).astype(np.float32),
            object_id=oid.reshape(height, width),
        )
