"""The level-0 index grid's aligned box: the same lookups as the tight box, corners on multiples, a budget fallback."""

from __future__ import annotations

import pytest
import torch

from voxfusion.core.errors import ValidationError
from voxfusion.core.map.index_grid import build_index_grid


def _coords(seed: int = 0, n: int = 200) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(-13, 11, (n, 3), generator=g)


@pytest.mark.parametrize("align", [2, 8, 16])
def test_aligned_box_gives_the_tight_boxs_lookups(align):
    coords = torch.unique(_coords(), dim=0)
    values = torch.arange(coords.shape[0])
    tight = build_index_grid(coords, values, 0, border=1, max_cells=1 << 20)
    aligned = build_index_grid(coords, values, 0, border=1, max_cells=1 << 20, align=align)
    assert all(o % align == 0 for o in aligned.origin_xyz)
    assert all(s % align == 0 for s in aligned.shape)
    # the aligned box holds the tight one (border included)
    for o_a, s_a, o_t, s_t in zip(aligned.origin_xyz, aligned.shape, tight.origin_xyz, tight.shape, strict=True):
        assert o_a <= o_t and o_a + s_a >= o_t + s_t
    assert aligned.n_occupied == tight.n_occupied
    probe = torch.cartesian_prod(*(torch.arange(-40, 40, 3),) * 3)  # inside, on the border and far outside
    assert torch.equal(aligned.lookup(probe), tight.lookup(probe))
    assert torch.equal(aligned.lookup(coords), values)


def test_a_map_growing_by_a_voxel_keeps_its_aligned_box():
    coords = torch.tensor([[0, 0, 0], [3, 2, 1]])
    grown = torch.cat([coords, torch.tensor([[4, 2, 1]])])
    boxes = [(g.origin_xyz, g.shape) for g in (build_index_grid(c, torch.arange(c.shape[0]), 0, 1, 1 << 20, align=8)
                                              for c in (coords, grown))]
    assert boxes[0] == boxes[1]
    tight = [build_index_grid(c, torch.arange(c.shape[0]), 0, 1, 1 << 20).shape for c in (coords, grown)]
    assert tight[0] != tight[1]


def test_aligned_box_over_the_budget_falls_back_to_the_tight_box():
    coords = torch.tensor([[1, 1, 1], [4, 4, 4]])  # tight with border: 6^3 = 216 cells; aligned to 8: 512
    g = build_index_grid(coords, torch.arange(2), 0, border=1, max_cells=300, align=8)
    assert g is not None and g.shape == (6, 6, 6)
    assert build_index_grid(coords, torch.arange(2), 0, border=1, max_cells=200, align=8) is None


def test_align_must_be_positive():
    with pytest.raises(ValidationError, match="align"):
        build_index_grid(torch.zeros(1, 3, dtype=torch.int64), torch.zeros(1), 0, 1, 100, align=0)
