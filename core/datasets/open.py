"""One front door for recorded captures: detect the format from the layout on disk and open it.

Known layouts (checked in this order; the first match wins):

============ =================================================== ==========================
format       what identifies it                                  reader
============ =================================================== ==========================
record3d     a ``.r3d`` file (or a folder holding exactly one)   :class:`Record3DCapture`
stray        ``odometry.csv`` and ``depth/``                     :class:`StrayCapture`
scannet      ``color/``, ``depth/`` and ``intrinsic/``           :class:`ScanNetCapture`
tum          ``rgb.txt`` and ``depth.txt``                       :class:`TUMCapture`
sevenscenes  ``frame-XXXXXX.pose.txt`` files                     :class:`SevenScenesCapture`
replica      ``results/`` and ``traj.txt``                       :class:`ReplicaCapture`
scanner3d    ``frame_XXXXX.json`` files (3D Scanner App)         :class:`Scanner3DCapture`
polycam      ``keyframes/`` (Polycam raw data)                   :class:`PolycamCapture`
============ =================================================== ==========================

The iPhone-app layouts are recognised by their marker alone (``frame_*.json``, ``keyframes/``), so a broken
export (no depth, a JSON without its pose, mismatched file counts) reaches its reader, which names what is
wrong, instead of being reported as an unknown layout.

Our synthetic generator writes the TUM or the Replica layout, so it needs no format of its own.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from ..errors import CaptureError, CaptureFormatError, ValidationError
from .frame import Capture
from .polycam import PolycamCapture, looks_like_polycam
from .record3d import Record3DCapture
from .replica import ReplicaCapture
from .scanner3d import Scanner3DCapture, looks_like_scanner3d
from .scannet import ScanNetCapture
from .sevenscenes import SevenScenesCapture
from .stray import StrayCapture
from .transforms import SlicedCapture
from .tum import TUMCapture

__all__ = ["CaptureFormat", "CAPTURE_FORMATS", "detect_format", "open_capture"]

CaptureFormat = Literal["record3d", "stray", "scannet", "tum", "sevenscenes", "replica", "scanner3d", "polycam",
                        "recording"]

def _recording(path: Path) -> Capture:
    """A server session recording (frame containers); the reader lives with the wire format."""
    from voxfusion.proto.recording import RecordingCapture  # lazy: the format is defined in proto/

    return RecordingCapture(path)


CAPTURE_FORMATS: dict[str, tuple[str, Callable[..., Capture]]] = {
    "record3d": ("a .r3d file (Record3D export)", Record3DCapture),
    "stray": ("odometry.csv + depth/ (Stray Scanner)", StrayCapture),
    "scannet": ("color/ + depth/ + intrinsic/ (ScanNet .sens export)", ScanNetCapture),
    "tum": ("rgb.txt + depth.txt (TUM RGB-D)", TUMCapture),
    "sevenscenes": ("frame-000000.pose.txt ... (7-Scenes)", SevenScenesCapture),
    "replica": ("results/ + traj.txt (Replica, NICE-SLAM release)", ReplicaCapture),
    "scanner3d": ("frame_00000.json + depth_00000.png ... (3D Scanner App 'All Data' export)", Scanner3DCapture),
    "polycam": ("keyframes/ with cameras/, images/, depth/ (Polycam raw-data export)", PolycamCapture),
    "recording": ("recording.vxr / *.vxr (a voxfusion server session's recording)", _recording),
}
"""Format name -> (layout description, reader)."""


def _single_r3d(folder: Path) -> Path | None:
    files = sorted(folder.glob("*.r3d"))
    return files[0] if len(files) == 1 else None


def detect_format(path: str | Path) -> CaptureFormat:
    """Name the capture format of ``path`` from its layout.

    Raises :class:`CaptureError` if ``path`` does not exist and :class:`CaptureFormatError`, listing
    the known layouts, if it matches none of them.
    """
    path = Path(path)
    if not path.exists():
        raise CaptureError(path, "capture not found")
    if path.is_file():
        if path.suffix.lower() == ".r3d":
            return "record3d"
        if path.suffix.lower() == ".vxr":
            return "recording"
    else:
        has = lambda name: (path / name).exists()  # noqa: E731
        if has("odometry.csv") and (path / "depth").is_dir():
            return "stray"
        if all((path / d).is_dir() for d in ("color", "depth", "intrinsic")):
            return "scannet"
        if has("rgb.txt") and has("depth.txt"):
            return "tum"
        if has("frame-000000.pose.txt") or next(path.glob("frame-*.pose.txt"), None) is not None:
            return "sevenscenes"
        if (path / "results").is_dir() and has("traj.txt"):
            return "replica"
        if looks_like_scanner3d(path):
            return "scanner3d"
        if looks_like_polycam(path):
            return "polycam"
        if _single_r3d(path) is not None:
            return "record3d"
        if has("recording.vxr") or next(path.glob("*.vxr"), None) is not None:
            return "recording"
    known = "; ".join(f"{name}: {desc}" for name, (desc, _) in CAPTURE_FORMATS.items())
    raise CaptureFormatError(path, f"unrecognised capture layout. Known layouts: {known}")


def open_capture(path: str | Path, format: CaptureFormat | None = None, *, start: int = 0,
                 limit: int | None = None, stride: int = 1, **reader_kwargs: object) -> Capture:
    """Open a recorded capture of any known format (auto-detected unless ``format`` is given).

    Args:
        path: capture folder, or ``.r3d`` file.
        format: force a reader instead of detecting one (see :data:`CAPTURE_FORMATS`).
        start: first source frame to use.
        limit: at most this many frames (after ``start`` and ``stride``); ``None`` = all.
        stride: use every ``stride``-th frame.
        **reader_kwargs: passed to the reader (e.g. ``intrinsics="fr2"`` for TUM,
            ``confidence_threshold=None`` for Stray, ``corrected=False`` for Polycam).

    Returns:
        A lazy :class:`Capture`; a :class:`SlicedCapture` view when ``start``/``limit``/``stride``
        select a subset.

    Example::

        cap = open_capture("rgbd_dataset_freiburg1_desk", stride=2, limit=100)
    """
    path = Path(path)
    fmt = detect_format(path) if format is None else format
    if fmt not in CAPTURE_FORMATS:
        known = ", ".join(CAPTURE_FORMATS)
        raise ValidationError("format", f"unknown capture format {fmt!r}; known: {known}")
    if stride < 1:
        raise ValidationError("stride", f"must be >= 1, got {stride}")
    if start < 0:
        raise ValidationError("start", f"must be >= 0, got {start}")
    if limit is not None and limit < 0:
        raise ValidationError("limit", f"must be >= 0 or None, got {limit}")
    if fmt == "record3d" and path.is_dir():
        r3d = _single_r3d(path)
        if r3d is None:
            raise CaptureFormatError(path, "folder must hold exactly one .r3d file")
        path = r3d
    reader = CAPTURE_FORMATS[fmt][1]
    try:
        inspect.signature(reader).bind(path, **reader_kwargs)
    except TypeError as e:
        raise ValidationError("reader_kwargs", f"{fmt} reader ({reader.__name__}): {e}") from e
    capture = reader(path, **reader_kwargs)
    if start == 0 and stride == 1 and limit is None:
        return capture
    stop = None if limit is None else start + limit * stride
    return SlicedCapture(capture, start, stop, stride)
