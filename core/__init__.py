"""The Vox-Fusion engine: frames and capture readers, geometry conventions, evaluation.

The front door: :class:`SlamSystem` (SLAM over a stream of frames: ``process`` / ``submit``, ``finish``,
``trajectory``, ``snapshot``) and :class:`MapSnapshot` (an immutable map with ``render``, ``mesh``, ``export``
and ``MapSnapshot.load(checkpoint)``), configured by :class:`VoxFusionConfig`. They load torch, so they are
imported on first use (``from voxfusion.core import SlamSystem``); frames, readers and errors are light.

Example::

    from voxfusion.core import MapSnapshot, SlamSystem, VoxFusionConfig
    slam = SlamSystem(VoxFusionConfig(mode="offline"))
    for frame in capture:
        slam.process(frame)
    slam.finish()
    slam.snapshot.mesh(mesh_res=8).export("mesh.ply")
"""

from .datasets.frame import BaseCapture, Capture, RGBDFrame
from .errors import (
    CaptureError,
    CaptureFormatError,
    ConfigError,
    EngineFailedError,
    MapNotReadyError,
    ShapeError,
    ValidationError,
    VoxFusionError,
)

_HEAVY = {"SlamSystem": ".slam.system", "MapSnapshot": ".slam.system", "FrameRecord": ".slam.system",
          "VoxFusionConfig": ".slam.presets"}


def __getattr__(name: str) -> object:
    module = _HEAVY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    return getattr(import_module(module, __name__), name)


__all__ = [
    "SlamSystem",
    "MapSnapshot",
    "FrameRecord",
    "VoxFusionConfig",
    "RGBDFrame",
    "Capture",
    "BaseCapture",
    "VoxFusionError",
    "CaptureError",
    "CaptureFormatError",
    "ConfigError",
    "MapNotReadyError",
    "EngineFailedError",
    "ShapeError",
    "ValidationError",
]
