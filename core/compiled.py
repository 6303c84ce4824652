"""``torch.compile`` on first use, with one clean fall-back: what the engine's compiled options share.

The options (``field.compile``: the decoder MLP; ``tracking.compile``: one iteration of the geometric
tracker, :func:`~.slam.tracking_sdf.linearize_terms`; ``mapping.compile``: a mapping iteration's renderer and losses,
:func:`~.slam.mapping.band_loss`, whose backward pass autograd then runs through the compiled graph) each wrap a plain
function in a :class:`CompiledFunction`. The
plain function stays the reference: tests hold the compiled one to it, and wherever compilation fails (no
C++ compiler, an unsupported platform or operator) the engine logs one warning naming the option and the
cause, then runs the plain function for the rest of the process.

Shapes are dynamic: the map grows (its embedding table and index grid change size between calls), so a
graph specialised to one size would be recompiled at every map update. Python floats are specialised
instead (they are configuration constants: a handful of graphs, one per solver stage), and parameters may
change size like any tensor (a map snapshot's embeddings are a parameter).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import torch

from .errors import VoxFusionError

__all__ = ["CompiledFunction"]

log = logging.getLogger("voxfusion.compiled")

_DYNAMO_OPTIONS = {"force_parameter_static_shapes": False, "specialize_float": True}
"""Tracing options applied around every call (they matter when a call compiles; see the module docstring)."""


class CompiledFunction:
    """``fn`` through :func:`torch.compile` (``dynamic=True``), compiled on the first call.

    Args:
        fn: the plain function (the reference, and the fall-back).
        option: the configuration name that asked for it (``"tracking.compile"``), for the warning.
        logger: where the one warning goes (the caller's module logger).

    A compilation failure (any exception from the compiled call that is not one of voxfusion's own typed
    errors) is logged once at WARNING; that call and every later one run ``fn``. :meth:`reset` forgets the
    compiled function and the failure (benchmarks compare a fresh compilation per variant).
    """

    def __init__(self, fn: Callable, option: str, logger: logging.Logger | None = None) -> None:
        self.fn = fn
        self.option = option
        self._log = logger or log
        self._lock = threading.Lock()
        self._compiled: Callable | None = None
        self.failed = False

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        compiled = self._get()
        if compiled is not None:
            try:
                with torch._dynamo.config.patch(**_DYNAMO_OPTIONS):
                    return compiled(*args, **kwargs)
            except VoxFusionError:
                raise  # the function's own error (bad input), not the compiler's
            except Exception as e:  # noqa: BLE001 - a compiler failure: warn once, stay eager
                self._fail(e)
        return self.fn(*args, **kwargs)

    def _get(self) -> Callable | None:
        with self._lock:
            if self.failed:
                return None
            if self._compiled is None:
                self._compiled = torch.compile(self.fn, dynamic=True)
            return self._compiled

    def _fail(self, error: Exception) -> None:
        with self._lock:
            if not self.failed:
                first_line = str(error).splitlines()[0] if str(error) else ""
                self._log.warning("%s: torch.compile failed (%s: %s); running eager", self.option,
                                  type(error).__name__, first_line)
            self.failed = True

    def reset(self) -> None:
        """Forget the compiled function and any failure: the next call compiles afresh."""
        with self._lock:
            self._compiled = None
            self.failed = False
