"""The map: a sparse voxel octree of feature embeddings and the decoder that reads it as a signed distance field.

* ``voxel_map.py``: :class:`VoxelMap`, voxels keyed by Morton codes (``morton.py``) with their corner embeddings,
  dense index grids for lookups (``index_grid.py``), surface marks and evidence counters;
* ``field.py``: the decoder (:class:`~.field.SDFDecoder`), trilinear interpolation and field queries
  (:class:`~.field.NeuralField`, :func:`~.field.query`);
* ``evidence.py``: free-space evidence, which marks voxels the rays saw empty inactive;
* ``export.py``: the voxel map as NPZ (everything needed to rebuild the field) or a PLY of voxel centres.

The voxel structure is exported here; the field, evidence and export from their modules
(``from voxfusion.core.map.field import SDFDecoder``).
"""

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
