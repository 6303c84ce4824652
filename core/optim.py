"""The one place optimisers are made and stepped: Adam, fused where PyTorch has a fused kernel for the device.

PyTorch's default (for-loop) Adam reads each parameter's step counter back to the host on every step (a
device synchronisation per parameter on a GPU) and launches several kernels per parameter; the fused
implementation keeps the counter on the device and updates every parameter in one kernel (CPU and CUDA).
On a 2-core CPU it is also far faster (measured: 1.2 vs ~2-60 ms a step for a 20k x 16 table + a small MLP).

:func:`adam_step` applies such an optimiser's update by calling that kernel directly. ``optimizer.step()`` is the
reference: the same kernel on the same state (the update is the same to the bit, tested), reached through
~100-250 us of Python per parameter group and call (hooks, profiler labels, grouping by device and dtype) on the
2-core AMD EPYC, where a mapping iteration steps two optimisers, one of them with a group per keyframe.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch

__all__ = ["adam", "adam_step", "preload"]


def adam(params: Iterable[Any], lr: float) -> torch.optim.Adam:
    """``torch.optim.Adam(params, lr)`` with ``fused=True``, or the default implementation when this build
    cannot fuse for these parameters (an unsupported device or dtype raises at construction)."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, ValueError, TypeError):
        return torch.optim.Adam(params, lr=lr)


def _plain_fused(group: dict[str, Any]) -> bool:
    """Whether :func:`adam_step` may run ``group`` itself: fused Adam with float settings and nothing else switched on
    (no amsgrad, maximize, decoupled weight decay, differentiable or tensor learning rate)."""
    return (bool(group.get("fused")) and not group.get("amsgrad") and not group.get("maximize")
            and not group.get("decoupled_weight_decay") and not group.get("differentiable")
            and not isinstance(group.get("lr"), torch.Tensor) and not any(map(torch.is_tensor, group["betas"])))


@torch.no_grad()
def adam_step(optimizer: torch.optim.Optimizer) -> None:
    """``optimizer.step()`` for an optimiser made by :func:`adam`: the parameters that have a gradient get one
    ``torch._fused_adam_`` call per (device, dtype, hyperparameters), across groups (the keyframe-pose optimiser has a
    group per keyframe, all alike: one call, not one per keyframe; the kernel updates each tensor on its own, so
    the grouping changes no number), with the state ``torch.optim.Adam`` keeps (``step`` float32 on the parameter's
    device, ``exp_avg``, ``exp_avg_sq``; created as it creates them), so the two can be mixed on one optimiser.
    Anything else (the default Adam, amsgrad, a tensor learning rate, a build without the kernel) goes through
    ``optimizer.step()``; a sparse gradient raises as there."""
    if (not isinstance(optimizer, torch.optim.Adam) or not hasattr(torch, "_fused_adam_")
            or not all(_plain_fused(g) for g in optimizer.param_groups)):
        optimizer.step()
        return
    state = optimizer.state
    calls: dict[tuple, tuple[list, list, list, list, list]] = {}
    for group in optimizer.param_groups:
        with_grad = [p for p in group["params"] if p.grad is not None]
        if not with_grad:  # a keyframe outside this mapping window
            continue
        settings = (group["lr"], *group["betas"], group["weight_decay"], group["eps"])
        for p in with_grad:
            if p.grad.is_sparse:
                raise RuntimeError("Adam does not support sparse gradients, please consider SparseAdam instead")
            s = state[p]
            if not s:
                s["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                s["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                s["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            lists = calls.setdefault((p.device, p.dtype, *settings), ([], [], [], [], []))
            for out, value in zip(lists, (p, p.grad, s["exp_avg"], s["exp_avg_sq"], s["step"]), strict=True):
                out.append(value)
    for (_, _, lr, beta1, beta2, weight_decay, eps), (params, grads, avgs, avg_sqs, steps) in calls.items():
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(params, grads, avgs, avg_sqs, [], steps, amsgrad=False, lr=lr, beta1=beta1, beta2=beta2,
                           weight_decay=weight_decay, eps=eps, maximize=False, grad_scale=None, found_inf=None)


def preload() -> None:
    """Import what ``torch.optim.Adam``'s constructor imports on its first call (``torch._dynamo``: ~0.7 s on a
    2-core CPU), so an engine built before its frames arrive (:class:`~.slam.SlamSystem`) does not add it to
    its first frame's latency. Not done at this module's import: commands that never optimise stay quick."""
    import torch._dynamo  # noqa: F401
