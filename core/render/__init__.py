"""Rendering the map: volume rendering of depth and colour along camera rays (:mod:`.volume`, the paper's section
3.1), the ray-voxel intersection it walks the octree with (:mod:`.raycast`), and the occlusion render replayed as
CUDA graphs (:mod:`.graphs`). The volume renderer's public API is re-exported here; the engine's own modules import
from the module that defines a name."""

from .volume import *  # noqa: F403 - the renderer's public API, listed once (volume.__all__)
from .volume import __all__  # noqa: F401
