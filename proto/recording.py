"""Session recordings: an append-only file of frame messages, durable before the server acknowledges them.

A recording (``recording.vxr``) is the frame messages a session received (:mod:`.frame_codec`, unchanged
bytes), each wrapped in a small record so that a crash in the middle of a write is detected::

    file    = file_header record*
    file_header (16 bytes) = magic b"VXRECORD" | u32 version (1) | u32 flags (0)
    record  = u32 length | u32 crc32(message) | message (length bytes, one VXFR frame message)

All integers are little-endian. :class:`RecordingWriter` appends a record with one ``write`` and makes it
durable with ``fdatasync`` before :meth:`RecordingWriter.append` returns (concurrent appends share one
sync: group commit). A process killed mid-write leaves at most one torn record at the end of the file;
opening the file for writing again detects it (short record, or a CRC mismatch on the last record) and
truncates it. A bad record *followed by* further data cannot come from a torn append and is reported as
corruption (:class:`~voxfusion.core.errors.CaptureError`) instead of being silently dropped.

:class:`RecordingCapture` reads a recording as a capture (``voxfusion run`` replays a session with it).

Example::

    writer = RecordingWriter(session_dir / "recording.vxr")
    writer.append(encode_frame(frame, seq=0))     # durable when this returns
    cap = RecordingCapture(session_dir)           # frames as RGBDFrame, index = position in the file
"""

from __future__ import annotations

import mmap
import os
import struct
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from voxfusion.core.datasets.frame import BaseCapture, RGBDFrame
from voxfusion.core.datasets.profile import LIDAR_MAX_DEPTH_M, CaptureProfile
from voxfusion.core.errors import CaptureError, CaptureFormatError, ValidationError

from .frame_codec import decode_frame, read_header

__all__ = [
    "RECORDING_MAGIC",
    "RECORDING_VERSION",
    "RECORDING_FILENAME",
    "MAX_RECORD_BYTES",
    "RecordingScan",
    "scan_recording",
    "iter_messages",
    "RecordingWriter",
    "RecordingReader",
    "RecordingCapture",
    "find_recording",
]

RECORDING_MAGIC = b"VXRECORD"
RECORDING_VERSION = 1
RECORDING_FILENAME = "recording.vxr"
"""File name of a session's recording inside its folder."""
MAX_RECORD_BYTES = 1 << 30
"""Largest message a record may hold (1 GiB); a larger stated length is corruption."""

_FILE_HEADER = struct.Struct("<8sII")
_datasync = getattr(os, "fdatasync", os.fsync)  # fdatasync is Linux-only; macOS has fsync
_RECORD_HEADER = struct.Struct("<II")


@dataclass(frozen=True)
class RecordingScan:
    """Where the valid records of a recording lie.

    Attributes:
        offsets: byte offset of each valid record's message (after its 8-byte record header).
        lengths: byte length of each message.
        valid_end: file offset just past the last valid record.
        file_size: size of the file when scanned; ``file_size > valid_end`` means a torn tail.
    """

    offsets: tuple[int, ...]
    lengths: tuple[int, ...]
    valid_end: int
    file_size: int

    @property
    def torn_bytes(self) -> int:
        """Bytes after the last valid record (a torn final write), 0 for a clean file."""
        return self.file_size - self.valid_end


def _check_file_header(path: Path, head: bytes) -> None:
    if len(head) < _FILE_HEADER.size:
        raise CaptureFormatError(path, f"recording header is {len(head)} bytes, expected {_FILE_HEADER.size}")
    magic, version, flags = _FILE_HEADER.unpack_from(head)
    if magic != RECORDING_MAGIC:
        raise CaptureFormatError(path, f"not a voxfusion recording (magic {magic!r}, expected {RECORDING_MAGIC!r})")
    if version != RECORDING_VERSION or flags != 0:
        raise CaptureFormatError(path, f"unsupported recording version {version} / flags {flags}; this build "
                                       f"reads version {RECORDING_VERSION}")


