"""Images that declare huge sizes (decompression bombs) or are cut short, in every image part of a multipart
frame (depth PNG, colour JPEG / PNG, confidence PNG) and in a binary frame message: each is a JSON 4xx naming
the part (413 for a huge declared size, 400 for a truncated or corrupt image), nothing is recorded, and the
session keeps taking frames."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
import zstandard
from srvutil import FAST, jpeg, make_scene, png

from voxfusion.proto import read_header
from voxfusion.proto.container import Payloads, pack_message
from voxfusion.proto.recording import RecordingCapture

W, H = 96, 72


def png_header_only(width: int, height: int, bit_depth: int = 16, colour_type: int = 0) -> bytes:
    """A PNG whose IHDR declares ``width`` x ``height`` but whose pixel data is (almost) nothing."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def jpeg_claiming(data: bytes, width: int, height: int) -> bytes:
    """``data`` (a baseline JPEG) with its SOF0 segment rewritten to declare ``width`` x ``height``."""
    i = data.index(b"\xff\xc0")
    return data[:i + 5] + struct.pack(">HH", height, width) + data[i + 9:]


@pytest.fixture(scope="module")
def scene():
    return make_scene(2, seed=5, width=W, height=H)


@pytest.fixture
def session(server_factory):
    srv = server_factory()
    sid, token = srv.api.create("bombs", config=FAST)
    return srv, sid, token


def check(r, status: int, field: str, *words: str) -> None:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json"), r.headers
    body = r.json()
    assert set(body) == {"detail", "field"} and body["field"] == field, body
    for w in words:
        assert w.lower() in body["detail"].lower(), body


def test_multipart_bombs_and_truncated_images_are_clean_4xx(session, scene):
    srv, sid, token = session
    api = srv.api
    frame = scene.capture[0]
    K = frame.K
    meta = {"seq": 0, "timestamp_s": 0.0, "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
                                                         "cy": K[1, 2], "width": W, "height": H}}
    depth_png = png(np.round(frame.depth_m * 1000).astype(np.uint16))
    color_jpg = jpeg(frame.color)
    color_png = png(frame.color[:, :, ::-1].copy())
    conf_png = png(np.full((H, W), 2, np.uint8))
    next_seq = iter(range(100, 1000))

    def post(files: dict, **extra) -> object:
        m = {**meta, "seq": next(next_seq), **extra}
        return api.http.post(f"/sessions/{sid}/frames", headers=api.auth(token), data={"metadata": json.dumps(m)},
                             files=files)

    def good() -> None:
        r = post({"depth": ("d.png", depth_png, "image/png"), "color": ("c.jpg", color_jpg, "image/jpeg"),
                  "confidence": ("q.png", conf_png, "image/png")})
        assert r.status_code == 202, r.text

    good()
    depth = ("d.png", depth_png, "image/png")
    zstd_bomb = zstandard.ZstdCompressor(level=1).compress(bytes(2 * 8192 * 6144))  # 96 MiB of zeros, ~3 KiB
    cases = [
        # depth: the reported 30000x30000 PNG (a plain-text 500 before), one under Pillow's bomb limit but over
        # the server's, a zstd payload that would inflate past the server's limit, truncated / cut headers
        ({"depth": ("d.png", png_header_only(30000, 30000), "image/png")}, {}, 413, "depth", "too large"),
        ({"depth": ("d.png", png_header_only(10000, 7500), "image/png")}, {}, 413, "depth", "10000x7500"),
        ({"depth": ("d.zst", zstd_bomb, "application/octet-stream")},
         {"depth_encoding": "zstd_u16_mm", "depth_width": 8192, "depth_height": 6144}, 413, "depth", "8192x6144"),
        ({"depth": ("d.png", depth_png[:len(depth_png) // 2], "image/png")}, {}, 400, "depth", "png"),
        ({"depth": ("d.png", depth_png[:20], "image/png")}, {}, 400, "depth", "png"),
        # colour: JPEG / PNG headers declaring huge sizes, truncated JPEG / PNG
        ({"depth": depth, "color": ("c.jpg", jpeg_claiming(color_jpg, 30000, 22500), "image/jpeg")}, {}, 413,
         "color", "too large"),
        ({"depth": depth, "color": ("c.png", png_header_only(40000, 30000, 8, 2), "image/png")}, {}, 413,
         "color", "too large"),
        ({"depth": depth, "color": ("c.jpg", jpeg_claiming(color_jpg, 9600, 7200), "image/jpeg")}, {}, 413,
         "color", "9600x7200"),
        ({"depth": depth, "color": ("c.jpg", color_jpg[:len(color_jpg) // 2], "image/jpeg")}, {}, 400, "color",
         "jpeg"),
        ({"depth": depth, "color": ("c.png", color_png[:len(color_png) // 2], "image/png")}, {}, 400, "color",
         "png"),
        ({"depth": depth, "color": ("c.jpg", color_jpg[:10], "image/jpeg")}, {}, 400, "color", "jpeg"),
        # confidence: a bomb header, a truncated PNG at the depth's size
        ({"depth": depth, "confidence": ("q.png", png_header_only(30000, 30000, 8), "image/png")}, {}, 413,
         "confidence", "too large"),
        ({"depth": depth, "confidence": ("q.png", conf_png[:len(conf_png) // 2], "image/png")}, {}, 400,
         "confidence", "png"),
    ]
    for files, extra, status, field, words in cases:
        check(post(files, **extra), status, field, words)
        good()
    st = api.status(sid, token)
    assert st["state"] == "running" and st["last_error"] is None
    assert st["frames_received"] == len(cases) + 1  # only the good frames were recorded
    assert len(RecordingCapture(srv.settings.sessions_dir / sid).seqs()) == len(cases) + 1


def test_binary_message_with_a_bomb_image_is_400(session, scene):
    """The binary body's images are checked against the header's sizes before they are decoded."""
    srv, sid, token = session
    api = srv.api
    msg = scene.messages[0]
    hdr = dict(read_header(msg).raw)
    frame = scene.capture[0]
    pl = Payloads(color=jpeg(frame.color), depth=png((frame.depth_m * 1000).astype(np.uint16)), confidence=b"")
    cases = [
        (pack_message(hdr, pl._replace(depth=png_header_only(30000, 30000))), "depth"),
        (pack_message(hdr, pl._replace(color=jpeg_claiming(pl.color, 30000, 22500))), "color"),
        (pack_message(hdr, pl._replace(depth=pl.depth[:len(pl.depth) // 2])), "depth"),
        (pack_message(hdr, pl._replace(color=pl.color[:len(pl.color) // 2])), "color"),
    ]
    for i, (data, field) in enumerate(cases):
        check(api.post_frame(sid, token, data), 400, field)
        r = api.post_frame(sid, token, scene.messages[i % 2])
        assert r.status_code == 202, r.text
    assert api.status(sid, token)["state"] == "running"
