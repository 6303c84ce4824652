"""Sparse marching cubes over allocated voxels: one welded, coloured triangle mesh.

The SDF is sampled on one global lattice: lattice point ``L`` (int, ``[3]``) sits at world position
``L * voxel_size_m / mesh_res`` and voxel ``ijk`` owns the points ``ijk * mesh_res + (0..mesh_res)`` on each
axis, so neighbouring voxels share their border samples. Every lattice point is queried exactly once
(deduplicated), so cells on both sides of a voxel border see bit-identical values. A cell (lattice cube) is
meshed only when it lies in an allocated voxel and all 8 corners are valid; each mesh vertex is keyed by
its lattice edge ``(lower lattice point, axis)``, which welds vertices shared by cells (and voxels) exactly.
The case table (:mod:`.cases`) draws the same iso-lines on a face from both sides, so the surface has no
cracks, and its triangles are wound with normals towards positive SDF (free space); ambiguous faces follow
the asymptotic decider, and the rare loop that cannot be triangulated without an edge another cell might
also draw gets a vertex of its own at the loop's mean.

Queries on a voxel face are moved about 1e-5 of a lattice step (more far from the origin, as float32 needs)
into one allocated voxel holding the point, so a field that finds a point's voxel by ``floor(p / v)`` sees
it as valid on the far faces of the allocated region too; the mesh moves by as little.

Memory: about 50-60 bytes per lattice sample (``M * (mesh_res + 1)^3`` before deduplication) for the sample
keys and values, plus whatever ``query_fn`` needs for ``chunk_points`` points, plus the mesh.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable

import numpy as np
import torch
import trimesh

from ..errors import ShapeError, ValidationError
from .cases import (
    CENTRE_CODE,
    CORNER_OFFSETS,
    EDGE_AXIS,
    EDGE_CORNERS,
    EDGE_ORIGIN,
    FACE_CORNERS,
    triangle_table,
)

__all__ = ["QueryFn", "GREY_RGB", "extract_mesh"]

QueryFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]]
"""``query(points_world [N, 3] float32 m) -> (sdf_m [N], rgb [N, 3] in [0, 1] or None, valid [N] bool)``."""

GREY_RGB = (128, 128, 128)
"""Vertex colour (uint8 RGB) used when the query returns no colour."""

_AXIS_BITS = 20  # bits per axis of a packed lattice-point key (3 * 20 bits, times 3 edge axes, fits int64)
_T_MARGIN = 1e-3  # a vertex stays this fraction of an edge away from its ends (no coincident vertices)
_NUDGE = 1e-5  # queries on voxel faces move this fraction of a lattice step into their voxel (see _inside)


def extract_mesh(
    voxel_coords: torch.Tensor | np.ndarray,
    voxel_size_m: float,
    query_fn: QueryFn,
    mesh_res: int = 8,
    chunk_points: int = 2**18,
    device: torch.device | str | None = None,
) -> trimesh.Trimesh:
    """Extract the zero level set of ``query_fn`` inside the allocated voxels.

    Args:
        voxel_coords: ``[M, 3]`` integer voxel coordinates ``ijk``; voxel ``ijk`` covers
            ``[ijk * voxel_size_m, (ijk + 1) * voxel_size_m)`` in world metres. Duplicates are ignored.
        voxel_size_m: voxel edge in metres (e.g. 0.2).
        query_fn: ``points_world [N, 3] float32 -> (sdf_m [N], rgb [N, 3] or None, valid [N] bool)``;
            negative SDF is inside (occupied). Called on chunks of at most ``chunk_points`` points, first
            at the lattice samples, then at the mesh vertices for colour.
        mesh_res: samples per voxel edge (cells per voxel edge); the lattice step is
            ``voxel_size_m / mesh_res`` (0.2 m / 8 = 25 mm).
        chunk_points: bound on points per query call and on lattice samples handled at once.
        device: where lattice tensors live and queries run; default: ``voxel_coords``' device or CPU.

    Returns:
        A ``trimesh.Trimesh`` (not processed: vertices are exactly the welded edge vertices; each sits at
        the linear zero crossing of its lattice edge, at least 1e-3 of the edge from either end), vertices
        float64 world metres ``[V, 3]``, faces int64 ``[F, 3]`` wound with normals towards positive SDF,
        vertex colours uint8 RGBA ``[V, 4]`` (grey :data:`GREY_RGB` where ``rgb`` is None). Empty when no
        allocated cell contains the surface. The same inputs give the same mesh for any ``chunk_points``.

    Example:
        >>> c = torch.tensor([0.31, 0.27, 0.33])
        >>> def sphere(p):
        ...     return (p - c).norm(dim=1) - 0.25, None, torch.ones(len(p), dtype=torch.bool)
        >>> ijk = torch.cartesian_prod(*[torch.arange(4)] * 3)
        >>> mesh = extract_mesh(ijk, 0.2, sphere, mesh_res=4)
        >>> bool(mesh.is_watertight)
        True
    """
    device = torch.device(device) if device is not None else (
        voxel_coords.device if isinstance(voxel_coords, torch.Tensor) else torch.device("cpu"))
    coords = _check_coords(voxel_coords, device)
    if not (isinstance(voxel_size_m, numbers.Real) and np.isfinite(voxel_size_m) and voxel_size_m > 0):
        raise ValidationError("voxel_size_m", f"must be a positive finite number, got {voxel_size_m!r}")
    if isinstance(mesh_res, bool) or not isinstance(mesh_res, numbers.Integral) or mesh_res < 1:
        raise ValidationError("mesh_res", f"must be an integer >= 1, got {mesh_res!r}")
    if isinstance(chunk_points, bool) or not isinstance(chunk_points, numbers.Integral) or chunk_points < 1:
        raise ValidationError("chunk_points", f"must be an integer >= 1, got {chunk_points!r}")
    if len(coords) == 0:
        return _empty_mesh()

    R, chunk_points = int(mesh_res), int(chunk_points)
    step_m = float(voxel_size_m) / R
    origin = coords.min(dim=0).values * R  # lattice point packed as key 0
    extent = (coords.max(dim=0).values + 1) * R - origin + 1
    if int(extent.max()) >= 2**_AXIS_BITS:
        raise ValidationError(
            "voxel_coords", f"map spans {int(extent.max())} lattice steps on an axis; the limit is "
            f"{2**_AXIS_BITS - 1} (lower mesh_res or extract in parts)")

    # Lattice samples of every voxel, deduplicated, each queried once.
    n1 = R + 1
    local = torch.stack(torch.meshgrid(*[torch.arange(n1, device=device)] * 3, indexing="ij"), -1).view(-1, 3)
    vox_per_chunk = max(1, chunk_points // n1**3)
    keys = (_pack(coords * R - origin)[:, None] + _pack(local)[None, :]).view(-1)  # fields never carry
    lattice_keys, sample_index = torch.unique(keys, return_inverse=True)
    del keys
    # Each sample is looked up from inside one allocated voxel holding it: the first in sorted order.
    first = torch.full((len(lattice_keys),), len(sample_index), dtype=torch.long, device=device)
    first.scatter_reduce_(0, sample_index, torch.arange(len(sample_index), device=device), "amin")
    sdf, valid = [], []
    for keys, owner in zip(lattice_keys.split(chunk_points), (first // n1**3).split(chunk_points), strict=True):
        s, _, ok = _call(query_fn, _inside(_unpack(keys) + origin, coords[owner] * R + R / 2, R, step_m))
        sdf.append(s.float())
        valid.append(ok & torch.isfinite(s))
    sdf, valid = torch.cat(sdf), torch.cat(valid)
    del first, lattice_keys

    # Marching cubes per chunk of voxels; triangle corners as vertex keys and positions, then welded.
    table = _Table(device, R)
    keys, positions, cells = [], [], []
    for start in range(0, len(coords), vox_per_chunk):
        stop = min(start + vox_per_chunk, len(coords))
        idx = sample_index[start * n1**3: stop * n1**3].view(-1, n1, n1, n1)
        k, p, c = _march(coords[start:stop], sdf[idx], valid[idx], R, origin, table)
        keys.append(k)
        positions.append(p)
        cells.append(c)
    corner_keys = torch.cat(keys).view(-1)
    if len(corner_keys) == 0:
        return _empty_mesh()
    vertex_keys, faces = torch.unique(corner_keys, return_inverse=True)
    vertices = torch.empty((len(vertex_keys), 3), dtype=torch.float64, device=device)
    vertices[faces] = torch.cat(positions).view(-1, 3)  # every copy of a vertex carries the same value
    first = torch.full((len(vertex_keys),), len(faces), dtype=torch.long, device=device)
    first.scatter_reduce_(0, faces, torch.arange(len(faces), device=device), "amin")
    cell_centre = torch.cat(cells)[first // 3] + 0.5  # a cell (in an allocated voxel) holding each vertex

    colors = _vertex_colors(query_fn, vertices, cell_centre, R, step_m, chunk_points)
    vertices = vertices * step_m
    return trimesh.Trimesh(vertices=vertices.cpu().numpy(), faces=faces.view(-1, 3).cpu().numpy(),
                           vertex_colors=colors, process=False)


class _Table:
    """The case table (:func:`.cases.triangle_table`) and cube geometry as tensors on one device."""

    def __init__(self, device: torch.device, mesh_res: int) -> None:
        triangles, centres = triangle_table()
        self.triangles = torch.from_numpy(triangles).to(device=device, dtype=torch.long)
        self.centres = torch.from_numpy(centres).to(device=device, dtype=torch.long)
        self.edge_origin = torch.from_numpy(EDGE_ORIGIN).to(device)
        self.edge_axis = torch.from_numpy(EDGE_AXIS).to(device)
        self.edge_corners = torch.from_numpy(EDGE_CORNERS).to(device)
        self.face_corners = torch.from_numpy(FACE_CORNERS).to(device)
        n1 = mesh_res + 1  # flat offsets of the 8 cube corners in an [n, R+1, R+1, R+1] sample grid
        self.corner_step = torch.from_numpy(CORNER_OFFSETS @ np.array([n1 * n1, n1, 1])).to(device)


def _march(coords: torch.Tensor, sdf: torch.Tensor, valid: torch.Tensor, R: int, origin: torch.Tensor,
           table: _Table) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Triangles of the cells of ``n`` voxels with sample grids ``sdf``/``valid`` ``[n, R+1, R+1, R+1]``.

    Returns the vertex keys ``[T, 3]`` int64 (lattice edge, or negative for a cell's centre vertex) and
    positions ``[T, 3, 3]`` float64 in lattice units of the triangles' corners, and the lower lattice corner
    ``[T, 3]`` int64 of each triangle's cell; cells in (voxel, x, y, z) order, triangles in table order.
    """
    negative = sdf < 0
    case = torch.zeros(sdf.shape[0], R, R, R, dtype=torch.int16, device=sdf.device)
    complete = torch.ones(sdf.shape[0], R, R, R, dtype=torch.bool, device=sdf.device)
    for c in range(8):  # bit c of the case: corner c (offset CORNER_OFFSETS[c]) is negative
        ox, oy, oz = c & 1, (c >> 1) & 1, c >> 2
        case |= negative[:, ox:ox + R, oy:oy + R, oz:oz + R].to(torch.int16) << c
        complete &= valid[:, ox:ox + R, oy:oy + R, oz:oz + R]
    active = complete & (case > 0) & (case < 255)
    cell = active.nonzero()  # [A, 4]: voxel, x, y, z
    n1 = R + 1
    base = ((cell[:, 0] * n1 + cell[:, 1]) * n1 + cell[:, 2]) * n1 + cell[:, 3]
    vals = sdf.reshape(-1)[base[:, None] + table.corner_step]  # [A, 8]
    case, neg = case[active].long(), vals < 0

    # Ambiguous faces: join the positive corners when the bilinear saddle is >= 0, i.e. when the product of
    # the positive diagonal >= that of the negative one (commutative products: same answer from both cells).
    bits = torch.zeros_like(case)
    for f in range(6):
        v, n = vals[:, table.face_corners[f]], neg[:, table.face_corners[f]]
        ambiguous = (n[:, 0] == n[:, 2]) & (n[:, 1] == n[:, 3]) & (n[:, 0] != n[:, 1])
        d02, d13 = v[:, 0] * v[:, 2], v[:, 1] * v[:, 3]
        positive_joined = torch.where(n[:, 0], d13 >= d02, d02 >= d13)
        bits |= (ambiguous & positive_joined).long() << f

    row = case * 64 + bits
    tri = table.triangles[row]  # [A, T_max, 3] table entries, -1 padded
    a, slot = (tri[..., 0] >= 0).nonzero(as_tuple=True)
    entry = tri[a, slot]  # [T, 3]
    cell_lattice = coords[cell[:, 0]] * R + cell[:, 1:]  # [A, 3] lower corner of each active cell
    positions, edge_keys = _edge_vertices(cell_lattice[a][:, None, :], vals[a][:, None, :],
                                          entry.clamp(max=CENTRE_CODE - 1), origin, table)
    centre = entry >= CENTRE_CODE
    if bool(centre.any()):  # a cell-private vertex at the mean of its loop's vertices, keyed below zero
        tc, corner = centre.nonzero(as_tuple=True)
        ac, loop = a[tc], entry[tc, corner] - CENTRE_CODE
        all_edges = torch.arange(CENTRE_CODE, device=sdf.device).expand(len(ac), -1)
        loop_pos, _ = _edge_vertices(cell_lattice[ac][:, None, :], vals[ac][:, None, :], all_edges, origin,
                                     table)
        members = ((table.centres[row[ac], loop][:, None] >> all_edges) & 1).double()  # [C, 12]
        positions[tc, corner] = (loop_pos * members[..., None]).sum(1) / members.sum(1, keepdim=True)
        edge_keys[tc, corner] = -(_pack(cell_lattice[ac] - origin) * 4 + loop) - 1
    return edge_keys, positions, cell_lattice[a]