def scan_recording(path: str | Path) -> RecordingScan:
    """Check every record's length and CRC and return where they lie (the file is not modified).

    A torn final record (the file ends inside it, or it is the last record and its CRC does not match)
    ends the scan; ``torn_bytes`` says how many bytes it covers.

    Raises:
        CaptureError: the file is missing, or a corrupt record is followed by more data.
        CaptureFormatError: the file header is not a version-1 recording header.
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(path, "recording not found")
    offsets: list[int] = []
    lengths: list[int] = []
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        _check_file_header(path, f.read(_FILE_HEADER.size))
        pos = _FILE_HEADER.size
        while pos < size:
            head = f.read(_RECORD_HEADER.size)
            if len(head) < _RECORD_HEADER.size:
                break  # torn: the file ends inside a record header
            length, crc = _RECORD_HEADER.unpack(head)
            end = pos + _RECORD_HEADER.size + length
            if length == 0 or length > MAX_RECORD_BYTES or end > size:
                if end <= size and length != 0:
                    raise CaptureError(path, f"record {len(offsets)} at byte {pos} states {length} bytes")
                break  # torn: the file ends inside the message (or a zero-filled tail)
            message = f.read(length)
            if zlib.crc32(message) != crc:
                if end < size:
                    raise CaptureError(path, f"record {len(offsets)} at byte {pos} is corrupt (CRC mismatch) and "
                                             f"{size - end} bytes follow it: not a torn write")
                break  # torn: the last record's bytes did not all reach the disk
            offsets.append(pos + _RECORD_HEADER.size)
            lengths.append(length)
            pos = end
    return RecordingScan(tuple(offsets), tuple(lengths), pos if pos <= size else size, size)


def iter_messages(path: str | Path, scan: RecordingScan | None = None,
                  stop: int | None = None) -> Iterator[bytes]:
    """Yield the frame messages of a recording in order (up to ``stop`` records), one read per record."""
    path = Path(path)
    scan = scan if scan is not None else scan_recording(path)
    n = len(scan.offsets) if stop is None else min(stop, len(scan.offsets))
    with open(path, "rb") as f:
        for off, length in zip(scan.offsets[:n], scan.lengths[:n], strict=True):
            f.seek(off)
            yield f.read(length)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class RecordingWriter:
    """Appends frame messages to a recording, each durable (``fdatasync``) before :meth:`append` returns.

    Opening an existing recording checks it (:func:`scan_recording`) and truncates a torn final record;
    ``recovered_bytes`` says how many bytes were cut. Thread-safe: concurrent appends are serialised and
    share a single ``fdatasync`` when they overlap (group commit).

    Args:
        path: the ``.vxr`` file (created with its folder if missing).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.recovered_bytes = 0
        self._write_lock = threading.Lock()
        self._sync_lock = threading.Lock()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.path.exists() or self.path.stat().st_size == 0:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
            os.write(self._fd, _FILE_HEADER.pack(RECORDING_MAGIC, RECORDING_VERSION, 0))
            os.fsync(self._fd)
            _fsync_dir(self.path.parent)
            self._count = 0
            self._end = _FILE_HEADER.size
        else:
            scan = scan_recording(self.path)
            self._fd = os.open(self.path, os.O_RDWR)
            if scan.torn_bytes:
                os.ftruncate(self._fd, scan.valid_end)
                os.fsync(self._fd)
                self.recovered_bytes = scan.torn_bytes
            self._count = len(scan.offsets)
            self._end = scan.valid_end
        os.lseek(self._fd, self._end, os.SEEK_SET)
        self._synced = self._end
        self._closed = False

    def __len__(self) -> int:
        return self._count

    @property
    def size_bytes(self) -> int:
        """Bytes of the file (valid records only)."""
        return self._end

    def append(self, message: bytes) -> int:
        """Append one message and make it durable; returns its 0-based position in the recording.

        Raises:
            ValidationError: ``message`` is empty or larger than :data:`MAX_RECORD_BYTES`, or the writer
                is closed.
        """
        if not 0 < len(message) <= MAX_RECORD_BYTES:
            raise ValidationError("message", f"must be 1..{MAX_RECORD_BYTES} bytes, got {len(message)}")
        record = _RECORD_HEADER.pack(len(message), zlib.crc32(message)) + bytes(message)
        with self._write_lock:
            if self._closed:
                raise ValidationError("recording", f"{self.path} is closed")
            view = memoryview(record)
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
            self._end += len(record)
            end = self._end
            index = self._count
            self._count += 1
        with self._sync_lock:
            if self._synced < end:
                target = self._end  # everything written before this sync starts is covered by it
                _datasync(self._fd)
                self._synced = max(self._synced, target)
        return index

    def close(self) -> None:
        """Close the file (appends after this raise)."""
        with self._write_lock:
            if not self._closed:
                self._closed = True
                os.close(self._fd)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RecordingReader:
    """Reads the records of a recording that another process keeps appending to, in order, without copying
    them: the file is memory-mapped (the page cache's pages, the very ones the writer's ``write`` filled) and
    each message is a read-only ``memoryview`` of that mapping. The session worker reads its frames this way.

    Only records the writer has finished are read: call :meth:`next` for record ``i`` only once the writer's
    :meth:`RecordingWriter.append` of it returned (a server tells its worker how many records exist).
    A view stays valid as long as it is referenced, also after the reader maps a longer file or is closed.

    Args:
        path: the ``.vxr`` file.

    Raises:
        CaptureError / CaptureFormatError: missing file or wrong header.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise CaptureError(self.path, "recording not found")
        self._fd = os.open(self.path, os.O_RDONLY)
        self._map: mmap.mmap | None = None
        self._view: memoryview | None = None
        self._pos = _FILE_HEADER.size
        self.index = 0
        """Position of the record :meth:`next` reads next."""
        self._remap()
        if self._view is None:
            raise CaptureFormatError(self.path, "recording header missing")
        _check_file_header(self.path, bytes(self._view[:_FILE_HEADER.size]))

    def _remap(self) -> None:
        size = os.fstat(self._fd).st_size
        if size < _FILE_HEADER.size or (self._view is not None and size <= len(self._view)):
            return
        # the old mapping is dropped, not closed: views handed out earlier keep it alive
        self._map = mmap.mmap(self._fd, size, prot=mmap.PROT_READ)
        self._view = memoryview(self._map)

    def next(self) -> memoryview:
        """The message of record :attr:`index` (then advance).

        Raises:
            CaptureError: the record is not (yet) complete in the file, or its CRC does not match.
        """
        view = self._view
        end_header = self._pos + _RECORD_HEADER.size
        if view is None or end_header > len(view):
            self._remap()
            view = self._view
        if view is None or end_header > len(view):
            raise CaptureError(self.path, f"record {self.index} is not in the file yet")
        length, crc = _RECORD_HEADER.unpack_from(view, self._pos)
        end = end_header + length
        if length == 0 or length > MAX_RECORD_BYTES:
            raise CaptureError(self.path, f"record {self.index} at byte {self._pos} states {length} bytes")
        if end > len(view):
            self._remap()
            view = self._view
            if view is None or end > len(view):
                raise CaptureError(self.path, f"record {self.index} is not complete in the file yet")
        message = view[end_header:end]
        if zlib.crc32(message) != crc:
            raise CaptureError(self.path, f"record {self.index} at byte {self._pos} is corrupt (CRC mismatch)")
        self._pos = end
        self.index += 1
        return message

    def close(self) -> None:
        """Close the file (views handed out stay readable)."""
        self._view = self._map = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def find_recording(path: str | Path) -> Path | None:
    """The recording file of ``path``: the path itself if it is a ``.vxr`` file, else ``recording.vxr`` or
    the single ``*.vxr`` file in the folder; ``None`` if there is none."""
    path = Path(path)
    if path.is_file():
        return path if path.suffix.lower() == ".vxr" else None
    if not path.is_dir():
        return None
    if (path / RECORDING_FILENAME).is_file():
        return path / RECORDING_FILENAME
    files = sorted(path.glob("*.vxr"))
    return files[0] if len(files) == 1 else None


class RecordingCapture(BaseCapture):
    """A session recording read as a capture (frames decoded lazily; a torn tail is ignored, not cut).

    Frames are numbered by their position in the recording (``frame.index``); the sender's ``seq`` and
    ``session`` are in ``frame.meta``. Recordings carry no reference pose (``T_world_cam`` is ``None``);
    the device pose, when sent, is ``T_world_cam_device``.

    Args:
        path: a ``.vxr`` file, or a folder holding ``recording.vxr`` (a server session folder) or one
            ``*.vxr`` file.
    """

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        rec = find_recording(path)
        if rec is None:
            raise CaptureFormatError(path, f"no recording: expected a .vxr file or a folder with {RECORDING_FILENAME}")
        self.path = path
        self.file = rec
        self.name = path.name if path.is_dir() else rec.stem
        self._scan = scan_recording(rec)

    def __len__(self) -> int:
        return len(self._scan.offsets)

    @property
    def torn_bytes(self) -> int:
        """Bytes of a torn final record that this reader skips."""
        return self._scan.torn_bytes

    def message(self, i: int) -> bytes:
        """The raw frame message of record ``i``."""
        n = len(self)
        if not 0 <= i < n:
            raise IndexError(f"record {i} out of range for {self.name} ({n} records)")
        with open(self.file, "rb") as f:
            f.seek(self._scan.offsets[i])
            return f.read(self._scan.lengths[i])

    @property
    def profile(self) -> CaptureProfile:
        """Read off the first frame: kind ``iphone`` (LiDAR depth to 5 m) when it carries a confidence map or
        a device pose, as phone clients send, else ``unknown``."""
        if self._profile is None:
            if not len(self):
                self._profile = CaptureProfile()
            else:
                f = self[0]
                phone = f.confidence is not None or f.T_world_cam_device is not None
                w, h = f.width, f.height
                self._profile = (CaptureProfile.from_frame(f, "iphone", max_depth_m=LIDAR_MAX_DEPTH_M,
                                                           sensor=f"voxfusion recording, phone {w}x{h}")
                                 if phone else CaptureProfile.from_frame(f, sensor=f"voxfusion recording {w}x{h}"))
        return self._profile

    def seqs(self) -> list[int]:
        """The sender's ``seq`` of every record, in order (headers only; no image is decoded)."""
        return [read_header(m).seq for m in iter_messages(self.file, self._scan)]

    def _load(self, i: int) -> RGBDFrame:
        decoded = decode_frame(self.message(i))
        meta = {**decoded.frame.meta, "seq": decoded.seq, "session": decoded.session}
        return decoded.frame.with_(index=i, meta=meta)
