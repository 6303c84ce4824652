"""Depth outlier filter: drop depth pixels that no neighbour confirms (flying pixels, speckle).

A depth sensor's isolated outliers (speckle, multipath, the "flying pixels" LiDAR and Kinect-class sensors
produce along depth edges) are single pixels or thin streaks whose depth agrees with none of their
neighbours. Back-projected, they land in free space in front of the real surfaces, where mapping would
allocate voxels for them and supervise a phantom surface. Real surfaces, even thin ones or surfaces seen
at grazing incidence, are continuous across several pixels.

The test (support counting): pixel ``p`` with depth ``d_p > 0`` keeps its depth when at least
``min_support`` of the other pixels ``q`` of the ``window_px x window_px`` window centred on it have a
valid depth that agrees with it within a relative tolerance::

    |ln d_q - ln d_p| <= ln(1 + rel_tol)        i.e.  d_q / d_p in [1 / (1 + rel_tol), 1 + rel_tol]

The criterion is symmetric (``q`` supports ``p`` exactly when ``p`` supports ``q``), so each pair of
pixels is compared once: ``(window_px**2 - 1) / 2`` shifted whole-image comparisons, no per-pixel Python
loop. Pixels without support become invalid (0) for both tracking and mapping: they neither allocate
voxels nor supervise rays. See :func:`~.framedata.frame_to_device`, where every frame goes through it.

Example (a flat wall at 2 m with one flying pixel at 0.6 m)::

    >>> depth = torch.full((8, 8), 2.0)
    >>> depth[4, 4] = 0.6
    >>> keep = depth_outlier_mask(depth, DepthFilterConfig())
    >>> bool(keep[4, 4]), int(keep.sum())
    (False, 63)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from . import native
from .errors import ConfigError, ShapeError

__all__ = ["DepthFilterConfig", "depth_support", "depth_outlier_mask"]


@dataclass(frozen=True)
class DepthFilterConfig:
    """Options of the neighbourhood-support depth filter (module docstring).

    Defaults, measured on the first frame of each dev capture (``../shared/data``) and the synthetic room:
    with a 5 x 5 window, 3 % tolerance and 4 supporters, 0.00-0.01 % of the valid pixels of TUM fr1/fr3,
    7-Scenes and the synthetic room and 0.5 % of the Stray iPhone LiDAR frame are dropped, while of 2 %
    pixels set to random depths in 0.3-1.0 m, 0.0-0.4 % survive (on TUM fr1 desk 2.8 %: those land within
    3 % of a real surface at that range, where they do no harm). Cost: 8-11 ms for a 640 x 480 frame on
    one CPU core (``bench/bench_outliers.py`` measures it).
    """

    enabled: bool = True
    """Apply the filter (False: depth passes unchanged, as before this filter existed)."""
    window_px: int = 5
    """Edge of the square window around each pixel, in pixels (odd, >= 3). A 5 x 5 window tolerates
    streaks of flying pixels up to about 2 px wide and still sees both sides of a thin real structure."""
    rel_tol: float = 0.03
    """A neighbour supports a pixel when their depths differ by at most this fraction (3 %: 6 cm at 2 m,
    about 3 sigma of Kinect-class noise at 3-4 m and a 2 px step on a plane seen at ~80 deg incidence)."""
    min_support: int = 4
    """Supporting neighbours needed to keep a pixel (of ``window_px**2 - 1``). 4 keeps a 1 px wide line
    (its 4 in-line neighbours in a 5 x 5 window; the last 2 px at each end have fewer and go), the corner
    of a surface and every pixel of a smooth surface, and drops isolated pixels, pairs and triples."""

    def __post_init__(self) -> None:
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise ConfigError("window_px", f"must be an odd integer >= 3, got {self.window_px}")
        if not (math.isfinite(self.rel_tol) and 0 < self.rel_tol < 1):
            raise ConfigError("rel_tol", f"must be in (0, 1), got {self.rel_tol}")
        if not 1 <= self.min_support <= self.window_px**2 - 1:
            raise ConfigError("min_support",
                              f"must be in [1, {self.window_px**2 - 1}] (window_px**2 - 1), got {self.min_support}")


def depth_support(depth_m: torch.Tensor, window_px: int = 5, rel_tol: float = 0.03) -> torch.Tensor:
    """Count, for each pixel, the neighbours in its window whose depth agrees with its own.

    Args:
        depth_m: ``[H, W]`` float depth in metres, 0 (or any value <= 0, or non-finite) = invalid.
        window_px: odd window edge in pixels.
        rel_tol: relative tolerance (see the module docstring).

    Returns:
        ``[H, W]`` uint8 number of supporting neighbours (0 for invalid pixels). Neighbours outside the
        image count as unsupported.

    On a CPU the pairs are counted by a C loop (``core/native/depth_support.c``; the same counts, tested), elsewhere
    (or without a C compiler) by the operators below: 12 shifted comparisons of a 5 x 5 window, ~2-3 ms at 320 x 240
    on the 2-core AMD EPYC.
    """
    if depth_m.dim() != 2:
        raise ShapeError("depth_m", tuple(depth_m.shape), "[H, W]")
    if window_px < 3 or window_px % 2 == 0:
        raise ConfigError("window_px", f"must be an odd integer >= 3, got {window_px}")
    h, w = depth_m.shape
    r = window_px // 2
    valid = torch.isfinite(depth_m) & (depth_m > 0)
    # log depth; NaN for invalid pixels, so that they agree with nothing (comparisons with NaN are False)
    ld = torch.where(valid, depth_m.float().clamp(min=1e-30).log(), torch.full_like(depth_m, math.nan,
                                                                                  dtype=torch.float32))
    tol = math.log1p(rel_tol)
    kernels = native.depth_support_kernels() if ld.device.type == "cpu" else None
    if kernels is not None:  # the same counts from one C loop (core/native/depth_support.c)
        ld = ld.contiguous()
        count = torch.empty(h, w, dtype=torch.uint8)
        kernels.depth_support(ld.data_ptr(), h, w, r, tol, count.data_ptr())
        return count
    count = torch.zeros(h, w, dtype=torch.uint8, device=depth_m.device)
    for dy in range(0, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx <= 0:
                continue  # each unordered pair of offsets once; (0, 0) is the pixel itself
            if dy >= h or abs(dx) >= w:
                continue
            # pixel a at (y, x) and its neighbour b at (y + dy, x + dx), both inside the image
            a_rows, b_rows = slice(0, h - dy), slice(dy, h)
            a_cols, b_cols = slice(max(0, -dx), w - max(0, dx)), slice(max(0, dx), w + min(0, dx))
            agree = (ld[a_rows, a_cols] - ld[b_rows, b_cols]).abs_() <= tol
            count[a_rows, a_cols] += agree
            count[b_rows, b_cols] += agree
    return count


def depth_outlier_mask(depth_m: torch.Tensor, config: DepthFilterConfig) -> torch.Tensor:
    """``[H, W]`` bool: the pixel has a valid depth that enough neighbours support (keep it).

    With ``config.enabled`` False every valid pixel is kept.
    """
    if depth_m.dim() != 2:
        raise ShapeError("depth_m", tuple(depth_m.shape), "[H, W]")
    valid = torch.isfinite(depth_m) & (depth_m > 0)
    if not config.enabled:
        return valid
    return valid & (depth_support(depth_m, config.window_px, config.rel_tol) >= config.min_support)
