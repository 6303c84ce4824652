"""Capture readers: every format converts to :class:`RGBDFrame` at the edge.

``open_capture(path)`` detects the format (TUM RGB-D, 7-Scenes, Replica, ScanNet, Stray Scanner,
Record3D, 3D Scanner App, Polycam) and returns a lazy :class:`Capture`; the readers can also be used
directly. Every capture has a ``profile`` (:class:`CaptureProfile`: kind, useful depth range, confidence,
colour) that the preset chooser (:func:`voxfusion.core.slam.presets.preset_for`) follows.
"""

from .frame import BaseCapture, Capture, RGBDFrame
from .open import CAPTURE_FORMATS, CaptureFormat, detect_format, open_capture
from .polycam import PolycamCapture
from .profile import CAPTURE_KINDS, CaptureKind, CaptureProfile
from .record3d import Record3DCapture
from .replica import ReplicaCapture
from .scanner3d import Scanner3DCapture
from .scannet import ScanNetCapture
from .sevenscenes import SevenScenesCapture
from .stray import StrayCapture
from .transforms import (
    RevisitCapture,
    SlicedCapture,
    TransformedCapture,
    clip_depth,
    drop_depth,
    filter_depth_by_confidence,
    resize_frame,
)
from .tum import TUMCapture

__all__ = [
    "RGBDFrame",
    "Capture",
    "BaseCapture",
    "CaptureProfile",
    "CaptureKind",
    "CAPTURE_KINDS",
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
    "Scanner3DCapture",
    "PolycamCapture",
    "resize_frame",
    "filter_depth_by_confidence",
    "clip_depth",
    "drop_depth",
    "TransformedCapture",
    "SlicedCapture",
    "RevisitCapture",
]
