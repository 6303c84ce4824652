"""Frames on the compute device, and random pixel sampling for tracking and mapping.

A :class:`FrameData` holds one frame's depth, colour and intrinsics as tensors on the map's device,
plus the flat indices of its usable pixels, so every optimisation iteration samples rays without
touching numpy or the disk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .datasets.frame import RGBDFrame
from .depth_filter import DepthFilterConfig, depth_outlier_mask
from .errors import ValidationError

__all__ = ["FrameData", "PixelBatch", "flat_uv", "frame_to_device", "sample_pixels", "sample_valid_pixels"]

_DEFAULT_DEPTH_FILTER = DepthFilterConfig()


@dataclass
class FrameData:
    """One frame's observations on the compute device.

    Attributes:
        index: position of the frame in its capture.
        timestamp_s: capture time (s).
        depth_m: ``[H, W]`` float32 metres, 0 = invalid (already range-, confidence- and outlier-filtered,
            see :func:`frame_to_device`).
        color: ``[H, W, 3]`` float32 RGB in [0, 1], or None for depth-only captures.
        K: ``[3, 3]`` float64 intrinsics for ``(W, H)``.
        valid_idx: ``[P]`` int64 flat indices ``v * W + u`` of pixels with valid depth.
    """

    index: int
    timestamp_s: float
    depth_m: torch.Tensor
    color: torch.Tensor | None
    K: torch.Tensor
    valid_idx: torch.Tensor

    @property
    def height(self) -> int:
        return int(self.depth_m.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth_m.shape[1])

    @property
    def n_valid(self) -> int:
        return int(self.valid_idx.numel())


@dataclass
class PixelBatch:
    """Sampled pixels of one frame: ``uv [N, 2]`` float64 (u = column, v = row), ``depth_m [N]``,
    ``color [N, 3]`` in [0, 1] or None."""

    uv: torch.Tensor
    depth_m: torch.Tensor
    color: torch.Tensor | None


def frame_to_device(frame: RGBDFrame, device: torch.device | str, min_depth_m: float = 0.05,
                    max_depth_m: float = 10.0, min_confidence: int | None = None,
                    use_color: bool = True,
                    depth_filter: DepthFilterConfig | None = _DEFAULT_DEPTH_FILTER) -> FrameData:
    """Move a frame to ``device`` and clean its depth; the one place frames become tensors, so tracking
    and mapping see the same depth.

    Depth becomes invalid (0) where it is non-finite or outside ``[min_depth_m, max_depth_m]``, below
    ``min_confidence`` when the frame has a confidence map, and, after those, where the neighbourhood
    support filter ``depth_filter`` finds no agreeing neighbours (isolated outliers, flying pixels; see
    :mod:`.depth_filter`; None or ``enabled=False`` turns it off). Invalid pixels neither allocate voxels
    nor supervise rays.
    """
    depth = np.asarray(frame.depth_m, dtype=np.float32)
    ok = np.isfinite(depth) & (depth >= min_depth_m) & (depth <= max_depth_m)
    if min_confidence is not None and frame.confidence is not None:
        ok &= frame.confidence >= min_confidence
    depth = np.where(ok, depth, 0.0).astype(np.float32)
    d = torch.from_numpy(depth).to(device)
    if depth_filter is not None and depth_filter.enabled:
        d = torch.where(depth_outlier_mask(d, depth_filter), d, torch.zeros_like(d))
    color = None
    if use_color and frame.color is not None:
        color = torch.from_numpy(np.ascontiguousarray(frame.color)).to(device).float() / 255.0
    valid_idx = torch.nonzero(d.reshape(-1) > 0).squeeze(1)
    return FrameData(index=frame.index, timestamp_s=float(frame.timestamp_s), depth_m=d, color=color,
                     K=torch.as_tensor(frame.K, dtype=torch.float64, device=device), valid_idx=valid_idx)


def sample_valid_pixels(frame: FrameData, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``[n]`` int64 flat indices ``v * W + u`` drawn uniformly (with replacement) among the valid pixels.

    Raises:
        ValidationError: the frame has no valid depth pixel.
    """
    if frame.n_valid == 0:
        raise ValidationError("depth_m", f"frame {frame.index} has no valid depth pixel to sample")
    # drawn where the generator lives: a generator on the frame's device (what the mapper and the tracker
    # keep) makes no host-to-device copy per call; a CPU generator (or None) draws on the CPU as before
    gdev = generator.device if generator is not None else torch.device("cpu")
    pick = torch.randint(0, frame.n_valid, (n,), generator=generator, device=gdev).to(frame.valid_idx.device)
    return frame.valid_idx.index_select(0, pick)


def flat_uv(flat: torch.Tensor, width: int) -> torch.Tensor:
    """``[..., 2]`` float64 ``(u, v)`` (column, row) of flat pixel indices ``flat [...]`` = ``v * width + u``."""
    return torch.stack([(flat % width).to(torch.float64),
                        torch.div(flat, width, rounding_mode="floor").to(torch.float64)], -1)


def sample_pixels(frame: FrameData, n: int, generator: torch.Generator | None = None) -> PixelBatch:
    """Draw ``n`` pixels uniformly (with replacement) among the frame's valid-depth pixels.

    Raises:
        ValidationError: the frame has no valid depth pixel.
    """
    flat = sample_valid_pixels(frame, n, generator)
    uv = flat_uv(flat, frame.width)
    depth = frame.depth_m.reshape(-1).index_select(0, flat)
    color = frame.color.reshape(-1, 3).index_select(0, flat) if frame.color is not None else None
    return PixelBatch(uv=uv, depth_m=depth, color=color)
