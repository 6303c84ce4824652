"""The Vox-Fusion engine: frames and capture readers, geometry conventions, evaluation.

``server/`` and ``clients/`` import only what this module exports.
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

__all__ = [
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
