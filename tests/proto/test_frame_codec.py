"""Round trips and error cases of the frame container (proto/README.md is the spec under test)."""

from __future__ import annotations

import json
import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import zstandard
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.errors import ValidationError, VoxFusionError
from voxfusion.core.geometry import make_intrinsics, opencv_to_opengl, opengl_to_opencv, scale_intrinsics
from voxfusion.proto import (
    DEPTH_ENCODINGS,
    ERROR_FIELDS,
    MAGIC,
    DecodedFrame,
    DecodeLimits,
    FrameDecodeError,
    WireIntrinsics,
    decode_frame,
    encode_frame,
    read_header,
)
from voxfusion.proto.container import PRELUDE_SIZE, Payloads, pack_message, unpack_message

REPO_ROOT = Path(__file__).resolve().parents[2]
W, H = 32, 24


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def _frame(seed: int = 0, w: int = W, h: int = H, color: bool = True, confidence: bool = True,
           pose: bool = True) -> RGBDFrame:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.2, 9.0, size=(h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.1] = 0.0
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rgb = np.stack([u * 255 // max(w - 1, 1), v * 255 // max(h - 1, 1), (u + v) * 4 % 256], -1).astype(np.uint8)
    return RGBDFrame(
        depth_m=depth, K=make_intrinsics(0.9 * w, 0.85 * w, (w - 1) / 2, (h - 1) / 2), timestamp_s=12.345678,
        color=rgb if color else None,
        confidence=rng.integers(0, 3, size=(h, w), dtype=np.uint8) if confidence else None,
        T_world_cam_device=_pose(seed) if pose else None,
    )


def _pack(header: bytes, color: bytes = b"", depth: bytes = b"\x00\x00", confidence: bytes = b"") -> bytes:
    """Build a message by hand from the README's layout (independent of ``pack_message``)."""
    body = struct.pack("<4sHHIIII", b"VXFR", 1, 0, len(header), len(color), len(depth), len(confidence))
    body += header + color + depth + confidence
    return body + struct.pack("<I", zlib.crc32(body))


def _rebuild(data: bytes, edit_header=None, **payloads: bytes) -> bytes:
    """Re-pack a valid message with an edited header and/or replaced payloads (CRC recomputed).

    Infinite floats in the edited header are written as ``1e999`` (valid JSON that parses to inf).
    """
    header, p = unpack_message(data)
    if edit_header is not None:
        edit_header(header)
    p = p._replace(**payloads)
    header_bytes = json.dumps(header).replace("Infinity", "1e999").encode()
    return _pack(header_bytes, p.color, p.depth, p.confidence)


def _decode_error(data: bytes, field: str, **kw) -> FrameDecodeError:
    with pytest.raises(FrameDecodeError) as info:
        decode_frame(data, **kw)
    assert info.value.field == field, f"{info.value.field}: {info.value.problem}"
    assert info.value.field in ERROR_FIELDS
    return info.value


# ------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("encoding", DEPTH_ENCODINGS)
def test_depth_round_trip(encoding):
    f = _frame(1)
    out = decode_frame(encode_frame(f, seq=0, depth_encoding=encoding)).frame
    assert out.depth_m.dtype == np.float32 and out.depth_m.shape == (H, W)
    np.testing.assert_array_equal(out.depth_m == 0, f.depth_m == 0)  # invalid stays invalid, valid stays valid
    err = np.abs(out.depth_m - f.depth_m)
    if encoding.endswith("_mm"):
        assert err.max() <= 0.5e-3 + 1e-6  # 1 mm quantisation
        assert err.max() > 0  # and it does quantise (the test would notice an accidental float path)
    elif encoding == "zstd_f16_m":
        valid = f.depth_m > 0
        assert (err[valid] / f.depth_m[valid]).max() <= 1e-3
    else:
        np.testing.assert_array_equal(out.depth_m, f.depth_m)


@pytest.mark.parametrize("encoding", DEPTH_ENCODINGS)
def test_depth_out_of_range_values_are_sent_as_invalid(encoding):
    f = _frame(2)
    d = f.depth_m.copy()
    d[0, :4] = [np.nan, np.inf, -1.0, 70000.0]
    d[1, 0] = 70.0  # beyond the mm encodings' 65.535 m
    out = decode_frame(encode_frame(f.with_(depth_m=d), seq=0, depth_encoding=encoding)).frame.depth_m
    assert np.all(out[0, :3] == 0)  # NaN, inf, negative
    assert np.all(np.isfinite(out))
    assert out[0, 3] == (70000.0 if encoding == "raw_f32_m" else 0.0)  # beyond float16 and mm range
    assert out[1, 0] == (0.0 if encoding.endswith("_mm") else 70.0)


@pytest.mark.parametrize("encoding", ["raw_rgb8", "png"])
def test_lossless_color_round_trip(encoding):
    f = _frame(3)
    rng = np.random.default_rng(3)
    noisy = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)  # lossless must survive pure noise
    out = decode_frame(encode_frame(f.with_(color=noisy), seq=0, color_encoding=encoding)).frame
    np.testing.assert_array_equal(out.color, noisy)


def test_jpeg_color_round_trip_is_close_and_keeps_channel_order():
    from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig

    f = SyntheticCapture(SyntheticConfig(n_frames=2, width=320, height=240))[1]  # smaller: all texture edges
    out = decode_frame(encode_frame(f, seq=0, color_encoding="jpeg", jpeg_quality=95)).frame
    err = np.abs(out.color.astype(np.int16) - f.color.astype(np.int16))
    assert err.mean() < 4.0
    # a swapped R/B would be far worse than compression noise on a coloured scene
    swapped = np.abs(out.color[..., ::-1].astype(np.int16) - f.color.astype(np.int16)).mean()
    assert swapped > 2 * err.mean()
    solid = f.with_(color=np.full((240, 320, 3), (200, 30, 90), np.uint8))
    got = decode_frame(encode_frame(solid, seq=0, jpeg_quality=90)).frame.color
    assert np.abs(got.reshape(-1, 3).mean(0) - (200, 30, 90)).max() < 3


def test_colour_and_confidence_can_be_absent():
    data = encode_frame(_frame(4, color=False, confidence=False, pose=False), seq=5)
    d = decode_frame(data)
    assert d.frame.color is None and d.frame.confidence is None and d.frame.T_world_cam_device is None
    assert d.header["color"] is None and d.header["confidence"] is None and d.header["device_pose"] is None
    # color_encoding=None drops colour even when the frame has it
    d = decode_frame(encode_frame(_frame(4), seq=5, color_encoding=None, confidence_encoding=None))
    assert d.frame.color is None and d.frame.confidence is None


@pytest.mark.parametrize("encoding", ["raw_u8", "zstd_u8", "png8"])
def test_confidence_round_trip(encoding):
    f = _frame(5)
    out = decode_frame(encode_frame(f, seq=0, confidence_encoding=encoding)).frame
    np.testing.assert_array_equal(out.confidence, f.confidence)
    assert out.confidence.dtype == np.uint8


def test_confidence_0_255_levels_map_to_0_1_2():
    f = _frame(6)
    polycam = np.array([0, 127, 255], np.uint8)[f.confidence]

    def to_255(h):
        h["confidence"] = {"encoding": "raw_u8", "levels": "0-255"}

    data = _rebuild(encode_frame(f, seq=0), to_255, confidence=polycam.tobytes())
    np.testing.assert_array_equal(decode_frame(data).frame.confidence, f.confidence)


def test_opencv_device_pose_round_trip():
    f = _frame(7)
    d = decode_frame(encode_frame(f, seq=0))
    assert d.header["device_pose"]["convention"] == "opencv"
    assert d.header["device_pose"]["layout"] == "row-major-c2w"
    np.testing.assert_array_equal(np.array(d.header["device_pose"]["matrix"]).reshape(4, 4), f.T_world_cam_device)
    np.testing.assert_allclose(d.frame.T_world_cam_device, f.T_world_cam_device, atol=1e-12)


def test_arkit_device_pose_is_converted_to_opencv():
    f = _frame(8, pose=False)
    T_gl = _pose(8)
    d = decode_frame(encode_frame(f, seq=0, device_pose=T_gl, device_pose_convention="arkit"))
    assert d.header["device_pose"]["convention"] == "arkit"
    np.testing.assert_allclose(d.frame.T_world_cam_device, opengl_to_opencv(T_gl), atol=1e-12)
    assert not np.allclose(d.frame.T_world_cam_device, T_gl, atol=1e-3)
    # a frame's (OpenCV) device pose sent in ARKit convention comes back unchanged
    g = _frame(9)
    d = decode_frame(encode_frame(g, seq=0, device_pose_convention="arkit"))
    np.testing.assert_allclose(np.array(d.header["device_pose"]["matrix"]).reshape(4, 4),
                               opencv_to_opengl(g.T_world_cam_device), atol=1e-12)
    np.testing.assert_allclose(d.frame.T_world_cam_device, g.T_world_cam_device, atol=1e-12)


@pytest.mark.parametrize("encoding", ["raw_rgb8", "png", "jpeg"])
def test_colour_at_another_resolution_is_resized_to_depth(encoding):
    f = _frame(10, w=32, h=24)
    rng = np.random.default_rng(10)
    big = cv2.resize(rng.integers(0, 256, size=(3, 4, 3), dtype=np.uint8), (80, 60), interpolation=cv2.INTER_LINEAR)
    d = decode_frame(encode_frame(f, seq=0, color=big, color_encoding=encoding, jpeg_quality=100))
    assert d.header["color"]["width"] == 80 and d.header["color"]["height"] == 60
    assert d.frame.color.shape == (24, 32, 3)
    expected = cv2.resize(big, (32, 24), interpolation=cv2.INTER_AREA)
    tol = 0 if encoding != "jpeg" else 3
    assert np.abs(d.frame.color.astype(int) - expected).mean() <= tol
    np.testing.assert_allclose(d.frame.K, f.K)  # intrinsics were for the depth: unchanged


def test_intrinsics_for_colour_resolution_are_scaled_to_depth():
    f = _frame(11, w=256, h=192, confidence=False)
    arkit = WireIntrinsics(fx=1450.0, fy=1452.0, cx=959.5, cy=719.5, width=1920, height=1440)
    d = decode_frame(encode_frame(f, seq=0, intrinsics=arkit))
    s = 256 / 1920
    np.testing.assert_allclose(d.frame.K, [[1450 * s, 0, 959.5 * s], [0, 1452 * s, 719.5 * s], [0, 0, 1]])
    np.testing.assert_allclose(d.frame.K, scale_intrinsics(arkit.K, (1920, 1440), (256, 192)))
    assert d.header["intrinsics"] == {"fx": 1450.0, "fy": 1452.0, "cx": 959.5, "cy": 719.5, "width": 1920,
                                      "height": 1440}


def test_session_seq_timestamp_are_preserved():
    f = _frame(12)
    data = encode_frame(f, seq=2**40 + 3, session="desk-01")
    d = decode_frame(data)
    assert isinstance(d, DecodedFrame)
    assert (d.seq, d.session, d.frame.index) == (2**40 + 3, "desk-01", 2**40 + 3)
    assert d.frame.timestamp_s == f.timestamp_s
    assert decode_frame(encode_frame(f, seq=0)).session is None
    h = read_header(data)
    assert (h.seq, h.session, h.depth_encoding, h.color_encoding) == (2**40 + 3, "desk-01", "zstd_u16_mm", "jpeg")
    assert data.startswith(MAGIC)
    assert struct.unpack_from("<I", data, len(data) - 4)[0] == zlib.crc32(data[:-4])


def test_accepts_bytearray_and_memoryview_and_refuses_other_types():
    data = encode_frame(_frame(13), seq=1)
    for buf in (bytearray(data), memoryview(data)):
        assert decode_frame(buf).seq == 1
    with pytest.raises(TypeError):
        decode_frame("not bytes")  # type: ignore[arg-type]


def test_real_stray_frame_round_trips_exactly_in_millimetres(shared_data):
    from voxfusion.core.datasets.stray import StrayCapture

    cap = StrayCapture(shared_data / "stray_iphone_lidar")
    f = cap[10]
    for enc in ("png16_mm", "zstd_u16_mm"):
        out = decode_frame(encode_frame(f, seq=10, depth_encoding=enc)).frame
        np.testing.assert_array_equal(np.rint(out.depth_m * 1000), np.rint(f.depth_m * 1000))
        np.testing.assert_array_equal(out.confidence, f.confidence)
        np.testing.assert_allclose(out.T_world_cam_device, f.T_world_cam_device, atol=1e-12)


def test_readme_worked_example_decodes():
    """The hex dump in proto/README.md is a real message: parse it and check what the README says it holds."""
    text = (REPO_ROOT / "proto" / "README.md").read_text()
    block = text.split("<!-- hexdump:begin -->", 1)[1].split("<!-- hexdump:end -->", 1)[0]
    hex_bytes = "".join("".join(re.findall(r"\b[0-9a-f]{2}\b", line.split("|")[0][10:]))
                        for line in block.splitlines() if re.match(r"^[0-9a-f]{8}  ", line))
    d = decode_frame(bytes.fromhex(hex_bytes))
    assert (d.seq, d.session, d.frame.timestamp_s) == (7, "demo", 0.5)
    np.testing.assert_array_equal(d.frame.depth_m, [[1.0, 1.5], [0.0, 2.25]])
    np.testing.assert_array_equal(d.frame.confidence, [[2, 1], [0, 2]])
    assert d.frame.color is None


def test_readme_example_header_is_valid():
    text = (REPO_ROOT / "proto" / "README.md").read_text()
    header = json.loads(text.split("```json", 1)[1].split("```", 1)[0])
    h = read_header(_pack(json.dumps(header).encode(), color=b"\xff", depth=b"\x00", confidence=b"\x00"))
    assert (h.seq, h.session, h.depth_width, h.color_width, h.intrinsics.width) == (42, "a1b2c3", 256, 640, 1920)
    assert h.device_pose_convention == "arkit"
    np.testing.assert_allclose(h.device_pose, opengl_to_opencv(np.array(header["device_pose"]["matrix"]).reshape(4, 4)))


# ------------------------------------------------------------------------------------------ errors


def test_error_type_is_a_validation_error():
    err = _decode_error(b"nope", "magic")
    assert isinstance(err, ValidationError) and isinstance(err, VoxFusionError) and isinstance(err, ValueError)


def _set(path: str, value):
    def edit(h):
        node = h
        keys = path.split(".")
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value
    return edit


def _delete(path: str):
    def edit(h):
        node = h
        keys = path.split(".")
        for k in keys[:-1]:
            node = node[k]
        del node[keys[-1]]
    return edit


HEADER_ERRORS = [
    ("missing seq", _delete("seq"), "header"),
    ("negative seq", _set("seq", -1), "header"),
    ("bool seq", _set("seq", True), "header"),
    ("string timestamp", _set("timestamp_s", "now"), "header"),
    ("empty session", _set("session", ""), "header"),
    ("numeric session", _set("session", 5), "header"),
    ("missing depth", _delete("depth"), "depth"),
    ("unknown depth encoding", _set("depth.encoding", "exr"), "depth"),
    ("depth units disagree", _set("depth.units", "m"), "depth"),
    ("zero depth width", _set("depth.width", 0), "depth"),
    ("oversize depth", _set("depth.width", 5000), "depth"),
    ("missing intrinsics", _delete("intrinsics"), "intrinsics"),
    ("zero fx", _set("intrinsics.fx", 0), "intrinsics"),
    ("negative fy", _set("intrinsics.fy", -10.0), "intrinsics"),
    ("infinite cx", _set("intrinsics.cx", float("inf")), "intrinsics"),
    ("principal point outside", _set("intrinsics.cx", 40.0), "intrinsics"),
    ("intrinsics for another aspect", _set("intrinsics.width", 64), "intrinsics"),
    ("unknown colour encoding", _set("color.encoding", "webp"), "color"),
    ("colour of another aspect", _set("color.height", 30), "color"),
    ("colour header null with payload", _set("color", None), "color"),
    ("colour not an object", _set("color", [1, 2]), "color"),
    ("unknown confidence encoding", _set("confidence.encoding", "bits"), "confidence"),
    ("unknown confidence levels", _set("confidence.levels", "0-1"), "confidence"),
    ("unknown convention", _set("device_pose.convention", "unity"), "device_pose"),
    ("unknown layout", _set("device_pose.layout", "column-major-c2w"), "device_pose"),
    ("15 numbers", _set("device_pose.matrix", [1.0] * 15), "device_pose"),
    ("scaled rotation", _set("device_pose.matrix", [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1]), "device_pose"),
    ("infinite translation", _set("device_pose.matrix", [1, 0, 0, float("inf"), 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
     "device_pose"),
    ("string in matrix", _set("device_pose.matrix", ["1"] * 16), "device_pose"),
]


@pytest.mark.parametrize("edit,field", [c[1:] for c in HEADER_ERRORS], ids=[c[0] for c in HEADER_ERRORS])
def test_bad_header_values_raise_with_the_field(edit, field):
    data = encode_frame(_frame(20), seq=3, color_encoding="raw_rgb8", confidence_encoding="raw_u8")
    _decode_error(_rebuild(data, edit), field)


def test_framing_errors():
    data = encode_frame(_frame(21), seq=3)
    _decode_error(b"", "length")
    _decode_error(b"VX", "length")
    _decode_error(b"PK\x03\x04" + data[4:], "magic")
    _decode_error(data[:4] + struct.pack("<H", 2) + data[6:], "version")
    _decode_error(data[:6] + struct.pack("<H", 1) + data[8:], "flags")
    _decode_error(data[:PRELUDE_SIZE], "length")
    _decode_error(data[:-1], "length")
    _decode_error(data + b"\x00", "length")
    corrupt = bytearray(data)
    corrupt[PRELUDE_SIZE + 40] ^= 0x01
    _decode_error(bytes(corrupt), "crc")


BAD_JSON = [b"{not json", b"[1, 2]", b"\xff\xfe{}", b'{"seq": NaN}', b"[" * 20000 + b"]" * 20000]


@pytest.mark.parametrize("header", BAD_JSON)
def test_bad_json_header(header):
    _decode_error(_pack(header), "header")


def test_header_size_limit():
    data = encode_frame(_frame(22), seq=0)
    _decode_error(data, "header", limits=DecodeLimits(max_header_bytes=100))
    _decode_error(data, "depth", limits=DecodeLimits(max_width=16))
    _decode_error(_pack(b'{"seq":1}', depth=b""), "depth")


def test_payload_errors():
    f = _frame(23)
    raw = encode_frame(f, seq=0, depth_encoding="raw_f32_m", color_encoding="raw_rgb8", confidence_encoding="raw_u8")
    _decode_error(_rebuild(raw, depth=b"\x00" * (4 * W * H - 4)), "depth")
    _decode_error(_rebuild(raw, color=b"\x00" * (3 * W * H + 3)), "color")
    _decode_error(_rebuild(raw, confidence=b"\x00" * (W * H - 1)), "confidence")
    _decode_error(_rebuild(raw, confidence=b"\x03" * (W * H)), "confidence")  # levels 0-2 but a 3
    _decode_error(_rebuild(raw, confidence=b""), "confidence")  # header says present, payload absent

    png = encode_frame(f, seq=0, depth_encoding="png16_mm", color_encoding="png", confidence_encoding="png8")
    header, p = unpack_message(png)
    _decode_error(_rebuild(png, depth=p.depth[: len(p.depth) // 2]), "depth")  # truncated PNG
    _decode_error(_rebuild(png, depth=p.color), "depth")  # 8-bit RGB PNG where 16-bit grey is due
    _decode_error(_rebuild(png, depth=cv2.imencode(".png", np.zeros((H + 1, W), np.uint16))[1].tobytes()), "depth")
    _decode_error(_rebuild(png, color=cv2.imencode(".jpg", np.zeros((H, W, 3), np.uint8))[1].tobytes()), "color")
    _decode_error(_rebuild(png, color=b"\x89PNG\r\n\x1a\n" + b"\x00" * 50), "color")
    _decode_error(_rebuild(png, confidence=p.depth), "confidence")  # 16-bit where 8-bit is due

    z = encode_frame(f, seq=0, depth_encoding="zstd_u16_mm")
    _decode_error(_rebuild(z, depth=b"\x28\xb5\x2f\xfd garbage"), "depth")
    _decode_error(_rebuild(z, depth=b"not zstd at all"), "depth")
    small = zstandard.ZstdCompressor().compress(b"\x00" * (2 * W * H - 2))
    _decode_error(_rebuild(z, depth=small), "depth")
    jpeg = encode_frame(f, seq=0, color_encoding="jpeg")
    _decode_error(_rebuild(jpeg, color=b"\xff\xd8\xff\xe0" + b"\x00" * 30), "color")


def test_zstd_decompression_bomb_is_refused_before_allocation():
    z = encode_frame(_frame(24), seq=0, depth_encoding="zstd_u16_mm")
    bomb = zstandard.ZstdCompressor(level=1).compress(b"\x00" * (64 << 20))  # 64 MiB of zeros, ~2 KiB on the wire
    assert len(bomb) < 10_000
    err = _decode_error(_rebuild(z, depth=bomb), "depth")
    assert "holds" in err.problem
    # without a content size in the frame header the output is bounded by the declared size instead
    unsized = zstandard.ZstdCompressor(level=1, write_content_size=False).compress(b"\x00" * (64 << 20))
    _decode_error(_rebuild(z, depth=unsized), "depth")


def test_image_bomb_is_refused_from_its_header():
    png = encode_frame(_frame(25), seq=0, depth_encoding="png16_mm")
    big = cv2.imencode(".png", np.zeros((4000, 4000), np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()
    err = _decode_error(_rebuild(png, depth=big), "depth")
    assert "4000x4000" in err.problem


# ------------------------------------------------------------------------------------ encoder args


@pytest.mark.parametrize("kwargs,field", [
    ({"depth_encoding": "exr"}, "depth_encoding"),
    ({"color_encoding": "webp"}, "color_encoding"),
    ({"confidence_encoding": "bits"}, "confidence_encoding"),
    ({"jpeg_quality": 0}, "jpeg_quality"),
    ({"seq": -1}, "seq"),
    ({"seq": True}, "seq"),
    ({"session": ""}, "session"),
    ({"device_pose": np.diag([2.0, 2.0, 2.0, 1.0])}, "device_pose"),
    ({"device_pose_convention": "unity"}, "device_pose_convention"),
    ({"color": np.zeros((30, 32, 3), np.uint8)}, "color"),
    ({"intrinsics": WireIntrinsics(10.0, 10.0, 5.0, 5.0, 64, 64)}, "intrinsics"),
    ({"zstd_level": 99}, "zstd_level"),
])
def test_encoder_argument_errors(kwargs, field):
    kwargs = {"seq": 0, **kwargs}
    with pytest.raises(ValidationError) as info:
        encode_frame(_frame(26), **kwargs)
    assert info.value.field == field
    assert not isinstance(info.value, FrameDecodeError)


def test_header_is_compact_json_with_named_units():
    data = encode_frame(_frame(27), seq=9, session="s")
    (header_len,) = struct.unpack_from("<I", data, 8)
    header = json.loads(data[PRELUDE_SIZE : PRELUDE_SIZE + header_len])
    assert set(header) == {"session", "seq", "timestamp_s", "intrinsics", "depth", "color", "confidence",
                           "device_pose"}
    assert header["depth"] == {"encoding": "zstd_u16_mm", "units": "mm", "width": W, "height": H}
    assert header["color"] == {"encoding": "jpeg", "width": W, "height": H}
    assert header["confidence"] == {"encoding": "zstd_u8", "levels": "0-2"}
    # unknown keys are ignored (forward compatibility within version 1)
    d = decode_frame(_rebuild(data, _set("future_key", {"x": 1})))
    assert d.header["future_key"] == {"x": 1}


def test_pack_message_refuses_non_finite_header():
    with pytest.raises(ValidationError) as info:
        pack_message({"timestamp_s": float("nan")}, Payloads(b"", b"\x00", b""))
    assert info.value.field == "header"
