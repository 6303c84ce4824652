"""Capture readers: every format converts to :class:`RGBDFrame` at the edge.

``open_capture(path)`` detects the format (TUM RGB-D, 7-Scenes, Replica, ScanNet, Stray Scanner,
Record3D) and returns a lazy :class:`Capture`; the readers can also be used directly.
"""

from .frame import BaseCapture, Capture, RGBDFrame
from .open import CAPTURE_FORMATS, CaptureFormat, detect_format, open_capture
from .record3d import Record3DCapture
from .replica import ReplicaCapture
from .scannet import ScanNetCapture
from .sevenscenes import SevenScenesCapture
from .stray import StrayCapture
from .transforms import (
    SlicedCapture,
    TransformedCapture,
    clip_depth,
    filter_depth_by_confidence,
    resize_frame,
)
from .tum import TUMCapture

__all__ = [
    "RGBDFrame",
    "Capture",
    "BaseCapture",
    "open_capture",
    "detect_format",
    "CaptureFormat",
    "CAPTURE_FORMATS",
    "TUMCapture",
    "SevenScenesCapture",
    "ReplicaCapture",
    "ScanNetCapture",
    "StrayCapture",
    "Record3DCapture",
    "resize_frame",
    "filter_depth_by_confidence",
    "clip_depth",
    "TransformedCapture",
    "SlicedCapture",
]
