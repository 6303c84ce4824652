"""Sparse marching cubes over allocated voxels: one welded, coloured triangle mesh.

The SDF is sampled on one global lattice: lattice point ``L`` (int, ``[3]``) sits at world position
``L * voxel_size_m / mesh_res`` and voxel ``ijk`` owns the points ``ijk * mesh_res + (0..mesh_res)`` on each
axis, so neighbouring voxels share their border samples. Within a chunk of voxels every lattice point is
queried once (deduplicated), and always at the same point whatever the chunking (see the owner rule
below), so cells on both sides of a voxel border see bit-identical values. A cell (lattice cube) is
meshed only when it lies in an allocated voxel and all 8 corners are valid; each mesh vertex is keyed by
its lattice edge ``(lower lattice point, axis)``, which welds vertices shared by cells (and voxels) exactly.
The case table (:mod:`.cases`) draws the same iso-lines on a face from both sides, so the surface has no
cracks, and its triangles are wound with normals towards positive SDF (free space); ambiguous faces follow
the asymptotic decider, and the rare loop that cannot be triangulated without an edge another cell might
also draw gets a vertex of its own at the loop's mean.

Queries on a voxel face are moved about 1e-5 of a lattice step (more far from the origin, as float32 needs)
into one allocated voxel holding the point (its owner: the first such voxel in sorted order), so a field
that finds a point's voxel by ``floor(p / v)`` sees it as valid on the far faces of the allocated region
too; the mesh moves by as little.

Two levels (the default from ``mesh_res`` 8 on, :func:`coarse_res_for`): at a 1 cm lattice (``mesh_res`` 20
for 0.2 m voxels) a voxel has 9,261 samples, and most of a voxel is far from the surface. The field is first
sampled at a coarse lattice (e.g. 5 cm) and only the coarse cells that can hold the surface are meshed at
the fine lattice, as "voxels" of their own: same global fine lattice, so the mesh is the same as a one-level
extraction's up to the sampling nudge. On the synthetic room this queries 10-20 % of the fine samples.

Memory: about 50-60 bytes per lattice sample of one chunk (``chunk_points`` samples), plus whatever
``query_fn`` needs for ``chunk_points`` points, plus the mesh. Samples on the border of two chunks are
queried by both (a few % more queries at the default chunk size).
"""

from __future__ import annotations

import itertools
import numbers
from collections.abc import Callable

import numpy as np
import torch
import trimesh

from ..errors import ShapeError, ValidationError
from ..map.morton import unique_rows
from .cases import (
    CENTRE_CODE,
    CORNER_OFFSETS,
    EDGE_AXIS,
    EDGE_CORNERS,
    EDGE_ORIGIN,
    FACE_CORNERS,
    triangle_table,
)

__all__ = ["QueryFn", "KeepFn", "GREY_RGB", "extract_mesh", "coarse_res_for"]

QueryFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]]
"""``query(points_world [N, 3] float32 m) -> (sdf_m [N], rgb [N, 3] in [0, 1] or None, valid [N] bool)``."""

KeepFn = Callable[[torch.Tensor], torch.Tensor]
"""``keep(centroids_world [F, 3] float64 m) -> [F] bool``: which faces to keep."""

GREY_RGB = (128, 128, 128)
"""Vertex colour (uint8 RGB) used when the query returns no colour."""

_AXIS_BITS = 20  # bits per axis of a packed lattice-point key (3 * 20 bits, times 3 edge axes, fits int64)
_T_MARGIN = 1e-3  # a vertex stays this fraction of an edge away from its ends (no coincident vertices)
_NEAR_RATIO = 0.6  # coarse cells with a corner |sdf| <= this times their diagonal are meshed finely
_NUDGE = 1e-5  # queries on voxel faces move this fraction of a lattice step into their voxel (see _inside)


