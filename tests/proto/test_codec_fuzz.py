"""Property tests: whatever bytes arrive, ``decode_frame`` returns a valid frame or raises ``FrameDecodeError``.

Any other exception (IndexError, struct.error, cv2.error, ZstdError, KeyError, TypeError, MemoryError...)
fails these tests. Messages with the CRC recomputed after a mutation reach the header and payload checks
(without it, the CRC catches every mutation first).
"""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.geometry import make_intrinsics
from voxfusion.proto import MAGIC, DecodedFrame, FrameDecodeError, WireIntrinsics, decode_frame, encode_frame
from voxfusion.proto.container import CRC_SIZE, PRELUDE_SIZE, unpack_message

FUZZ = settings(max_examples=200, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _frame(seed: int, w: int = 8, h: int = 6) -> RGBDFrame:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.3, 5.0, size=(h, w)).astype(np.float32)
    depth[0, 0] = 0.0
    T = np.eye(4)
    T[:3, 3] = rng.normal(size=3)
    return RGBDFrame(depth_m=depth, K=make_intrinsics(8.0, 8.0, (w - 1) / 2, (h - 1) / 2), timestamp_s=float(seed),
                     color=rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8),
                     confidence=rng.integers(0, 3, size=(h, w), dtype=np.uint8), T_world_cam_device=T)


def _messages() -> list[bytes]:
    out = []
    combos = [("png16_mm", "png", "png8"), ("zstd_u16_mm", "jpeg", "zstd_u8"), ("zstd_f16_m", "raw_rgb8", "raw_u8"),
              ("raw_f32_m", None, None)]
    for i, (dep, col, conf) in enumerate(combos):
        out.append(encode_frame(_frame(i), seq=i, session=f"s{i}", depth_encoding=dep, color_encoding=col,
                                confidence_encoding=conf))
    big = np.random.default_rng(9).integers(0, 256, size=(12, 16, 3), dtype=np.uint8)
    out.append(encode_frame(_frame(5), seq=5, color=big, color_encoding="jpeg",
                            intrinsics=WireIntrinsics(64.0, 64.0, 31.5, 23.5, 64, 48)))
    out.append(encode_frame(_frame(6), seq=6, device_pose=np.eye(4), device_pose_convention="arkit",
                            depth_encoding="png16_mm", color=big, color_encoding="png"))
    return out


MESSAGES = _messages()
MESSAGE = st.sampled_from(MESSAGES)


def _check(data: bytes) -> DecodedFrame | None:
    """Decode; a FrameDecodeError is fine, a returned frame must satisfy the RGBDFrame contract."""
    try:
        d = decode_frame(data)
    except FrameDecodeError as e:
        assert e.field in ("magic", "version", "flags", "length", "crc", "header", "intrinsics", "depth", "color",
                           "confidence", "device_pose")
        return None
    f = d.frame
    assert f.depth_m.dtype == np.float32 and np.all(np.isfinite(f.depth_m)) and np.all(f.depth_m >= 0)
    assert np.all(np.isfinite(f.K)) and f.K[0, 0] > 0 and f.K[1, 1] > 0
    if f.color is not None:
        assert f.color.shape == (*f.depth_m.shape, 3)
    if f.confidence is not None:
        assert f.confidence.max(initial=0) <= 2
    return d


def _reseal(body: bytes) -> bytes:
    """Replace the CRC trailer with the right one for ``body`` (the message without its last 4 bytes)."""
    return body + struct.pack("<I", zlib.crc32(body))


@FUZZ
@given(st.binary(max_size=600))
def test_random_bytes(data):
    assert _check(data) is None


@FUZZ
@given(st.binary(max_size=600), st.integers(0, 3))
def test_random_bytes_behind_a_valid_prelude_start(tail, version):
    assert _check(MAGIC + struct.pack("<HH", version, 0) + tail) is None


@FUZZ
@given(MESSAGE, st.data())
def test_truncated_messages(msg, data):
    cut = data.draw(st.integers(0, len(msg) - 1))
    assert _check(msg[:cut]) is None


@FUZZ
@given(MESSAGE, st.data(), st.integers(1, 255))
def test_single_byte_mutations_are_always_detected(msg, data, xor):
    pos = data.draw(st.integers(0, len(msg) - 1))
    mutated = bytearray(msg)
    mutated[pos] ^= xor
    assert _check(bytes(mutated)) is None  # CRC-32 detects every single-byte error


