"""Session recordings (proto/recording.py): durable appends, torn-tail recovery, replay as a capture."""

from __future__ import annotations

import struct
import threading

import numpy as np
import pytest

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import CaptureError, CaptureFormatError
from voxfusion.proto import decode_frame, encode_frame
from voxfusion.proto.recording import (
    RECORDING_FILENAME,
    RecordingCapture,
    RecordingReader,
    RecordingWriter,
    find_recording,
    iter_messages,
    scan_recording,
)


@pytest.fixture(scope="module")
def frames():
    return list(SyntheticCapture(SyntheticConfig(n_frames=4, width=32, height=24, seed=3)).frames())


@pytest.fixture(scope="module")
def messages(frames):
    return [encode_frame(f, seq=10 + i, session="s", depth_encoding="raw_f32_m") for i, f in enumerate(frames)]


def test_append_and_read_back_in_order(tmp_path, messages):
    path = tmp_path / RECORDING_FILENAME
    with RecordingWriter(path) as w:
        assert [w.append(m) for m in messages] == [0, 1, 2, 3]
        assert len(w) == 4
    assert list(iter_messages(path)) == messages
    scan = scan_recording(path)
    assert scan.torn_bytes == 0 and scan.valid_end == path.stat().st_size
    # reopening appends after the existing records
    with RecordingWriter(path) as w:
        assert len(w) == 4 and w.recovered_bytes == 0
        assert w.append(messages[0]) == 4
    assert len(list(iter_messages(path))) == 5


def test_concurrent_appends_are_all_recorded_whole(tmp_path, messages):
    path = tmp_path / "r.vxr"
    w = RecordingWriter(path)
    threads = [threading.Thread(target=lambda m=m: [w.append(m) for _ in range(5)]) for m in messages]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    w.close()
    got = list(iter_messages(path))
    assert len(got) == 20
    assert sorted(got) == sorted(messages * 5)


@pytest.mark.parametrize("cut", [1, 5, 9, 200])
def test_torn_tail_is_detected_and_truncated(tmp_path, messages, cut):
    path = tmp_path / RECORDING_FILENAME
    with RecordingWriter(path) as w:
        for m in messages[:3]:
            w.append(m)
    good_size = path.stat().st_size
    with RecordingWriter(path) as w:
        w.append(messages[3])
    # simulate kill -9 in the middle of the 4th append: only its first bytes reached the disk
    with open(path, "r+b") as f:
        f.truncate(good_size + cut)
    assert scan_recording(path).torn_bytes == cut
    assert len(RecordingCapture(path)) == 3  # readers skip the torn tail without modifying the file
    assert path.stat().st_size == good_size + cut
    w = RecordingWriter(path)
    assert w.recovered_bytes == cut and len(w) == 3
    assert path.stat().st_size == good_size
    assert w.append(messages[3]) == 3
    w.close()
    assert list(iter_messages(path)) == messages


def test_last_record_with_bad_crc_is_torn_but_a_middle_one_is_corruption(tmp_path, messages):
    path = tmp_path / "r.vxr"
    with RecordingWriter(path) as w:
        for m in messages:
            w.append(m)
    scan = scan_recording(path)
    data = bytearray(path.read_bytes())
    last = scan.offsets[-1] + 40
    data[last] ^= 0xFF
    path.write_bytes(bytes(data))
    assert len(scan_recording(path).offsets) == 3
    data[last] ^= 0xFF
    data[scan.offsets[1] + 40] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CaptureError, match="corrupt"):
        scan_recording(path)
    with pytest.raises(CaptureError, match="corrupt"):
        RecordingWriter(path)


def test_not_a_recording(tmp_path):
    bad = tmp_path / "x.vxr"
    bad.write_bytes(b"NOTAREC!" + struct.pack("<II", 1, 0))
    with pytest.raises(CaptureFormatError, match="not a voxfusion recording"):
        scan_recording(bad)
    with pytest.raises(CaptureFormatError, match="no recording"):
        RecordingCapture(tmp_path / "missing")
    assert find_recording(tmp_path) == bad


def test_recording_capture_replays_the_frames(tmp_path, frames, messages):
    folder = tmp_path / "session"
    with RecordingWriter(folder / RECORDING_FILENAME) as w:
        for m in messages:
            w.append(m)
    cap = RecordingCapture(folder)
    assert len(cap) == len(frames) and cap.name == "session"
    assert cap.seqs() == [10, 11, 12, 13]
    for i, (got, want) in enumerate(zip(cap.frames(), frames, strict=True)):
        assert got.index == i and got.meta["seq"] == 10 + i and got.meta["session"] == "s"
        np.testing.assert_array_equal(got.depth_m, want.depth_m)
        np.testing.assert_allclose(got.K, want.K)
        assert got.timestamp_s == pytest.approx(want.timestamp_s)
        assert got.T_world_cam is None  # recordings carry no reference pose
    assert cap[-1].index == 3


def test_reader_follows_a_growing_recording_without_copies(tmp_path, messages):
    path = tmp_path / "rec.vxr"
    writer = RecordingWriter(path)
    reader = RecordingReader(path)
    with pytest.raises(CaptureError, match="not in the file yet"):
        reader.next()  # nothing appended: a clear error, the position unchanged
    views = []
    for i, m in enumerate(messages):
        writer.append(m)
        view = reader.next()  # the file grew since the reader mapped it
        assert isinstance(view, memoryview) and view.readonly and reader.index == i + 1
        views.append(view)
    reader.close()
    writer.close()
    assert [bytes(v) for v in views] == messages  # views stay readable after close and remaps
    assert decode_frame(views[1]).seq == 11  # frames decode straight from the mapping


def test_reader_refuses_a_corrupt_record(tmp_path, messages):
    path = tmp_path / "rec.vxr"
    with RecordingWriter(path) as writer:
        for m in messages[:2]:
            writer.append(m)
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF  # a byte of the second message
    path.write_bytes(bytes(data))
    with RecordingReader(path) as reader:
        assert bytes(reader.next()) == messages[0]
        with pytest.raises(CaptureError, match=r"record 1 .* \(CRC mismatch\)"):
            reader.next()
    with pytest.raises(CaptureError, match="not found"):
        RecordingReader(tmp_path / "missing.vxr")
    (tmp_path / "not.vxr").write_bytes(b"NOTAVXR0" + bytes(8))
    with pytest.raises(CaptureFormatError, match="not a voxfusion recording"):
        RecordingReader(tmp_path / "not.vxr")
