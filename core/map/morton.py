"""Morton (Z-order) codes of integer lattice coordinates, and sorted-code set helpers.

Codes interleave 21 bits per axis (x in bit 0, y in bit 1, z in bit 2, ...) of ``coord + 2**20``, so
coordinates in ``[-2**20, 2**20 - 1]`` are encodable (about +-209 km at 0.2 m voxels). The octree is
implicit: the parent of a code is ``code >> 3`` (a cell of twice the edge on the offset lattice).
"""

from __future__ import annotations

import torch

from ..errors import ShapeError, ValidationError

__all__ = [
    "MORTON_BITS",
    "MORTON_OFFSET",
    "MORTON_MIN_COORD",
    "MORTON_MAX_COORD",
    "CORNER_OFFSETS",
    "morton_encode",
    "morton_decode",
    "unique_codes_tagged",
    "morton_encode_planar",
    "unique_bounded",
    "unique_codes",
    "unique_rows",
    "check_coord_range",
    "find_sorted",
    "merge_sorted",
]

MORTON_BITS = 21
"""Bits per axis in a Morton code."""
MORTON_OFFSET = 1 << (MORTON_BITS - 1)
"""Added to each integer coordinate before encoding so negative coordinates work."""
MORTON_MIN_COORD = -MORTON_OFFSET
MORTON_MAX_COORD = MORTON_OFFSET - 1

