"""Depth L1: mean absolute difference between a rendered and an observed depth map."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError, ValidationError

__all__ = ["DepthL1Result", "depth_l1"]


@dataclass(frozen=True)
class DepthL1Result:
    """Depth L1 over the pixels valid in both maps.

    Attributes:
        mean_abs_m: mean of ``|rendered - observed|`` over valid pixels, metres.
        n: number of valid pixels.
    """

    mean_abs_m: float
    n: int


def _to_numpy(x: object, field: str) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor (any device)
        x = x.detach().cpu().numpy()
    a = np.asarray(x)
    if a.ndim != 2:
        raise ShapeError(field, a.shape, "[H, W]")
    return a


def depth_l1(rendered_m: np.ndarray, observed_m: np.ndarray, mask: np.ndarray | None = None) -> DepthL1Result:
    """Mean absolute depth error on pixels where both depths are valid (finite and > 0).

    Args:
        rendered_m: ``[H, W]`` rendered depth, metres, 0 = no surface hit (numpy array or torch tensor).
        observed_m: ``[H, W]`` input depth, metres, 0 = invalid.
        mask: optional ``[H, W]`` bool; only ``True`` pixels count.

    Raises:
        ShapeError: shapes differ or are not 2-D.
        ValidationError: no pixel is valid in both maps (and the mask).
    """
    r = _to_numpy(rendered_m, "rendered_m").astype(np.float64)
    o = _to_numpy(observed_m, "observed_m").astype(np.float64)
    if r.shape != o.shape:
        raise ShapeError("rendered_m", r.shape, f"{o.shape} (the observed depth's shape)")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & np.isfinite(o) & (r > 0) & (o > 0)
    if mask is not None:
        m = _to_numpy(mask, "mask")
        if m.shape != o.shape:
            raise ShapeError("mask", m.shape, f"{o.shape}")
        valid &= m.astype(bool)
    n = int(valid.sum())
    if n == 0:
        raise ValidationError("depth", "no pixel has valid depth in both the rendered and the observed map")
    return DepthL1Result(float(np.abs(r[valid] - o[valid]).mean()), n)
