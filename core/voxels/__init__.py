"""Sparse voxel map (:class:`VoxelMap`) keyed by Morton codes; see ``voxel_map.py`` and ``morton.py``."""

from .morton import (
    CORNER_OFFSETS,
    MORTON_BITS,
    MORTON_MAX_COORD,
    MORTON_MIN_COORD,
    MORTON_OFFSET,
    morton_decode,
    morton_encode,
)
from .voxel_map import SURFACE_CELLS, MemoryReport, SurfacePoints, VoxelMap

__all__ = [
    "MORTON_BITS",
    "MORTON_OFFSET",
    "MORTON_MIN_COORD",
    "MORTON_MAX_COORD",
    "CORNER_OFFSETS",
    "morton_encode",
    "morton_decode",
    "MemoryReport",
    "VoxelMap",
    "SURFACE_CELLS",
    "SurfacePoints",
]