CORNER_OFFSETS = torch.tensor(
    [[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], dtype=torch.int64
)
"""``[8, 3]`` int64 lattice offsets of a voxel's corners; row ``c`` is corner ``c = 4 dx + 2 dy + dz``."""


def _spread_bits(x: torch.Tensor) -> torch.Tensor:
    x = x & 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    x = (x | (x << 2)) & 0x1249249249249249
    return x


def _compact_bits(x: torch.Tensor) -> torch.Tensor:
    x = x & 0x1249249249249249
    x = (x ^ (x >> 2)) & 0x10C30C30C30C30C3
    x = (x ^ (x >> 4)) & 0x100F00F00F00F00F
    x = (x ^ (x >> 8)) & 0x1F0000FF0000FF
    x = (x ^ (x >> 16)) & 0x1F00000000FFFF
    x = (x ^ (x >> 32)) & 0x1FFFFF
    return x


def check_coord_range(ijk: torch.Tensor, field: str, lo: int = MORTON_MIN_COORD,
                       hi: int = MORTON_MAX_COORD) -> None:
    """Raise ``ValidationError(field)`` unless every entry of ``ijk [..., 3]`` lies in ``[lo, hi]``."""
    if ijk.numel() == 0:
        return
    smallest, largest = torch.stack(torch.aminmax(ijk)).tolist()  # one read-back
    if smallest < lo or largest > hi:
        bad = ijk.reshape(-1, 3)[((ijk.reshape(-1, 3) < lo) | (ijk.reshape(-1, 3) > hi)).any(-1)][0]
        raise ValidationError(
            field,
            f"integer voxel coordinate {bad.tolist()} lies outside the Morton-encodable range "
            f"[{lo}, {hi}] per axis",
        )


def morton_encode(ijk: torch.Tensor) -> torch.Tensor:
    """Morton-encode integer lattice coordinates.

    Args:
        ijk: ``[..., 3]`` integer tensor, each entry in ``[-2**20, 2**20 - 1]``.

    Returns:
        ``[...]`` int64 codes (non-negative; bit ``3k + a`` holds bit ``k`` of axis ``a`` + offset).

    Raises:
        ShapeError: last dimension is not 3. ValidationError: a coordinate is out of range.
    """
    if ijk.shape[-1:] != (3,):
        raise ShapeError("ijk", tuple(ijk.shape), "[..., 3]")
    if ijk.is_floating_point() or ijk.is_complex():
        raise ValidationError("ijk", f"must be an integer tensor, got {ijk.dtype}")
    ijk = ijk.to(torch.int64)
    check_coord_range(ijk, "ijk")
    # axis-first contiguous copy: the bit tricks are far faster on contiguous tensors
    return morton_encode_planar(ijk.movedim(-1, 0).contiguous())


def morton_encode_planar(ijk_planar: torch.Tensor) -> torch.Tensor:
    """:func:`morton_encode` for axis-first int64 coordinates ``[3, ...]`` -> codes ``[...]``.

    No range check: the caller guarantees every entry lies in ``[MORTON_MIN_COORD, MORTON_MAX_COORD]``.
    """
    u = ijk_planar + MORTON_OFFSET
    return _spread_bits(u[0]) | (_spread_bits(u[1]) << 1) | (_spread_bits(u[2]) << 2)


def unique_bounded(values: torch.Tensor, bound: int, max_dense: int = 1 << 24) -> torch.Tensor:
    """Sorted distinct entries of the int64 ``values`` that lie in ``[0, bound)`` (the others, e.g. -1 for
    "none", are dropped): ``u = torch.unique(values); u[(u >= 0) & (u < bound)]``, the reference it falls back
    to when ``bound > max_dense``. Otherwise the entries are marked in a dense occupancy array of ``bound``
    flags and read back in order: linear in ``N`` instead of a sort of all ``N`` values."""
    if bound > max_dense:
        u = torch.unique(values)
        return u[(u >= 0) & (u < bound)]
    ok = (values >= 0) & (values < bound)
    occupied = torch.zeros(bound + 1, dtype=torch.bool, device=values.device)  # the last flag: out of range
    occupied[torch.where(ok, values, torch.full_like(values, bound))] = True
    return torch.nonzero(occupied[:bound]).squeeze(1)


def unique_rows(rows: torch.Tensor, return_inverse: bool = False
                ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """``torch.unique(rows, dim=0)`` (and ``return_inverse``) for integer rows ``[N, 3]``: the same sorted rows
    ``[U, 3]`` (and inverse ``[N]``), through one int64 key per row (mixed radix over the rows' ranges, which sorts
    as the rows do) where those ranges fit in 62 bits, else the reference. Waits for the device once (the ranges).
    2.2 M rows (1.7 M distinct, with inverse) on the 2-core AMD EPYC: 0.13 s against 4.3 s for the reference and
    4.1 s for ``np.unique(axis=0)``."""
    if rows.dim() != 2 or rows.shape[1] != 3:
        raise ShapeError("rows", tuple(rows.shape), "[N, 3]")
    if rows.shape[0] == 0:
        out = rows.clone()
        return (out, torch.zeros(0, dtype=torch.int64, device=rows.device)) if return_inverse else out
    lo = rows.min(0).values
    sx, sy, sz = (int(e) for e in (rows.max(0).values - lo + 1).tolist())
    if float(sx) * float(sy) * float(sz) >= 2.0**62:
        return torch.unique(rows, dim=0, return_inverse=return_inverse)
    rel = rows.to(torch.int64) - lo
    packed = torch.unique((rel[:, 0] * sy + rel[:, 1]) * sz + rel[:, 2], return_inverse=return_inverse)
    keys, inverse = packed if return_inverse else (packed, None)
    uniq = (torch.stack([keys // (sy * sz), (keys // sz) % sy, keys % sz], 1) + lo).to(rows.dtype)
    return (uniq, inverse) if return_inverse else uniq


def unique_codes(ijk: torch.Tensor, max_dense_cells: int = 1 << 22) -> torch.Tensor:
    """Sorted distinct Morton codes of integer lattice coordinates ``[N, 3]`` (in range; see
    :func:`morton_encode`): what ``torch.unique(morton_encode(ijk))`` returns, the reference.

    When the points' bounding box has at most ``max_dense_cells`` cells (a depth frame's points at 0.2 m
    voxels: ~10^4-10^6), the occupied cells of the box are found with :func:`unique_bounded` and only they
    are encoded and sorted (274k points of a 640x480 7-Scenes frame: 11.9 -> 2.3 ms on a 2-core CPU);
    otherwise (a box too large, e.g. centimetre voxels) the reference. Waits for the device once (the box)."""
    if ijk.shape[0] == 0:
        return torch.unique(morton_encode(ijk))
    lo = ijk.min(0).values
    ex, ey, ez = (int(e) for e in (ijk.max(0).values - lo + 1).tolist())
    if ex * ey * ez > max_dense_cells:
        return torch.unique(morton_encode(ijk))
    rel = ijk - lo
    cells = unique_bounded((rel[:, 0] * ey + rel[:, 1]) * ez + rel[:, 2], ex * ey * ez, max_dense_cells)
    cells_ijk = torch.stack([cells // (ey * ez), (cells // ez) % ey, cells % ez], -1) + lo
    return torch.sort(morton_encode(cells_ijk)).values


def unique_codes_tagged(ijk: torch.Tensor, tag: torch.Tensor | None, n_tags: int,
                        max_dense_cells: int = 1 << 22) -> tuple[torch.Tensor, torch.Tensor]:
    """Distinct ``(voxel, tag)`` pairs of integer lattice coordinates ``ijk [N, 3]`` (in range; see
    :func:`morton_encode`) each tagged ``tag [N]`` in ``[0, n_tags)`` (e.g. the frame a point came from):
    ``(codes [U], tags [U])``, the pairs' Morton codes ascending and a voxel's pairs by ascending tag, so the first
    pair of each voxel names the first tag that has it. ``tag`` None: :func:`unique_codes` and zero tags.

    As :func:`unique_codes`: the occupied cells of the points' bounding box, now times the tags, are found with
    :func:`unique_bounded` when there are at most ``max_dense_cells`` of them, else by a sort of the pairs (the
    reference). Waits for the device once (the box), plus the unique's read-back."""
    if tag is None:
        codes = unique_codes(ijk, max_dense_cells)
        return codes, torch.zeros_like(codes)
    if tag.shape != ijk.shape[:1]:
        raise ShapeError("tag", tuple(tag.shape), f"({ijk.shape[0]},)")
    if ijk.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=ijk.device), tag.to(torch.int64)
    lo = ijk.min(0).values
    ex, ey, ez = (int(e) for e in (ijk.max(0).values - lo + 1).tolist())
    if ex * ey * ez * n_tags > max_dense_cells:
        pairs = torch.unique(torch.stack([morton_encode(ijk), tag.to(torch.int64)], 1), dim=0)  # by code, then tag
        return pairs[:, 0].contiguous(), pairs[:, 1].contiguous()
    rel = ijk - lo
    cells = (rel[:, 0] * ey + rel[:, 1]) * ez + rel[:, 2]
    keys = unique_bounded(cells * n_tags + tag, ex * ey * ez * n_tags, max_dense_cells)  # by cell, then tag
    cells, tags = torch.div(keys, n_tags, rounding_mode="floor"), keys % n_tags
    cells_ijk = torch.stack([cells // (ey * ez), (cells // ez) % ey, cells % ez], -1) + lo
    codes, order = torch.sort(morton_encode(cells_ijk), stable=True)  # a voxel's pairs keep their tag order
    return codes, tags[order]


def morton_decode(codes: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`morton_encode`: ``[...]`` int64 codes -> ``[..., 3]`` int64 coordinates."""
    codes = codes.to(torch.int64)
    xyz = torch.stack([_compact_bits(codes), _compact_bits(codes >> 1), _compact_bits(codes >> 2)], -1)
    return xyz - MORTON_OFFSET


def find_sorted(sorted_codes: torch.Tensor, perm: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """Index (via ``perm``) of each query code in ``sorted_codes``, -1 where absent. Same shape as query."""
    if sorted_codes.numel() == 0:
        return torch.full_like(query, -1)
    pos = torch.searchsorted(sorted_codes, query).clamp_(max=sorted_codes.numel() - 1)
    found = sorted_codes[pos] == query
    return torch.where(found, perm[pos], torch.full_like(query, -1))


def merge_sorted(sorted_old: torch.Tensor, perm_old: torch.Tensor, new_sorted: torch.Tensor,
                  first_new_index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Merge distinct ascending ``new_sorted`` (absent from ``sorted_old``) into it, in O(n + k log n).

    New items get indices ``first_new_index, first_new_index + 1, ...`` in ascending-code order.
    """
    n, k = sorted_old.numel(), new_sorted.numel()
    dev = sorted_old.device
    pos_new = torch.searchsorted(sorted_old, new_sorted) + torch.arange(k, device=dev)
    pos_old = torch.searchsorted(new_sorted, sorted_old) + torch.arange(n, device=dev)
    merged = torch.empty(n + k, dtype=torch.int64, device=dev)
    merged_perm = torch.empty(n + k, dtype=torch.int64, device=dev)
    merged[pos_old] = sorted_old
    merged[pos_new] = new_sorted
    merged_perm[pos_old] = perm_old
    merged_perm[pos_new] = torch.arange(first_new_index, first_new_index + k, device=dev)
    return merged, merged_perm


