"""Rendering the map: volume rendering of depth and colour along camera rays (:mod:`.volume`, the paper's section
3.1), the ray-voxel intersection it walks the octree with (:mod:`.raycast`), and the occlusion render replayed as
CUDA graphs (:mod:`.graphs`). The volume renderer's public API is re-exported here; the engine's own modules import
from the module that defines a name."""

from .volume import (
    RaySamples,
    RenderConfig,
    RenderedImage,
    RenderOutput,
    VoxelHits,
    band_jitter,
    band_sample_count,
    band_samples,
    camera_directions,
    camera_rays,
    composite,
    image_chunk_rays,
    intersect_voxels,
    intersect_voxels_reference,
    render_band,
    render_depth_image,
    render_rays,
    render_rays_fixed,
    sample_along_hits,
)

__all__ = [
    "RenderConfig",
    "image_chunk_rays",
    "camera_rays",
    "camera_directions",
    "VoxelHits",
    "intersect_voxels",
    "intersect_voxels_reference",
    "RaySamples",
    "sample_along_hits",
    "RenderOutput",
    "render_rays",
    "render_rays_fixed",
    "composite",
    "band_samples",
    "band_jitter",
    "band_sample_count",
    "render_band",
    "RenderedImage",
    "render_depth_image",
]