def _edge_vertices(cell_lattice: torch.Tensor, vals: torch.Tensor, edges: torch.Tensor, origin: torch.Tensor,
                   table: _Table) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices on cube ``edges`` ``[T, K]`` of cells with lower corners ``[T, 1, 3]`` and SDF ``[T, 1, 8]``.

    Returns positions ``[T, K, 3]`` float64 in lattice units and lattice-edge keys ``[T, K]`` int64. The
    vertex sits where the SDF interpolates linearly to zero, kept a fraction ``_T_MARGIN`` of the edge away
    from its ends; every cell sharing an edge computes bit-identical values.
    """
    lower = cell_lattice + table.edge_origin[edges]  # [T, K, 3]
    axis = table.edge_axis[edges]
    keys = _pack(lower - origin) * 3 + axis
    ends = table.edge_corners[edges]  # [T, K, 2]
    v = vals.double().expand(-1, edges.shape[1], -1)
    s_lo = torch.gather(v, 2, ends[..., :1])[..., 0]
    s_hi = torch.gather(v, 2, ends[..., 1:])[..., 0]
    t = (s_lo / (s_lo - s_hi)).clamp(_T_MARGIN, 1.0 - _T_MARGIN)
    positions = lower.double() + t[..., None] * torch.nn.functional.one_hot(axis, 3).double()
    return positions, keys


def _vertex_colors(query_fn: QueryFn, vertices: torch.Tensor, cell_centre: torch.Tensor, R: int,
                   step_m: float, chunk_points: int) -> np.ndarray:
    """uint8 RGBA ``[V, 4]``: the colour head at vertices ``[V, 3]`` (lattice units), grey where none."""
    rgba = np.empty((len(vertices), 4), dtype=np.uint8)
    rgba[:, :3] = GREY_RGB
    rgba[:, 3] = 255
    start = 0
    for points, centre in zip(vertices.split(chunk_points), cell_centre.split(chunk_points), strict=True):
        _, rgb, ok = _call(query_fn, _inside(points, centre, R, step_m))
        if rgb is not None:
            rgb = (torch.nan_to_num(rgb.float(), nan=0.5).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
            rows = slice(start, start + len(points))
            rgba[rows, :3] = np.where(ok.cpu().numpy()[:, None], rgb.cpu().numpy(), rgba[rows, :3])
        start += len(points)
    return rgba


def _inside(points: torch.Tensor, centre: torch.Tensor, R: int, step_m: float) -> torch.Tensor:
    """World query points ``[N, 3]`` float32 for lattice-unit points ``[N, 3]`` (int64 or float64).

    A coordinate that lies on a voxel face (a multiple of ``R``) moves a hair (``_NUDGE`` of the step, or more
    where float32 needs it) towards ``centre`` ``[N, 3]`` (inside an allocated voxel holding the point), so a
    field that finds voxels by ``floor(p / voxel_size)`` sees an allocated voxel despite rounding, also on
    the far faces of the allocated region. Per point, so the result does not depend on chunking.
    """
    world_m = points.double() * step_m
    nudge_m = torch.clamp(world_m.abs().amax(dim=1, keepdim=True) * 2.0**-20, min=_NUDGE * step_m)
    on_face = torch.remainder(points, R) == 0
    return (world_m + on_face * torch.sign(centre - points) * nudge_m).float()


def _call(query_fn: QueryFn, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Run ``query_fn`` without autograd and check the shapes it returns; results on ``points``' device."""
    n = len(points)
    with torch.no_grad():
        out = query_fn(points)
    if not (isinstance(out, tuple) and len(out) == 3):
        raise ValidationError("query_fn", "must return a tuple (sdf [N], rgb [N, 3] or None, valid [N])")
    sdf, rgb, valid = out
    if not isinstance(sdf, torch.Tensor) or tuple(sdf.shape) != (n,):
        raise ShapeError("query_fn sdf", tuple(getattr(sdf, "shape", ())), f"[{n}]")
    if not isinstance(valid, torch.Tensor) or tuple(valid.shape) != (n,):
        raise ShapeError("query_fn valid", tuple(getattr(valid, "shape", ())), f"[{n}]")
    if rgb is not None and (not isinstance(rgb, torch.Tensor) or tuple(rgb.shape) != (n, 3)):
        raise ShapeError("query_fn rgb", tuple(getattr(rgb, "shape", ())), f"[{n}, 3]")
    rgb = None if rgb is None else rgb.to(points.device)
    return sdf.to(points.device), rgb, valid.to(device=points.device, dtype=torch.bool)


