"""The lean Adam step (core/optim.py) against ``torch.optim.Adam.step``, its reference."""

from __future__ import annotations

import copy

import pytest
import torch

from voxfusion.core.optim import adam, adam_step


def _problem(seed: int) -> tuple[list[torch.nn.Parameter], list[dict]]:
    g = torch.Generator().manual_seed(seed)
    table = torch.nn.Parameter(torch.randn(50, 16, generator=g))
    mlp = [torch.nn.Parameter(torch.randn(16, 8, generator=g)), torch.nn.Parameter(torch.randn(8, generator=g))]
    poses = [torch.nn.Parameter(torch.randn(6, generator=g, dtype=torch.float64)) for _ in range(3)]
    groups = [{"params": [table], "lr": 1e-2}, {"params": mlp, "lr": 1e-3},
              *({"params": [p], "lr": 1e-4} for p in poses)]
    return [table, *mlp, *poses], groups


def _loss(params: list[torch.nn.Parameter], k: int) -> torch.Tensor:
    table, w, b, *poses = params
    # parameters outside the step's "window" get no gradient, as keyframes outside a mapping window
    out = (torch.tanh(table @ w + b) ** 2).sum() + sum((p ** 2).sum() * (i + 1) for i, p in enumerate(poses)
                                                      if (i + k) % 3 != 0)
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_adam_step_matches_torch_adam_to_the_bit(seed: int) -> None:
    params_a, groups_a = _problem(seed)
    params_b = copy.deepcopy(params_a)
    id_map = {id(a): b for a, b in zip(params_a, params_b, strict=True)}
    groups_b = [{**g, "params": [id_map[id(p)] for p in g["params"]]} for g in groups_a]
    opt_a, opt_b = adam(groups_a, lr=1e-2), adam(groups_b, lr=1e-2)
    assert all(g["fused"] for g in opt_a.param_groups), "this build should fuse Adam on a CPU"
    for k in range(12):
        for params, opt, stepper in ((params_a, opt_a, lambda o: o.step()), (params_b, opt_b, adam_step)):
            opt.zero_grad(set_to_none=True)
            _loss(params, k).backward()
            stepper(opt)
    for a, b in zip(params_a, params_b, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    for a, b in zip(params_a, params_b, strict=True):
        sa, sb = opt_a.state[a], opt_b.state[b]
        assert sa.keys() == sb.keys()
        for key in sa:
            torch.testing.assert_close(sa[key], sb[key], rtol=0, atol=0)


def test_adam_step_defers_to_the_reference_where_it_does_not_apply() -> None:
    p = torch.nn.Parameter(torch.ones(4))
    q = copy.deepcopy(p)
    opt_p = torch.optim.Adam([p], lr=0.1, amsgrad=True)  # not fused, amsgrad: torch's own step
    opt_q = torch.optim.Adam([q], lr=0.1, amsgrad=True)
    for _ in range(3):
        for x, opt, stepper in ((p, opt_p, lambda o: o.step()), (q, opt_q, adam_step)):
            opt.zero_grad()
            (x ** 3).sum().backward()
            stepper(opt)
    torch.testing.assert_close(p, q, rtol=0, atol=0)


def test_adam_step_rejects_a_sparse_gradient_as_torch_does() -> None:
    emb = torch.nn.Embedding(10, 4, sparse=True)
    opt = adam(emb.parameters(), lr=0.1)
    emb(torch.tensor([1, 2])).sum().backward()
    with pytest.raises(RuntimeError, match="sparse gradients"):
        adam_step(opt)