def extract_mesh(
    voxel_coords: torch.Tensor | np.ndarray,
    voxel_size_m: float,
    query_fn: QueryFn,
    mesh_res: int = 8,
    chunk_points: int = 2**18,
    device: torch.device | str | None = None,
    coarse_res: int | None = None,
    keep_fn: KeepFn | None = None,
    lattice_query_fn: QueryFn | None = None,
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
            ``voxel_size_m / mesh_res`` (0.2 m / 20 = 10 mm).
        chunk_points: bound on points per query call and on lattice samples handled at once (memory stays
            bounded however large the map: the fine lattice is sampled and marched chunk by chunk).
        device: where lattice tensors live and queries run; default: ``voxel_coords``' device or CPU.
        coarse_res: two-level extraction (:func:`coarse_res_for`, chosen automatically when None): the SDF
            is first sampled at ``coarse_res`` samples per voxel edge, and only the coarse cells that can
            hold the surface (a sign change, or a corner closer to it than the cell diagonal) are sampled
            at the full ``mesh_res``. ``coarse_res = mesh_res`` (or 0) samples every voxel at full
            resolution. ``mesh_res`` must be a multiple of ``coarse_res``.
        keep_fn: optional face filter ``centroids_world [F, 3] float64 m -> keep [F] bool`` (e.g. the
            observation support, :class:`.support.SurfaceSupport`); dropped faces' unused vertices go too.
        lattice_query_fn: the query used at the lattice samples, whose colour is never used (e.g. one that
            skips the colour head); default ``query_fn``. Must return the same SDF as ``query_fn``.

    Returns:
        A ``trimesh.Trimesh`` (not processed: vertices are exactly the welded edge vertices; each sits at
        the linear zero crossing of its lattice edge, at least 1e-3 of the edge from either end), vertices
        float64 world metres ``[V, 3]``, faces int64 ``[F, 3]`` wound with normals towards positive SDF,
        vertex colours uint8 RGBA ``[V, 4]`` (grey :data:`GREY_RGB` where ``rgb`` is None). Empty when no
        allocated cell contains the surface. The same inputs give the same mesh for any ``chunk_points``
        (up to float rounding of samples shared by two chunks of the fine pass).

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
    coarse = coarse_res_for(int(mesh_res)) if coarse_res is None else int(coarse_res)
    sdf_fn = query_fn if lattice_query_fn is None else lattice_query_fn
    if coarse < 0 or (coarse and int(mesh_res) % coarse):
        raise ValidationError("coarse_res", f"must divide mesh_res={mesh_res} (or be 0), got {coarse_res!r}")
    if len(coords) == 0:
        return _empty_mesh()

    R, chunk_points = int(mesh_res), int(chunk_points)
    extent = (coords.max(dim=0).values - coords.min(dim=0).values + 1) * R + 1
    if int(extent.max()) >= 2**_AXIS_BITS:
        raise ValidationError(
            "voxel_coords", f"map spans {int(extent.max())} lattice steps on an axis; the limit is "
            f"{2**_AXIS_BITS - 1} (lower mesh_res or extract in parts)")
    step_m = float(voxel_size_m) / R
    if 0 < coarse < R:  # cells of the coarse lattice that can hold the surface, as "voxels" of size v/coarse
        coords = _near_surface_cells(coords, coarse, float(voxel_size_m) / coarse, sdf_fn, chunk_points)
        R = R // coarse
        if len(coords) == 0:
            return _empty_mesh()
    origin = coords.min(dim=0).values * R  # lattice point packed as key 0

    # Triangle corners as vertex keys and positions, chunk by chunk over the (sorted) cells, then welded.
    table = _Table(device, R)
    all_cells = _Cells(coords, R)
    n1 = R + 1
    per_chunk = max(1, chunk_points // n1**3)
    keys, positions, cells = [], [], []
    for start in range(0, len(coords), per_chunk):
        n = min(per_chunk, len(coords) - start)
        sdf, valid, sample_index = _sample_lattice(all_cells, start, n, step_m, sdf_fn, chunk_points)
        k, p, c = _march(coords[start:start + n], sdf[sample_index], valid[sample_index], R, origin,
                         table)
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
    faces = faces.view(-1, 3)

    if keep_fn is not None:
        faces, vertices, cell_centre = _filter_faces(faces, vertices, cell_centre, step_m, keep_fn)
        if len(faces) == 0:
            return _empty_mesh()
    colors = _vertex_colors(query_fn, vertices, cell_centre, R, step_m, chunk_points)
    vertices = vertices * step_m
    return trimesh.Trimesh(vertices=vertices.cpu().numpy(), faces=faces.cpu().numpy(),
                           vertex_colors=colors, process=False)


def coarse_res_for(mesh_res: int) -> int:
    """Coarse samples per voxel edge for two-level extraction at ``mesh_res``: the divisor ``c >= 2`` of
    ``mesh_res`` whose fine factor ``mesh_res / c`` is nearest 5 (20 -> 4, i.e. 5 cm coarse cells of 1 cm
    fine cells at 0.2 m voxels; 16 -> 4; 12 -> 3); 0 (single level) below 8 or without such a divisor."""
    if mesh_res < 8:
        return 0
    divisors = [c for c in range(2, mesh_res // 2 + 1) if mesh_res % c == 0 and mesh_res // c >= 2]
    if not divisors:
        return 0
    return min(divisors, key=lambda c: (abs(mesh_res // c - 5), -c))


class _Cells:
    """The sorted set of cells being meshed (``[n, 3]`` int64, unique and sorted lexicographically, ``R`` lattice
    steps per edge), for finding the owner of a lattice sample: the first cell in sorted order that holds it. The
    owner depends only on the sample and the whole set, never on how the cells are chunked."""

    def __init__(self, coords: torch.Tensor, R: int) -> None:
        self.R = R
        self.coords = coords  # sorted, unique: row i is the cell of key i
        self.lo = coords.min(dim=0).values - 1
        self.keys = _pack(coords - self.lo)  # sorted as coords are (lexicographically)
        self.samples = _CellSamples(R, coords.device)

    def neighbours(self, start: int, n: int) -> torch.Tensor:
        """``[n, 27]`` int64: for cells ``start .. start + n`` and each offset of :data:`_NEIGHBOURS`, the row of
        that neighbour in the set, or -1 where it is not in the set."""
        cand = self.coords[start:start + n, None, :] + _NEIGHBOURS.to(self.coords.device)  # [n, 27, 3]
        key = _pack(cand - self.lo)
        pos = torch.searchsorted(self.keys, key).clamp(max=len(self.keys) - 1)
        return torch.where(self.keys[pos] == key, pos, -1)

    def owners(self, lattice: torch.Tensor) -> torch.Tensor:
        """``[S, 3]`` int64 owner cell of each lattice point ``[S, 3]`` (each lies in at least one cell): the plain
        rule, point by point (up to 8 searches each); :meth:`owned_samples` computes the same per cell."""
        base = torch.div(lattice, self.R, rounding_mode="floor")
        on_face = torch.remainder(lattice, self.R) == 0
        owner = base.clone()  # a point inside a cell's interior belongs to that cell
        found = ~on_face.any(dim=1)
        for d in ((1, 1, 1), (1, 1, 0), (1, 0, 1), (1, 0, 0), (0, 1, 1), (0, 1, 0), (0, 0, 1), (0, 0, 0)):
            delta = torch.tensor(d, device=base.device)
            allowed = (on_face | (delta == 0)).all(dim=1) & ~found
            if not bool(allowed.any()):
                continue
            cand = base[allowed] - delta
            key = _pack(cand - self.lo)
            pos = torch.searchsorted(self.keys, key).clamp(max=len(self.keys) - 1)
            hit = self.keys[pos] == key
            rows = allowed.nonzero().squeeze(1)[hit]
            owner[rows] = cand[hit]
            found[rows] = True
        return owner

    def owned_samples(self, start: int, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Each lattice sample of cells ``start .. start + n`` (``(R + 1)^3`` per cell, in
        :class:`_CellSamples` order) as its owner's row in the set and its offset within the owner: ``rows
        [n, (R+1)^3]`` int64 and ``offsets [n, (R+1)^3]`` int64 (flat, into ``(R+1)^3``). One pair per lattice
        point, whichever cell lists it: the point's canonical name. The owner is :meth:`owners`' (the first of
        the at most 8 cells holding it in sorted order), found per cell and per kind of sample (which faces it
        lies on, 27 kinds) from the cell's 26 neighbours rather than by a search per sample."""
        table = self.samples
        nb = self.neighbours(start, n)
        present = torch.cat([nb, torch.full((n, 1), -1, dtype=torch.long, device=nb.device)], 1) >= 0  # [n, 28]
        first = present[:, table.candidates].to(torch.uint8).argmax(dim=2)  # [n, 27]: the cell itself is present
        owner = table.candidates[table.kinds, first]  # [n, 27] the owner's _NEIGHBOURS row, per kind
        kind = table.kind.expand(n, -1)
        rows = nb.gather(1, owner).gather(1, kind)
        offsets = table.sample_ids - table.shift[owner].gather(1, kind)
        return rows, offsets


class _CellSamples:
    """The ``(R + 1)^3`` lattice samples of a cell of ``R`` steps, in (x, y, z) order (``local [S, 3]`` int64
    offsets), by kind: which faces a sample lies on (per axis: coordinate 0, which the neighbour below on that
    axis holds too, ``R``, which the one above holds, or neither; ``kind [S]``, 27 kinds). For each kind, the
    cells holding such a sample as :data:`_NEIGHBOURS` rows in the cells' sorted order (``candidates [27, 8]``,
    padded with 27), and by how much a sample's flat offset drops when it is named from a neighbour
    (``shift [27]``)."""

    def __init__(self, R: int, device: torch.device) -> None:
        n1 = R + 1
        local = np.stack(np.meshgrid(*[np.arange(n1)] * 3, indexing="ij"), -1).reshape(-1, 3)
        side = np.where(local == 0, 0, np.where(local == R, 2, 1))  # [S, 3]: below, neither, above
        candidates = np.full((27, 8), 27, dtype=np.int64)
        for k, sides in enumerate(itertools.product(range(3), repeat=3)):
            axes = [(-1, 0) if v == 0 else (0, 1) if v == 2 else (0,) for v in sides]
            for j, e in enumerate(itertools.product(*axes)):  # lexicographic: the cells' sorted order
                candidates[k, j] = (e[0] + 1) * 9 + (e[1] + 1) * 3 + (e[2] + 1)
        self.local = torch.from_numpy(local).to(device)
        self.kind = torch.from_numpy(side @ np.array([9, 3, 1]))[None].to(device)  # [1, S]
        self.candidates = torch.from_numpy(candidates).to(device)
        self.shift = (_NEIGHBOURS @ torch.tensor([n1 * n1, n1, 1]) * R).to(device)
        self.sample_ids = torch.arange(len(local), device=device)
        self.kinds = torch.arange(27, device=device)


_NEIGHBOURS = torch.cartesian_prod(*[torch.arange(-1, 2)] * 3)
"""``[27, 3]`` int64 offsets of a cell and its neighbours, in lexicographic order (row 13 is the cell)."""


def _sample_lattice(cells: _Cells, start: int, n: int, step_m: float, query_fn: QueryFn, chunk_points: int
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SDF at the lattice samples of cells ``start .. start + n`` of ``cells`` (``R + 1`` per edge), each
    queried once.

    Returns ``sdf [S]`` float32, ``valid [S]`` bool over the deduplicated samples and ``sample_index
    [n, R+1, R+1, R+1]`` int64 into them. Each sample is looked up from inside its owner cell
    (:class:`_Cells`), see :func:`_inside`. The samples whose owner is one of these cells are listed from their
    owner; the others (on the border with cells of other chunks) once each, after them.
    """
    R = cells.R
    n1 = R + 1
    per_cell = n1**3
    rows, offsets = cells.owned_samples(start, n)
    names = (rows * per_cell + offsets).view(-1) - start * per_cell  # [n S]; 0 .. n S - 1 when owned here
    own = names == torch.arange(len(names), device=names.device)
    own_flat = own.nonzero().squeeze(1)
    in_chunk = (names >= 0) & (names < len(names))
    # each sample's slot in own_flat (read through a clamped name for the samples outside, which are set below)
    sample_index = (own.cumsum(0) - 1).gather(0, names.clamp(0, len(names) - 1))
    outside = (~in_chunk).nonzero().squeeze(1)
    outside_names, outside_index = torch.unique(names[outside], return_inverse=True)
    sample_index[outside] = len(own_flat) + outside_index
    owner_rows = torch.cat([rows.view(-1).index_select(0, own_flat), outside_names // per_cell + start])
    local = torch.cat([offsets.view(-1).index_select(0, own_flat), outside_names % per_cell])
    owner = cells.coords.index_select(0, owner_rows)
    lattice = owner * R + cells.samples.local.index_select(0, local)
    sdf, valid = [], []
    for first in range(0, len(lattice), chunk_points):
        part = slice(first, first + chunk_points)
        s, _, ok = _call(query_fn, _inside(lattice[part], owner[part] * R + R / 2, R, step_m))
        sdf.append(s.float())
        valid.append(ok & torch.isfinite(s))
    return torch.cat(sdf), torch.cat(valid), sample_index.view(-1, n1, n1, n1)


def _near_surface_cells(coords: torch.Tensor, c: int, cell_m: float, query_fn: QueryFn,
                        chunk_points: int) -> torch.Tensor:
    """Coarse cells (``[C, 3]`` int64 in units of ``cell_m``, ``c`` per voxel edge) of voxels ``coords``
    that may hold the zero level set: a sign change between valid corners, or a valid corner with
    ``|sdf| <= 0.6 *`` the cell diagonal (any point of a cube is within half its diagonal of some
    corner, so a surface inside the cell is that close to a corner of an exact SDF; the margin covers a
    learned field that is not exactly one)."""
    all_cells = _Cells(coords, c)
    n1 = c + 1
    per_chunk = max(1, chunk_points // n1**3)
    diagonal = float(np.sqrt(3.0) * cell_m) * _NEAR_RATIO
    out = []
    for start in range(0, len(coords), per_chunk):
        part = coords[start:start + per_chunk]
        sdf, valid, index = _sample_lattice(all_cells, start, len(part), cell_m, query_fn, chunk_points)
        s, ok = sdf[index], valid[index]  # [n, c+1, c+1, c+1]
        near = torch.zeros(len(part), c, c, c, dtype=torch.bool, device=coords.device)
        neg = torch.zeros_like(near)
        pos = torch.zeros_like(near)
        for corner in range(8):
            ox, oy, oz = corner & 1, (corner >> 1) & 1, corner >> 2
            cs, cok = s[:, ox:ox + c, oy:oy + c, oz:oz + c], ok[:, ox:ox + c, oy:oy + c, oz:oz + c]
            near |= cok & (cs.abs() <= diagonal)
            neg |= cok & (cs < 0)
            pos |= cok & (cs >= 0)
        near |= neg & pos
        v, x, y, z = near.nonzero(as_tuple=True)
        out.append(part[v] * c + torch.stack([x, y, z], 1))
    return unique_rows(torch.cat(out))  # sorted (lexicographically), as the fine pass expects


def _filter_faces(faces: torch.Tensor, vertices: torch.Tensor, cell_centre: torch.Tensor, step_m: float,
                  keep_fn: KeepFn) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Faces ``[F, 3]`` whose centroid ``keep_fn`` keeps, with unused vertices (lattice units) removed."""
    centroids = vertices[faces].mean(dim=1) * step_m
    keep = keep_fn(centroids)
    if not isinstance(keep, torch.Tensor) or tuple(keep.shape) != (len(faces),):
        raise ShapeError("keep_fn result", tuple(getattr(keep, "shape", ())), f"[{len(faces)}]")
    faces = faces[keep.to(faces.device, torch.bool)]
    used, remap = torch.unique(faces, return_inverse=True)
    return remap.view(-1, 3), vertices[used], cell_centre[used]


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
    return unique_rows(coords)


def _pack(lattice: torch.Tensor) -> torch.Tensor:
    """Non-negative lattice offsets ``[..., 3]`` int64 -> keys ``[...]`` int64 (20 bits per axis)."""
    return (lattice[..., 0] << (2 * _AXIS_BITS)) | (lattice[..., 1] << _AXIS_BITS) | lattice[..., 2]


def _empty_mesh() -> trimesh.Trimesh:
    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