def _check_coords(voxel_coords: torch.Tensor | np.ndarray, device: torch.device) -> torch.Tensor:
    """``[M, 3]`` int64 on ``device``, deduplicated and sorted (the mesh does not depend on input order)."""
    if isinstance(voxel_coords, np.ndarray):
        if not np.issubdtype(voxel_coords.dtype, np.integer):
            raise ValidationError("voxel_coords", f"must hold integers, got dtype {voxel_coords.dtype}")
        voxel_coords = torch.from_numpy(voxel_coords.astype(np.int64))
    elif not isinstance(voxel_coords, torch.Tensor):
        raise ValidationError("voxel_coords", f"must be a tensor or array, got {type(voxel_coords).__name__}")
    dtype = voxel_coords.dtype
    if dtype.is_floating_point or dtype.is_complex or dtype == torch.bool:
        raise ValidationError("voxel_coords", f"must hold integers, got dtype {voxel_coords.dtype}")
    if voxel_coords.dim() != 2 or voxel_coords.shape[1] != 3:
        raise ShapeError("voxel_coords", tuple(voxel_coords.shape), "[M, 3]")
    coords = voxel_coords.to(device=device, dtype=torch.long)
    return torch.unique(coords, dim=0) if len(coords) else coords


def _pack(lattice: torch.Tensor) -> torch.Tensor:
    """Non-negative lattice offsets ``[..., 3]`` int64 -> keys ``[...]`` int64 (20 bits per axis)."""
    return (lattice[..., 0] << (2 * _AXIS_BITS)) | (lattice[..., 1] << _AXIS_BITS) | lattice[..., 2]


def _unpack(keys: torch.Tensor) -> torch.Tensor:
    mask = (1 << _AXIS_BITS) - 1
    return torch.stack([keys >> (2 * _AXIS_BITS), (keys >> _AXIS_BITS) & mask, keys & mask], -1)


def _empty_mesh() -> trimesh.Trimesh:
    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