@FUZZ
@given(MESSAGE, st.data(), st.integers(0, 255))
def test_single_byte_mutations_with_a_valid_crc(msg, data, value):
    pos = data.draw(st.integers(0, len(msg) - CRC_SIZE - 1))
    mutated = bytearray(msg[:-CRC_SIZE])
    mutated[pos] = value
    _check(_reseal(bytes(mutated)))


@FUZZ
@given(MESSAGE, st.data())
def test_payload_byte_mutations_with_a_valid_crc(msg, data):
    """Corrupt PNG / JPEG / zstd / raw payloads in several places at once."""
    header_len = struct.unpack_from("<I", msg, 8)[0]
    start = PRELUDE_SIZE + header_len
    stop = len(msg) - CRC_SIZE
    body = bytearray(msg[:-CRC_SIZE])
    for _ in range(data.draw(st.integers(1, 8))):
        body[data.draw(st.integers(start, stop - 1))] = data.draw(st.integers(0, 255))
    _check(_reseal(bytes(body)))


JSON_SCALAR = (st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False)
               | st.text(max_size=12) | st.sampled_from(["png16_mm", "zstd_u16_mm", "jpeg", "raw_u8", "0-255",
                                                         "arkit", "row-major-c2w", "mm", "m"]))
JSON_VALUE = st.recursive(JSON_SCALAR, lambda c: st.lists(c, max_size=17) | st.dictionaries(st.text(max_size=8), c,
                                                                                            max_size=5),
                          max_leaves=20)
HEADER_PATHS = ["seq", "session", "timestamp_s", "intrinsics", "intrinsics.fx", "intrinsics.fy", "intrinsics.cx",
                "intrinsics.cy", "intrinsics.width", "intrinsics.height", "depth", "depth.encoding", "depth.units",
                "depth.width", "depth.height", "color", "color.encoding", "color.width", "color.height", "confidence",
                "confidence.encoding", "confidence.levels", "device_pose", "device_pose.convention",
                "device_pose.layout", "device_pose.matrix", "device_pose.matrix.3", "device_pose.matrix.0"]


def _pack(header: dict, msg: bytes) -> bytes:
    _, p = unpack_message(msg)
    hb = json.dumps(header).replace("Infinity", "1e999").encode()  # -Infinity becomes -1e999
    body = struct.pack("<4sHHIIII", MAGIC, 1, 0, len(hb), len(p.color), len(p.depth), len(p.confidence))
    return _reseal(body + hb + p.color + p.depth + p.confidence)


@FUZZ
@given(MESSAGE, st.lists(st.tuples(st.sampled_from(HEADER_PATHS), st.booleans(), JSON_VALUE), min_size=1, max_size=3))
def test_header_value_mutations(msg, edits):
    header, _ = unpack_message(msg)
    for path, delete, value in edits:
        node = header
        keys = path.split(".")
        for k in keys[:-1]:
            # an earlier edit may have replaced a parent with another type: then the path leads nowhere
            node = node.get(k) if isinstance(node, dict) else (
                node[int(k)] if isinstance(node, list) and k.isdigit() and int(k) < len(node) else None)
        last = keys[-1]
        if isinstance(node, dict):
            if delete:
                node.pop(last, None)
            else:
                node[last] = value
        elif isinstance(node, list) and last.isdigit() and int(last) < len(node):
            node[int(last)] = value
    _check(_pack(header, msg))


@FUZZ
@given(MESSAGE, st.sampled_from(["color", "depth", "confidence"]), st.binary(max_size=300))
def test_random_payloads_under_a_valid_header(msg, which, payload):
    header, p = unpack_message(msg)
    p = p._replace(**{which: payload})
    hb = json.dumps(header).encode()
    body = struct.pack("<4sHHIIII", MAGIC, 1, 0, len(hb), len(p.color), len(p.depth), len(p.confidence))
    _check(_reseal(body + hb + p.color + p.depth + p.confidence))


def test_fuzz_messages_are_valid():
    """The seeds above decode (so the mutations start from valid messages)."""
    for msg in MESSAGES:
        assert _check(msg) is not None
