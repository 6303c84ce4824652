"""Observation support for mesh faces: surface only where depth was actually observed.

The neural field is defined in every allocated voxel, and where no depth point ever landed (behind an
object, outside the views, in a voxel an outlier allocated) its zero level set can be anything: extraction
would draw phantom sheets there. Mapping marks the surface cells (:data:`~..map.SURFACE_CELLS` per voxel
edge, 1.25 cm in 0.2 m voxels) that held a posed depth point
(:meth:`~..map.VoxelMap.add_surface_points`); a mesh face is kept only when its centroid lies in such a
cell or one of its 26 neighbours (``dilate=1``), i.e. within at most two cell diagonals (4.3 cm at 0.2 m
voxels, under the 5 cm of the phantom-surface figure) of an observed depth point.

Example:
    >>> import torch
    >>> support = SurfaceSupport(torch.tensor([[0, 0, 40]]), cell_size_m=0.025)
    >>> support(torch.tensor([[0.01, 0.01, 1.01], [0.2, 0.2, 1.5]])).tolist()
    [True, False]
"""

from __future__ import annotations

import torch

from ..errors import ShapeError, ValidationError
from ..map import SURFACE_CELLS, VoxelMap

__all__ = ["SurfaceSupport"]

_BITS = 21  # bits per axis of a packed cell key


class SurfaceSupport:
    """Membership test "is this point within ``dilate`` cells of an observed surface cell?".

    Args:
        cells: ``[K, 3]`` int64 global coordinates of observed cells; cell ``c`` covers
            ``[c, c + 1) * cell_size_m`` in world metres.
        cell_size_m: cell edge in metres.
        dilate: neighbourhood radius in cells (Chebyshev): 0 = the cell itself, 1 = its 3 x 3 x 3 block.
    """

    def __init__(self, cells: torch.Tensor, cell_size_m: float, dilate: int = 1) -> None:
        if cells.dim() != 2 or cells.shape[1] != 3:
            raise ShapeError("cells", tuple(cells.shape), "[K, 3]")
        if not cell_size_m > 0:
            raise ValidationError("cell_size_m", f"must be > 0, got {cell_size_m}")
        if dilate < 0:
            raise ValidationError("dilate", f"must be >= 0, got {dilate}")
        self.cell_size_m = float(cell_size_m)
        self.device = cells.device
        self.n_cells = len(cells)
        if self.n_cells == 0:
            self._keys = torch.empty(0, dtype=torch.int64, device=self.device)
            self._lo = torch.zeros(3, dtype=torch.int64, device=self.device)
            self._hi = self._lo - 1
            self._offsets = torch.zeros(1, 3, dtype=torch.int64, device=self.device)
            return
        r = torch.arange(-dilate, dilate + 1, device=self.device)
        offsets = torch.cartesian_prod(r, r, r).view(-1, 3)
        # nearest first (the cell itself, then faces, edges, corners): most points are settled by the first few
        self._offsets = offsets[torch.argsort(offsets.abs().sum(1), stable=True)]
        self._lo = cells.min(0).values - dilate
        self._hi = cells.max(0).values + dilate
        if int((self._hi - self._lo).max()) >= 1 << _BITS:
            raise ValidationError("cells", f"span more than {1 << _BITS} cells on an axis")
        self._keys = torch.unique(self._pack(cells - self._lo))  # sorted; neighbours are probed per query

    @classmethod
    def from_map(cls, voxel_map: VoxelMap, dilate: int = 1) -> SurfaceSupport | None:
        """The support of ``voxel_map``'s observed-surface mask; None when the map has no such evidence
        (a checkpoint saved before it existed), so callers keep every face."""
        if not voxel_map.has_surface_evidence:
            return None
        return cls(voxel_map.surface_cells(), voxel_map.voxel_size_m / SURFACE_CELLS, dilate)

    def _cells(self, points_world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The cell ``[N, 3]`` int64 of each point ``[N, 3]`` (world metres) and whether its neighbourhood can
        hold a supported cell at all (``[N]`` bool)."""
        if points_world.dim() != 2 or points_world.shape[1] != 3:
            raise ShapeError("points_world", tuple(points_world.shape), "[N, 3]")
        cell = torch.floor(points_world.to(self.device, torch.float64) / self.cell_size_m).to(torch.int64)
        return cell, ((cell >= self._lo) & (cell <= self._hi)).all(dim=1) & (self.n_cells > 0)

    def __call__(self, points_world: torch.Tensor) -> torch.Tensor:
        """``[N]`` bool: point ``[N, 3]`` (world metres) lies in a supported cell."""
        cell, inside = self._cells(points_world)
        out = torch.zeros(len(cell), dtype=torch.bool, device=self.device)
        pending = inside.nonzero().squeeze(1)  # points not yet found supported
        top = self._lo + (1 << _BITS) - 1
        for offset in self._offsets:  # a point stops probing once one of its neighbours is found
            if len(pending) == 0:
                break
            c = cell[pending] + offset
            ok = ((c >= self._lo) & (c <= top)).all(1)
            key = self._pack((c - self._lo).clamp(min=0))
            pos = torch.searchsorted(self._keys, key).clamp(max=len(self._keys) - 1)
            found = (self._keys[pos] == key) & ok
            out[pending[found]] = True
            pending = pending[~found]
        return out

    def reference(self, points_world: torch.Tensor) -> torch.Tensor:
        """:meth:`__call__` the plain way: every point probes its whole neighbourhood at once (``[N]`` bool)."""
        cell, inside = self._cells(points_world)
        out = torch.zeros(len(cell), dtype=torch.bool, device=self.device)
        rows = inside.nonzero().squeeze(1)
        for part in rows.split(1 << 15):  # bounds the probe tensors to ~40 MB
            c = cell[part][:, None, :] + self._offsets  # [n, 27, 3] the neighbourhood
            ok = ((c >= self._lo) & (c <= self._lo + (1 << _BITS) - 1)).all(-1)
            keys = self._pack((c - self._lo).clamp(min=0).view(-1, 3)).view(len(part), -1)
            pos = torch.searchsorted(self._keys, keys).clamp(max=len(self._keys) - 1)
            out[part] = ((self._keys[pos] == keys) & ok).any(dim=1)
        return out

    @staticmethod
    def _pack(c: torch.Tensor) -> torch.Tensor:
        return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]
