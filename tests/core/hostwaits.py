"""Detectors of what a CUDA graph cannot hold, for CPU tests of code meant for capture (the tracker's solver stages,
the occlusion render): operators that make the host wait for the device or read a device value, and tensors made
from host data (a host-to-device copy on a GPU)."""

from __future__ import annotations

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

SYNC_OPS = {"_local_scalar_dense", "nonzero", "nonzero_static", "masked_select", "_unique", "_unique2", "unique_dim",
            "unique_consecutive", "repeat_interleave", "is_nonzero", "equal", "item"}
HOST_DATA = {torch.tensor, torch.as_tensor, torch.from_numpy, torch.Tensor.new_tensor}

class HostWaits(TorchDispatchMode):
    """Records the operators that make the host wait for the device (or read a device value), or copy to it."""

    def __init__(self, allow: frozenset[str] = frozenset()) -> None:
        """``allow``: operators of :data:`SYNC_OPS` not to record (``nonzero_static``, whose CUDA kernel does not wait
        for the host since PyTorch 2.6, for code that relies on that)."""
        super().__init__()
        self.allow = allow
        self.seen: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        name = func._overloadpacket.__name__
        if name in self.allow:
            return func(*args, **(kwargs or {}))
        masks = name in ("index", "index_put", "index_put_") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ()))
        # a boolean mask as an index is a nonzero inside the kernel; lift_fresh: a tensor made from host data (a
        # Python scalar written by indexing, torch.tensor), which on a GPU is a host-to-device copy
        if name in SYNC_OPS or masks or name == "lift_fresh":
            self.seen.append(str(func))
        return func(*args, **(kwargs or {}))


class HostData(TorchFunctionMode):
    """Records tensors made from host data (a host-to-device copy on a GPU)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        if func in HOST_DATA:
            self.seen.append(getattr(func, "__name__", str(func)))
        return func(*args, **(kwargs or {}))
