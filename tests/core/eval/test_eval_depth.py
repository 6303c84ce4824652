"""Depth L1 on valid pixels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.eval import depth_l1


def test_mean_abs_error_over_pixels_valid_in_both():
    observed = np.array([[1.0, 2.0, 0.0], [3.0, 4.0, 5.0]], dtype=np.float32)
    rendered = np.array([[1.1, 1.8, 2.0], [0.0, 4.0, np.nan]], dtype=np.float32)
    r = depth_l1(rendered, observed)
    assert r.n == 3  # (0,2) invalid input, (1,0) no render, (1,2) NaN render
    assert r.mean_abs_m == pytest.approx((0.1 + 0.2 + 0.0) / 3, abs=1e-6)


def test_mask_restricts_pixels():
    observed = np.full((4, 5), 2.0, np.float32)
    rendered = observed + np.arange(20, dtype=np.float32).reshape(4, 5) * 0.01
    mask = np.zeros((4, 5), bool)
    mask[0, :2] = True
    r = depth_l1(rendered, observed, mask=mask)
    assert r.n == 2
    assert r.mean_abs_m == pytest.approx(0.005, abs=1e-6)


def test_torch_tensors_are_accepted():
    observed = torch.full((3, 3), 1.5)
    r = depth_l1(observed + 0.25, observed)
    assert r.n == 9 and r.mean_abs_m == pytest.approx(0.25)


def test_errors():
    with pytest.raises(ShapeError):
        depth_l1(np.ones((3, 3)), np.ones((3, 4)))
    with pytest.raises(ShapeError):
        depth_l1(np.ones(9), np.ones(9))
    with pytest.raises(ShapeError):
        depth_l1(np.ones((3, 3)), np.ones((3, 3)), mask=np.ones((2, 3), bool))
    with pytest.raises(ValidationError):
        depth_l1(np.zeros((3, 3)), np.ones((3, 3)))
