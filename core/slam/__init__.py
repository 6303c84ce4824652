"""SLAM: the engine object and its parts.

* :mod:`.system`: :class:`SlamSystem` (frames in, poses and map snapshots out) and :class:`MapSnapshot`;
* :mod:`.presets`: :class:`VoxFusionConfig` and the presets ``voxfusion run`` picks per capture and device;
* :mod:`.tracking`: the tracker (the paper's ``render`` method and the geometric ``sdf`` one), whose solver is
  :mod:`.tracking_sdf` and whose CUDA graphs are :mod:`.tracking_graphs`;
* :mod:`.mapping`: keyframes, the mapping iteration and the mapper.

The names below load torch, so they are imported on first use (``from voxfusion.core.slam import SlamSystem``).
"""

from __future__ import annotations

_LAZY = {"SlamSystem": ".system", "MapSnapshot": ".system", "FrameRecord": ".system", "SlamStats": ".system",
         "realtime_thread_count": ".system", "VoxFusionConfig": ".presets"}


def __getattr__(name: str) -> object:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    return getattr(import_module(module, __name__), name)


__all__ = list(_LAZY)
